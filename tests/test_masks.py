"""``anisdf process-data --masks``: foreground masks of an object capture from GrabCut seeded by the sparse points and
the object's sphere, made consistent across views; a synthetic capture (an object in a papered room) is segmented
against its true silhouettes, and missing inputs are named."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scenes import ObjectCapture, write_object_capture

from anisdf.cli import main
from anisdf.data import load_scene
from anisdf.errors import AnisdfError, DataError

pytest.importorskip("cv2")

MIN_MEAN_IOU = 0.94
"""Measured 0.966 (every view >= 0.95) on this capture; maryrose reached 0.954 against its own masks."""


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> ObjectCapture:
    return write_object_capture(tmp_path_factory.mktemp("object_capture"))


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_masks_match_the_silhouettes_and_make_an_object_scene(capture: ObjectCapture, tmp_path: Path,
                                                               capsys) -> None:
    from anisdf.tasks.train import data_kind

    scene = tmp_path / "scene"
    shutil.copytree(capture.root, scene)
    assert data_kind(scene) == "unbounded"
    assert main(["process-data", str(scene), "--out", str(scene), "--masks", "--no-progress"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(out[: out.rindex("}") + 1])
    assert summary["masks"] == "masks/" and summary["sphere_method"] == "visual-hull"
    ious = [_iou(np.asarray(Image.open(scene / "masks" / f"view_{i:02d}.png")) >= 128, truth)
            for i, truth in enumerate(capture.truth_masks)]
    assert np.mean(ious) >= MIN_MEAN_IOU and min(ious) >= 0.9, np.round(ious, 3)

    meta = json.loads((scene / "transforms.json").read_text())
    assert all(f["mask_path"].startswith("masks/") for f in meta["frames"]) and "bounding_sphere" not in meta
    loaded = load_scene(scene)
    assert loaded.masks is not None and loaded.roi_method == "visual-hull"
    # the object (two spheres within 0.73 of the origin) fills the visual-hull sphere: tighter than SfM's 0.95
    assert 0.7 < loaded.scene_radius < 0.95 and np.linalg.norm(loaded.center) < 0.2
    assert data_kind(scene) == "object"
    assert (scene / "cameras.png").is_file()


def test_missing_inputs_are_named(capture: ObjectCapture, tmp_path: Path, capsys, monkeypatch) -> None:
    from anisdf.data.process import process_data

    scene = tmp_path / "scene"
    shutil.copytree(capture.root, scene)
    with pytest.raises(DataError, match="already a scene: --masks adds masks to it in place"):
        process_data(scene, tmp_path / "elsewhere", masks=True)
    (scene / "sparse_pc.ply").unlink()
    with pytest.raises(DataError, match="sparse_pc.ply: sparse points are missing"):
        process_data(scene, scene, masks=True, progress=False)
    meta = json.loads((capture.root / "transforms.json").read_text())
    del meta["bounding_sphere"]
    shutil.copy(capture.root / "sparse_pc.ply", scene / "sparse_pc.ply")
    (scene / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="has no bounding_sphere"):
        process_data(scene, scene, masks=True, progress=False)
    assert not (scene / "masks").exists()

    monkeypatch.setitem(sys.modules, "cv2", None)  # OpenCV not installed
    assert main(["process-data", str(scene), "--out", str(scene), "--masks"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'anisdf[masks]'" in err, err
    with pytest.raises(AnisdfError, match=r"needs OpenCV's GrabCut: pip install 'anisdf\[masks\]'"):
        process_data(scene, scene, masks=True)
