"""The outputs a user holds after training: mesh, renders, video, eval.json and report, chamfer CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from test_training import TINY

from anisdf.cli import main


@pytest.fixture(scope="module")
def trained_run(toy_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run"
    assert main(["train", str(toy_scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "30",
                 "--no-progress", *TINY]) == 0
    return out


def test_extract_mesh_is_in_the_dataset_frame_with_colours(trained_run, toy_scene, capsys):
    assert main(["extract-mesh", str(trained_run), "--resolution", "64", "--format", "ply"]) == 0
    mesh = trimesh.load(trained_run / "mesh.ply", process=False)
    assert len(mesh.faces) > 100
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape[0] == len(mesh.vertices) and colors[:, :3].std() > 0
    gt = trimesh.load(toy_scene / "gt_mesh.ply")
    # dataset frame: the mesh overlaps the ground truth's bounding box (not the normalised unit sphere)
    assert np.abs(mesh.bounds.mean(0) - gt.bounds.mean(0)).max() < 0.3
    assert main(["extract-mesh", str(trained_run), "--resolution", "48", "--format", "glb"]) == 0
    assert (trained_run / "mesh.glb").stat().st_size > 0


def test_render_writes_every_map_and_a_video(trained_run):
    assert main(["render", str(trained_run), "--max-views", "1", "--video"]) == 0
    names = {p.name for p in (trained_run / "renders" / "test").iterdir()}
    for key in ("rgb", "normal", "depth", "opacity", "c_view", "c_ref", "weight"):
        assert f"000_{key}.png" in names, key
    videos = list((trained_run / "renders").glob("orbit.*"))
    assert videos and videos[0].stat().st_size > 1000


def test_eval_reports_psnr_ssim_normals_and_chamfer(trained_run, toy_scene, capsys):
    assert main(["eval", str(trained_run), "--gt-mesh", str(toy_scene / "gt_mesh.ply"), "--chamfer-points",
                 "20000", "--mesh-resolution", "64"]) == 0
    metrics = json.loads((trained_run / "eval.json").read_text())
    for key in ("psnr", "ssim", "chamfer", "normal_mae_deg", "n_views", "steps", "train_seconds"):
        assert key in metrics, key
    assert metrics["n_views"] == 2 and metrics["steps"] == 30
    assert 5 < metrics["psnr"] < 60 and 0 < metrics["chamfer"] < 0.5 and 0 <= metrics["normal_mae_deg"] <= 180
    assert (trained_run / "report.html").is_file() and (trained_run / "report.md").is_file()
    assert f"{metrics['psnr']:.2f}"[:4] in (trained_run / "report.md").read_text()


def test_chamfer_cli_prints_the_distance_last(tmp_path, capsys):
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = a.copy()
    b.apply_translation((0.0, 0.0, 0.01))
    a.export(tmp_path / "a.ply")
    b.export(tmp_path / "b.ply")
    assert main(["chamfer", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--points", "50000"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert 0.002 < float(last) < 0.02
    assert main(["chamfer", str(tmp_path / "a.ply"), str(tmp_path / "missing.ply")]) == 2
    assert "missing.ply" in capsys.readouterr().err


def test_photos_without_masks_train_validate_render_and_evaluate(tmp_path, capsys):
    """Opaque photos without masks (instant-ngp, LLFF, COLMAP) have no white background to compose on:
    validation, render and eval compare them as photographed."""
    from anisdf.data.testscenes import write_test_scene

    scene = tmp_path / "scene"
    write_test_scene(scene, "instant-ngp", n_images=8, width=16, height=12, distortion=(0.02, 0.0, 0.0, 0.0))
    out = tmp_path / "run"
    # rays cross the whole sphere in such scenes: a coarse march keeps the reference encoding quick
    assert main(["train", str(scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "3",
                 "--no-progress", *TINY, "train.val_every=3", "renderer.march_steps=64", "renderer.init_rays=64",
                 "renderer.min_rays=32"]) == 0
    assert list((out / "val").glob("*.png"))
    assert main(["render", str(out), "--max-views", "1"]) == 0
    assert main(["eval", str(out), "--mesh-resolution", "32", "--chamfer-points", "2000"]) == 0
    metrics = json.loads((out / "eval.json").read_text())
    assert np.isfinite(metrics["psnr"]) and metrics["n_views"] >= 1
