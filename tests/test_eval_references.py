"""eval checks what a reference holds before scoring against it: normal maps that are not unit normals stored as
(n + 1) / 2 are skipped with the reason, a reference mesh in another frame is flagged, and the scored mesh's inner
shells (closed components no camera sees) are measured."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from test_training import TINY

from anisdf.cli import main
from anisdf.data.images import read_normal, read_normal_raw
from anisdf.eval.metrics import NORMAL_LENGTH_TOLERANCE, normal_map_problem
from anisdf.tasks.evaluate.scoring import chamfer_frame_warning
from anisdf.tasks.evaluate.shells import inner_shells

BUNDLED = Path(__file__).resolve().parents[1] / "src" / "anisdf" / "demo" / "bunny_plastic" / "test"


def saturate(path: Path, out: Path) -> Path:
    """``path``'s normal map with its channels saturated as NeRF-synthetic's test normals are: max(n, 0) * 255."""
    rgba = np.asarray(Image.open(path).convert("RGBA"))
    n = rgba[..., :3].astype(np.float64) / 255.0 * 2.0 - 1.0
    enc = np.clip(np.round(np.maximum(n, 0.0) * 255.0), 0, 255).astype(np.uint8)
    Image.fromarray(np.dstack([enc, rgba[..., 3]]), "RGBA").save(out)
    return out


def test_bundled_normal_maps_are_unit_and_saturated_ones_are_refused(tmp_path):
    maps = sorted(BUNDLED.glob("r_*_normal.png"))
    assert maps
    for path in maps:
        raw = read_normal_raw(path)
        assert normal_map_problem(raw, raw[..., 3]) is None, path
        # what the scorer reads is the same map, renormalised
        unit, _ = read_normal(path)
        cover = raw[..., 3] > 0.5
        assert np.allclose(unit[cover][:, :3], raw[cover][:, :3] / np.linalg.norm(raw[cover][:, :3], axis=-1,
                                                                                   keepdims=True), atol=1e-5)
        bad = read_normal_raw(saturate(path, tmp_path / path.name))
        reason = normal_map_problem(bad, bad[..., 3])
        assert reason is not None and "not unit length" in reason and f"tolerance {NORMAL_LENGTH_TOLERANCE}" in reason
    # resized to the size eval renders at, the check still passes on the real maps
    half = read_normal_raw(maps[0], (64, 64))
    assert half.shape == (64, 64, 4) and normal_map_problem(half, half[..., 3]) is None
    # nothing covered: nothing to judge
    assert normal_map_problem(np.zeros((4, 4, 4)), np.zeros((4, 4))) is None


def test_chamfer_far_above_the_scene_scale_says_so():
    to_world = np.diag([2.0, 2.0, 2.0, 1.0])  # radius 1 -> a sphere of diameter 4 dataset units
    assert chamfer_frame_warning(0.3, 1.0, to_world) is None
    warning = chamfer_frame_warning(0.5, 1.0, to_world)
    assert warning is not None and "another frame or scale" in warning and "13%" in warning
    assert chamfer_frame_warning(float("nan"), 1.0, to_world) is None


def test_inner_shell_share_is_the_enclosed_components_area():
    outer = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.5).apply_translation([0.1, -0.05, 0.0])
    nested = inner_shells(trimesh.util.concatenate([outer, inner]))
    expected = inner.area / (inner.area + outer.area)
    assert nested["components"] == 2 and nested["inner_components"] == 1
    assert nested["share"] == pytest.approx(expected, rel=0.03)
    side = trimesh.util.concatenate([outer, inner.copy().apply_translation([2.5, 0.0, 0.0])])
    assert inner_shells(side) == {"share": 0.0, "components": 2, "inner_components": 0}
    assert inner_shells(outer)["share"] == 0.0
    # an outer shell with a hole: the inner one is seen through it
    holed = outer.copy()
    holed.update_faces(holed.triangles_center[:, 2] < 0.7)
    holed.remove_unreferenced_vertices()
    assert inner_shells(trimesh.util.concatenate([holed, inner]))["share"] == 0.0
    # split vertices (as a glb may hold them) give the same components
    both = trimesh.util.concatenate([outer, inner])
    split = trimesh.Trimesh(both.triangles.reshape(-1, 3), np.arange(3 * len(both.faces)).reshape(-1, 3),
                            process=False)
    assert inner_shells(split)["share"] == pytest.approx(nested["share"])


@pytest.fixture(scope="module")
def saturated_run(toy_scene, tmp_path_factory):
    """A run trained on a copy of the toy scene whose test normal maps are saturated."""
    root = tmp_path_factory.mktemp("saturated")
    scene = root / "scene"
    shutil.copytree(toy_scene, scene)
    maps = sorted((scene / "test").glob("r_*_normal.png"))
    assert maps
    for path in maps:
        saturate(path, path)
    out = root / "run"
    assert main(["train", str(scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "5",
                 "--no-progress", *TINY]) == 0
    return out, scene


def test_eval_skips_saturated_normal_maps_and_flags_a_reference_in_another_frame(saturated_run, toy_scene, caplog):
    run, scene = saturated_run
    gt = trimesh.load(scene / "gt_mesh.ply", process=False)
    gt.apply_scale(10.0)
    gt.export(run.parent / "gt_x10.ply")
    with caplog.at_level(logging.INFO, logger="anisdf"):
        assert main(["eval", str(run), "--gt-mesh", str(run.parent / "gt_x10.ply"), "--chamfer-points", "5000",
                     "--mesh-resolution", "40"]) == 0
    out = json.loads((run / "eval.json").read_text())
    assert "normal_mae_deg" not in out and all("normal_mae_deg" not in r for r in out["per_view"])
    p = out["protocol"]
    assert p["normal_mae"] is None
    skipped = p["normal_maps_skipped"]
    assert sorted(s["file"] for s in skipped) == sorted(m.name for m in (scene / "test").glob("r_*_normal.png"))
    assert all("not unit length" in s["reason"] for s in skipped)
    assert caplog.text.count("reference normal map(s) not scored") == 1
    # the Chamfer number is still written, with the warning
    assert out["chamfer"] > 0 and "another frame or scale" in p["chamfer"]["warning"]
    assert "another frame or scale" in caplog.text
    # the inner-shell check runs on the scored mesh
    assert 0.0 <= out["inner_shell_share"] <= 1.0
    assert p["inner_shells"]["components"] >= 1 and p["inner_shells"]["grid"] > 0
    report = (run / "report.md").read_text()
    assert "inner_shell_share" in report and "normal_maps_skipped" in report
    # one map as it should be: that view is scored, the other still skipped
    caplog.clear()
    shutil.copy(toy_scene / "test" / skipped[0]["file"], scene / "test" / skipped[0]["file"])
    with caplog.at_level(logging.INFO, logger="anisdf"):
        assert main(["eval", str(run)]) == 0
    out = json.loads((run / "eval.json").read_text())
    assert 0 <= out["normal_mae_deg"] <= 180 and out["protocol"]["normal_mae"]["views"] == 1
    assert [s["file"] for s in out["protocol"]["normal_maps_skipped"]] == [skipped[1]["file"]]
    assert "normal_mae_deg over the 1 other view(s)" in caplog.text
