"""The user's region of interest (data.roi_center / data.roi_radius), what inspect says of it, and extract-mesh
--bbox: an automatic sphere that misses the object on purpose is put right by the override; bad spheres are refused
in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from scenes import write_test_scene
from test_training import TINY

from anisdf.cli import main
from anisdf.config import load_config
from anisdf.data import inspect_dataset, load_scene
from anisdf.errors import AnisdfError

CENTER = np.array([0.3, -0.2, 0.1])
OBJECT_RADIUS = 0.5


@pytest.fixture(scope="module")
def off_aim(tmp_path_factory) -> Path:
    """A COLMAP capture (no masks) whose cameras all look 1.2 units beside the object: the automatic sphere, from
    the camera rays, is centred where they look and holds only part of the object."""
    root = tmp_path_factory.mktemp("off_aim")
    write_test_scene(root, "colmap", n_images=8, width=32, height=24, center=tuple(CENTER),
                     sphere_radius=OBJECT_RADIUS, aim=tuple(CENTER + [1.2, 0.0, 0.0]))
    return root


def _object_reach(scene) -> float:
    """How far the object reaches from the origin of the normalised frame (the unit sphere must hold it: < 1)."""
    c = scene.to_normalised_frame(CENTER[None])[0]
    return float(np.linalg.norm(c) + OBJECT_RADIUS / scene.scale)


def test_override_fixes_a_wrong_automatic_sphere(off_aim: Path) -> None:
    auto = load_scene(off_aim)
    assert auto.roi_method == "camera-axes"
    assert _object_reach(auto) > 1.2  # the automatic sphere leaves part of the object out

    cfg = load_config(None, ["data.roi_center=0.3,-0.2,0.1", "data.roi_radius=0.75"])
    scene = load_scene(off_aim, roi_center=cfg.data.roi_center, roi_radius=cfg.data.roi_radius)
    assert scene.roi_method == "user"
    np.testing.assert_allclose(scene.center, CENTER, atol=1e-12)
    assert scene.scene_radius == pytest.approx(0.75) and scene.scale == pytest.approx(0.75)
    expected = np.diag([0.75, 0.75, 0.75, 1.0])
    expected[:3, 3] = CENTER
    np.testing.assert_allclose(scene.to_world, expected, atol=1e-12)
    # the cameras move by the same similarity: normalised centre = (centre - roi centre) / roi radius
    np.testing.assert_allclose(scene.cameras.centers.double().numpy(),
                               (auto.to_dataset_frame(auto.cameras.centers.double().numpy()) - CENTER) / 0.75,
                               atol=1e-5)
    assert _object_reach(scene) == pytest.approx(OBJECT_RADIUS / 0.75, abs=1e-9)  # < 1: inside

    # only the radius given: the automatic centre stays, and inspect says both
    half = inspect_dataset(off_aim, ["data.roi_radius=1.4"])
    assert half["roi"]["method"] == "user-radius+camera-axes" and half["roi"]["radius"] == 1.4
    np.testing.assert_allclose(half["roi"]["center"], auto.center, atol=1e-5)
    assert "radius given" in half["roi"]["found_from"] and "camera rays" in half["roi"]["found_from"]


def test_inspect_prints_and_draws_the_sphere(off_aim: Path, tmp_path: Path, capsys) -> None:
    picture = tmp_path / "cameras.png"
    assert main(["inspect", str(off_aim), "data.roi_center=0.3,-0.2,0.1", "data.roi_radius=0.75",
                 "--picture", str(picture)]) == 0
    out = capsys.readouterr()
    report = json.loads(out.out)
    assert report["roi"] == {"center": [0.3, -0.2, 0.1], "radius": 0.75, "method": "user",
                             "found_from": "the user's region of interest (data.roi_center, data.roi_radius)"}
    assert out.err.strip() == ("region of interest: centre (0.3, -0.2, 0.1), radius 0.75 (dataset frame), from the "
                               "user's region of interest (data.roi_center, data.roi_radius)")
    img = np.asarray(Image.open(picture).convert("RGB"))
    assert img.shape == (644, 1200, 3)
    red = (img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)
    blue = (img[..., 2] > 180) & (img[..., 0] < 60)
    assert red.sum() > 500 and blue.sum() > 100  # the sphere and the cameras are drawn

    assert main(["inspect", str(off_aim)]) == 0
    assert "from the camera rays" in capsys.readouterr().err


@pytest.mark.parametrize("overrides, message", [
    (["data.roi_radius=-1"], "data.roi_radius must be a positive number"),
    (["data.roi_center=1,2"], "data.roi_center needs three numbers x,y,z"),
    (["data.roi_center=0.3,-0.2,0.1", "data.roi_radius=3"], "holds 8 of 8 cameras"),
    (["data.roi_center=0.3,-0.2,60", "data.roi_radius=1"], "is in the view of none of the 8 cameras"),
    (["train.lr=3"], "inspect reads data.* settings only"),
])
def test_bad_regions_are_refused_in_one_line(off_aim: Path, capsys, overrides: list[str], message: str) -> None:
    assert main(["inspect", str(off_aim), *overrides]) == 2
    err = capsys.readouterr().err
    assert err.startswith("anisdf: error:") and err.count("\n") == 1 and message in err, err


def test_train_reads_the_roi_and_extract_mesh_crops_to_bbox(toy_scene: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["train", str(toy_scene), "--out", str(run), "--preset", "cpu-quick", "--max-steps", "1",
                 "--no-progress", *TINY, "train.init_rays=64", "train.samples_per_step=512",
                 "data.roi_center=0,0,0.05", "data.roi_radius=1.25"]) == 0
    capsys.readouterr()
    import torch

    ck = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=False)
    expected = np.diag([1.25, 1.25, 1.25, 1.0])
    expected[2, 3] = 0.05
    np.testing.assert_allclose(np.asarray(ck["to_world"]), expected, atol=1e-12)

    assert main(["extract-mesh", str(run), "--resolution", "40"]) == 0
    full = trimesh.load(run / "mesh.ply", process=False)
    box = [0.0, -2.0, -2.0, 2.0, 2.0, 0.3]
    assert main(["extract-mesh", str(run), "--resolution", "40",
                 "--bbox", ",".join(map(str, box))]) == 0
    capsys.readouterr()
    cropped = trimesh.load(run / "mesh.ply", process=False)
    v = np.asarray(cropped.vertices)
    assert len(cropped.faces) > 0 and len(cropped.faces) < 0.75 * len(full.faces)
    assert (v >= np.array(box[:3]) - 1e-6).all() and (v <= np.array(box[3:]) + 1e-6).all()
    assert v[:, 0].max() > 0.2 and v[:, 2].min() < 0.3 - 0.2  # what is inside the box stays
    assert json.loads((run / "mesh.json").read_text())["bbox"] == box

    for bad, message in (("0,0,0,1,1", "six numbers"), ("1,0,0,0,1,1", "xmax must be greater than xmin"),
                         ("5,5,5,6,6,6", "lies outside the region the run models")):
        assert main(["extract-mesh", str(run), "--bbox", bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
    with pytest.raises(AnisdfError, match="no surface inside the box|no surface found"):
        from anisdf.tasks.mesh import extract_mesh

        extract_mesh(run, resolution=24, progress=False, bbox=[-0.05, -0.05, -0.05, 0.05, 0.05, 0.05])
