"""The outputs a user holds after training: mesh, renders, video, eval.json and report, chamfer CLI; a missing
optional extra stops a command before any work."""

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


def test_eval_reports_psnr_ssim_normals_and_chamfer(trained_run, toy_scene, capsys, caplog):
    """eval scores the mesh extract-mesh wrote (the last one: mesh.glb at 48) as it is, and records every choice."""
    import logging

    sidecar = json.loads((trained_run / "mesh.json").read_text())
    assert sidecar["mesh"] == "mesh.glb" and sidecar["resolution"] == 48 and sidecar["written_by"] == "extract-mesh"
    assert sidecar["remove_floaters"] is False and sidecar["remove_inner"] is False  # not cleaned unless asked
    before = {name: (trained_run / name).read_bytes() for name in ("mesh.glb", "mesh.ply")}
    with caplog.at_level(logging.INFO, logger="anisdf"):
        assert main(["eval", str(trained_run), "--gt-mesh", str(toy_scene / "gt_mesh.ply"), "--chamfer-points",
                     "20000", "--chamfer-seed", "3"]) == 0
    assert {name: (trained_run / name).read_bytes() for name in before} == before  # scored, not replaced
    assert "scoring" in caplog.text and "mesh.glb" in caplog.text
    out = json.loads((trained_run / "eval.json").read_text())
    for key in ("psnr", "ssim", "chamfer", "normal_mae_deg", "n_views", "steps", "train_seconds", "protocol"):
        assert key in out, key
    assert out["n_views"] == 2 and out["steps"] == 30
    assert 5 < out["psnr"] < 60 and 0 < out["chamfer"] < 0.5 and 0 <= out["normal_mae_deg"] <= 180
    assert out["mesh"].endswith("mesh.glb")
    p = out["protocol"]
    assert p["split"] == "test" and p["held_out"] and p["view_selection"] == "transforms_test.json"
    assert p["eval_downscale"] == 1.0 and p["image_size"] == [32, 32] and p["background"].startswith("white")
    assert p["mesh"]["written_by"] == "extract-mesh" and p["mesh"]["resolution"] == 48
    assert p["mesh"]["remove_floaters"] is False and p["mesh"]["remove_inner"] is False
    assert p["chamfer"]["points"] == 20000 and (p["chamfer"]["seed_pred"], p["chamfer"]["seed_gt"]) == (3, 4)
    assert p["normal_mae"]["reference"] == ["<image>_normal.png"] and p["normal_mae"]["mask"] == "refnerf"
    assert p["normal_mae"]["weights"] == "rendered opacity x ground-truth alpha"
    report = (trained_run / "report.md").read_text()
    assert f"{out['psnr']:.2f}"[:4] in report and "mesh.resolution" in report
    assert (trained_run / "report.html").is_file()
    # at half the dataset's resolution, and weighting normals by the ground-truth alpha alone
    assert main(["eval", str(trained_run), "--eval-downscale", "2", "--normal-mask", "alpha"]) == 0
    half = json.loads((trained_run / "eval.json").read_text())["protocol"]
    assert half["image_size"] == [16, 16] and half["eval_downscale"] == 2.0 and half["mesh"] is None
    assert half["normal_mae"]["weights"] == "ground-truth alpha"


def test_eval_never_changes_the_mesh_silently(trained_run, toy_scene, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run, ignore=shutil.ignore_patterns("mesh.*", "eval*", "report.*"))
    gt = ["--gt-mesh", str(toy_scene / "gt_mesh.ply"), "--chamfer-points", "5000"]
    # no mesh yet: eval extracts one with the defaults (as extract-mesh's) and says so
    assert main(["eval", str(run), *gt, "--max-views", "1", "--mesh-resolution", "40"]) == 0
    info = json.loads((run / "mesh.json").read_text())
    assert info["written_by"] == "eval" and info["resolution"] == 40 and info["mesh"] == "mesh.ply"
    assert not info["remove_floaters"] and not info["remove_inner"]
    # another setting than the existing mesh's: refused, not silently ignored or re-extracted
    before = (run / "mesh.ply").read_bytes()
    assert main(["eval", str(run), *gt, "--max-views", "1", "--mesh-resolution", "44"]) == 2
    assert main(["eval", str(run), *gt, "--max-views", "1", "--remove-floaters"]) == 2
    assert "--re-extract" in capsys.readouterr().err and (run / "mesh.ply").read_bytes() == before
    # --re-extract replaces it, cleaned as asked
    assert main(["eval", str(run), *gt, "--max-views", "1", "--re-extract", "--mesh-resolution", "44",
                 "--remove-floaters", "--remove-inner"]) == 0
    info = json.loads((run / "mesh.json").read_text())
    assert info["written_by"] == "eval --re-extract" and info["resolution"] == 44
    assert info["remove_floaters"] and info["remove_inner"] and info["floater_min_fraction"] == 0.01
    proto = json.loads((run / "eval.json").read_text())["protocol"]["mesh"]
    assert proto["written_by"] == "eval --re-extract" and proto["remove_inner"] is True
    # a mesh from another step, or one without its sidecar: refused with a way out
    (run / "mesh.json").write_text(json.dumps({**info, "step": 7}))
    assert main(["eval", str(run), *gt, "--max-views", "1"]) == 2
    assert "step 7" in capsys.readouterr().err
    (run / "mesh.json").unlink()
    assert main(["eval", str(run), *gt, "--max-views", "1"]) == 2
    assert "no mesh.json" in capsys.readouterr().err
    # eval without a reference mesh neither needs nor touches one, and says so if mesh options come without it
    assert main(["eval", str(run), "--max-views", "1"]) == 0
    assert main(["eval", str(run), "--max-views", "1", "--re-extract"]) == 2
    assert "--gt-mesh" in capsys.readouterr().err


def test_eval_holds_out_every_8th_view_at_the_dataset_resolution(tmp_path, capsys):
    """COLMAP / LLFF (Mip-NeRF 360): the test views are every 8th in name order, as Table 5; eval reloads them
    at the resolution on disk although training used half of it."""
    from scenes import write_test_scene

    scene = tmp_path / "scene"
    truth = write_test_scene(scene, "colmap", n_images=17, width=16, height=12)
    names = sorted(p.name for p in truth.image_paths)
    out = tmp_path / "run"
    fast = [*TINY, "renderer.march_steps=64", "renderer.init_rays=64", "renderer.min_rays=32",
            "cameras.refine=off"]  # the given poses: eval fits none (not the subject here)
    assert main(["train", str(scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "2",
                 "--no-progress", *fast, "data.downscale=2", "data.min_size=0"]) == 0
    assert main(["eval", str(out)]) == 0
    res = json.loads((out / "eval.json").read_text())
    assert [r["image"] for r in res["per_view"]] == names[::8] == ["r_0.png", "r_16.png", "r_9.png"]
    p = res["protocol"]
    assert p["held_out"] and p["view_selection"].startswith("every 8th image in name order")
    assert p["train_downscale"] == 2.0 and p["eval_downscale"] == 1.0 and p["image_size"] == [16, 12]
    assert p["background"].startswith("none") and p["normal_mae"] is None
    # trained on every view (data.train_split=all): the same views, recorded as not held out
    out_all = tmp_path / "run_all"
    assert main(["train", str(scene), "--out", str(out_all), "--preset", "cpu-quick", "--max-steps", "1",
                 "--no-progress", *fast, "data.train_split=all"]) == 0
    assert main(["eval", str(out_all), "--max-views", "1"]) == 0
    assert json.loads((out_all / "eval.json").read_text())["protocol"]["held_out"] is False


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
    from scenes import write_test_scene

    scene = tmp_path / "scene"
    write_test_scene(scene, "instant-ngp", n_images=8, width=16, height=12, distortion=(0.02, 0.0, 0.0, 0.0))
    out = tmp_path / "run"
    # rays cross the whole sphere in such scenes: a coarse march keeps the reference encoding quick
    assert main(["train", str(scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "3",
                 "--no-progress", *TINY, "train.val_every=3", "renderer.march_steps=64", "renderer.init_rays=64",
                 "renderer.min_rays=32"]) == 0
    assert list((out / "val").glob("*.png"))
    assert main(["render", str(out), "--max-views", "1"]) == 0
    assert main(["eval", str(out)]) == 0
    metrics = json.loads((out / "eval.json").read_text())
    assert np.isfinite(metrics["psnr"]) and metrics["n_views"] >= 1


@pytest.mark.parametrize(("argv", "extra", "module"), [
    (["export", "RUN", "--out", "OUT"], "export", "xatlas"),
    (["view", "RUN"], "viewer", "viser"),
    (["train", "DATA", "--out", "OUT", "--viewer"], "viewer", "viser"),
    (["batch", "JOBS", "--out", "OUT", "--ray"], "cluster", "ray"),
])
def test_a_missing_extra_stops_the_command_before_any_work(trained_run, toy_scene, tmp_path, monkeypatch, capsys,
                                                           argv, extra, module):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == module else find_spec(name, *a))
    names = {"RUN": str(trained_run), "OUT": str(tmp_path / "out"), "DATA": str(toy_scene), "JOBS": "jobs.yaml"}
    assert main([names.get(a, a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    command = " ".join([argv[0], *[a for a in argv if a in ("--viewer", "--ray")]])
    assert err == [f"anisdf: error: anisdf {command} needs the {extra} extra: pip install 'anisdf[{extra}]' "
                   f"(missing: {module})"]
    assert not (tmp_path / "out").exists()


def test_train_viewer_serves_the_run_while_it_trains(toy_scene, tmp_path, capsys):
    """``train --viewer``: the command line hands train() a setup that serves the model between steps."""
    import socket

    pytest.importorskip("viser", reason="the viewer extra is not installed")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["train", str(toy_scene), "--out", str(tmp_path / "run"), "--preset", "cpu-quick", "--max-steps", "2",
                 "--no-progress", "--viewer", "--port", str(port), *TINY]) == 0
    out = capsys.readouterr().out
    assert f"viewer: open http://127.0.0.1:{port}/" in out and json.loads(out[out.index("{"):])["step"] == 2
    with socket.socket() as s:  # closed when training ended (a listener would still hold the port)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


def test_atomic_outputs_get_the_mode_an_ordinary_write_gets(tmp_path):
    """mkstemp's private 0600 must not leak into outputs: a page or a mesh is for web servers and other users."""
    import os

    from anisdf.export.asset_files import AssetFolder
    from anisdf.utils.atomic import write_text_atomic

    mask = os.umask(0o022)
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        write_text_atomic(tmp_path / "atomic.txt", "x")
        with AssetFolder(tmp_path / "asset") as folder:
            folder.write("index.html", b"<html></html>")
    finally:
        os.umask(mask)
    files = (plain, tmp_path / "atomic.txt", tmp_path / "asset" / "index.html")
    modes = {p.name: p.stat().st_mode & 0o777 for p in files}
    assert set(modes.values()) == {0o644}, modes
