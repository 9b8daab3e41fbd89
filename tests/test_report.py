"""The evaluation report's figures: training curve, PSNR per view with the worst views' panels, mesh turntable.

A small fake run folder (log.jsonl, eval/ panels, a mesh) stands in for a trained run: no training here.
"""

from __future__ import annotations

import base64
import io
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from anisdf.run_dir import RunDir
from anisdf.tasks.evaluate.figures import cluster_vertices, decimate, turntable
from anisdf.tasks.evaluate.report import read_log, worst_views, write_run_report

PSNRS = [31.0, 24.5, 29.0, 22.0, 33.0, 26.0, 30.5]


def fake_run(root: Path, log: bool = True, validation: bool = True, mesh: bool = True):
    """A run folder with what eval leaves behind: eval/NNN.png panels, and optionally log.jsonl and mesh.ply."""
    rd = RunDir(root)
    rd.eval_images.mkdir(parents=True)
    per_view, images = [], []
    rng = np.random.default_rng(0)
    for i, p in enumerate(PSNRS):
        path = rd.eval_images / f"{i:03d}.png"
        Image.fromarray(rng.integers(0, 255, (8, 24, 3), dtype=np.uint8)).save(path)
        per_view.append({"view": i, "image": f"r_{i}.png", "psnr": p, "ssim": 0.9})
        images.append(path)
    if log:
        lines, val = [], []
        for step in range(10, 210, 10):
            lines.append({"step": step, "time": step * 0.3, "rgb": 0.05 / step, "total": 0.1 / step,
                          "psnr": 15 + 5 * np.log10(step), "n_rays": 256})
            if validation and step % 50 == 0:
                val.append({"step": step, "time": step * 0.3 + 0.1, "val_psnr": 14 + 5 * np.log10(step)})
        text = "".join(json.dumps(r) + "\n" for r in lines)
        rd.log.write_text(text + '{"step": 200, "time": 60.0, "psn')  # a last line cut short by a kill
        if val:  # as the trainer writes them, beside the validation panels
            rd.validation_log.parent.mkdir(parents=True, exist_ok=True)
            rd.validation_log.write_text("".join(json.dumps(r) + "\n" for r in val))
    if mesh:
        trimesh.creation.icosphere(subdivisions=2).export(rd.mesh("ply"))
    metrics = {"split": "test", "n_views": len(PSNRS), "psnr": float(np.mean(PSNRS)), "ssim": 0.9}
    return metrics, per_view, images


def sections(html_text: str) -> dict[str, str]:
    return dict(re.findall(r'<section id="([^"]+)">(.*?)</section>', html_text, flags=re.S))


def embedded_png(section: str) -> np.ndarray:
    """The one figure embedded in a report section, decoded."""
    found = re.findall(r'src="data:image/png;base64,([^"]+)"', section)
    assert len(found) == 1
    with Image.open(io.BytesIO(base64.b64decode(found[0]))) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"))


def test_report_has_the_three_figures_and_the_worst_views(tmp_path):
    run = tmp_path / "run"
    metrics, per_view, images = fake_run(run)
    html_path, md_path = write_run_report(run, metrics, per_view, images, protocol={"split": "test"})
    assert (html_path, md_path) == (RunDir(run).report_html, RunDir(run).report_md)
    html_text = html_path.read_text()
    found = sections(html_text)
    assert set(found) == {"training-curve", "per-view-psnr", "mesh-turntable"}
    for name, body in found.items():
        picture = embedded_png(body)
        assert picture.shape[0] > 100 and picture.shape[1] > 300, name
        assert picture.std() > 5, name  # something is drawn
    assert "(val/psnr.jsonl), 4 lines" in found["training-curve"] and "no validation" not in found["training-curve"]
    # the worst three views, lowest PSNR first, linked relative to the report (the folder can move)
    assert worst_views(per_view) == [3, 1, 5]
    links = re.findall(r'<img src="([^"]+)"', found["per-view-psnr"])
    assert links == ["eval/003.png", "eval/001.png", "eval/005.png"]
    assert all((run / link).is_file() for link in links)
    assert "PSNR 22.00 dB" in found["per-view-psnr"] and "mesh.ply" in found["mesh-turntable"]
    # the turntable is one strip of 8 views
    strip = embedded_png(found["mesh-turntable"])
    assert strip.shape[1] >= 6 * strip.shape[0]
    # the tables and report.md are there as before, and the figures do not go into report.md
    assert "<h2>Per view</h2>" in html_text and "data:image" not in md_path.read_text()


def test_report_without_log_or_validation_lines_says_so(tmp_path):
    run = tmp_path / "run"
    write_run_report(run, *fake_run(run, log=False, mesh=False))
    found = sections(RunDir(run).report_html.read_text())
    assert "No training curve: this run has no log.jsonl." in found["training-curve"]
    assert "data:image" not in found["training-curve"] and "data:image" not in found["mesh-turntable"]
    assert "No mesh" in found["mesh-turntable"]
    embedded_png(found["per-view-psnr"])

    other = tmp_path / "other"
    write_run_report(other, *fake_run(other, validation=False, mesh=False))
    curve = sections(RunDir(other).report_html.read_text())["training-curve"]
    assert "no validation yet" in curve
    embedded_png(curve)


def test_read_log_keeps_the_last_line_of_a_repeated_step(tmp_path):
    path = tmp_path / "log.jsonl"
    rows = [{"step": 10, "time": 1.0, "psnr": 20.0, "total": 0.1}, {"step": 20, "time": 2.0, "psnr": 21.0,
                                                                     "total": 0.09},
            {"step": 20, "time": 2.5, "psnr": 22.0, "total": 0.08}, {"step": 20, "time": 2.6, "val_psnr": 19.0}]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + "not json\n[1, 2]\n")
    train, val = read_log(path)
    assert [(r["step"], r["psnr"]) for r in train] == [(10, 20.0), (20, 22.0)]
    assert [r["val_psnr"] for r in val] == [19.0]


def test_turntable_decimates_a_large_mesh_and_stays_fast():
    mesh = trimesh.creation.icosphere(subdivisions=6)  # 81,920 faces
    start = time.perf_counter()
    png = turntable(mesh, up=np.array([0.0, 1.0, 0.0]))
    assert time.perf_counter() - start < 5.0
    with Image.open(io.BytesIO(png)) as im:
        assert im.format == "PNG" and im.width >= 6 * im.height
    assert len(decimate(mesh).faces) <= 20_500


@pytest.mark.parametrize("max_faces", [300, 2000])
def test_vertex_clustering_fallback_keeps_the_shape_under_the_budget(max_faces):
    mesh = trimesh.creation.icosphere(subdivisions=5)
    v, f = cluster_vertices(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_faces)
    assert 0 < len(f) <= max_faces and f.max() < len(v)
    radii = np.linalg.norm(v[np.unique(f)], axis=1)
    assert 0.85 < radii.min() and radii.max() <= 1.0 + 1e-9
