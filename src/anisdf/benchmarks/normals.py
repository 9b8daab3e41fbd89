"""Analytic vs finite-difference normals: cost per step and what each does to the surface.

``python benchmarks/normals_cost_and_accuracy.py [--steps 300] [--size 96] [--json]`` trains the analytic
torus-and-sphere scene (written by :mod:`anisdf.data.synthetic`, so the true SDF and normals are known everywhere) with
the cpu-quick preset once per normal mode, the same number of steps each, and prints a table: ms per step, samples/s,
test PSNR, the angle between the learned SDF gradient and the true normal on the true surface, and |SDF| there.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

MODES = ("finite_difference", "analytic")


def surface_points(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` points on the synthetic scene's true surface (random points projected along the SDF gradient)."""
    from anisdf.data.synthetic import scene_sdf

    g = torch.Generator().manual_seed(seed)
    p = (torch.rand(4 * n, 3, generator=g) * 2 - 1) * 0.8
    for _ in range(30):
        p.requires_grad_(True)
        d = scene_sdf(p)
        (grad,) = torch.autograd.grad(d.sum(), p)
        p = (p - d[:, None] * grad).detach()
    return p[scene_sdf(p).abs() < 1e-5][:n]


def surface_errors(trainer: Any, points: torch.Tensor) -> dict[str, float]:
    """Median angle (deg) between the learned SDF gradient and the true normal, and median |SDF| (world units),
    at true surface points. Gradients are taken analytically here, whatever mode trained the model."""
    from anisdf.data.synthetic import scene_normal

    scene = trainer.scene
    x = torch.as_tensor(scene.to_normalised_frame(points.numpy()), dtype=torch.float32)
    geo = trainer.model.geometry
    x.requires_grad_(True)
    sdf = geo.sdf(x)
    (grad,) = torch.autograd.grad(sdf.sum(), x)
    # the normalisation is a similarity, so its rotation maps normals back to the world frame
    rot = torch.as_tensor(scene.to_world[:3, :3] / scene.scale, dtype=torch.float32)
    n_world = torch.nn.functional.normalize(grad @ rot.T, dim=-1)
    cos = (n_world * scene_normal(points)).sum(-1).clamp(-1, 1)
    return {"normal_err_deg": float(torch.rad2deg(torch.acos(cos)).median()),
            "surface_abs_sdf": float((sdf.detach().abs() * scene.scale).median())}


def bench_normals(steps: int = 300, size: int = 96, data: Path | None = None) -> dict[str, Any]:
    from anisdf.config import load_config
    from anisdf.data.dataparsers import load_scene
    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.data.synthetic import make_synthetic_scene
    from anisdf.models.views import render_view
    from anisdf.training.trainer import Trainer

    rows = []
    points = surface_points(4000)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(data) if data else make_synthetic_scene(Path(tmp) / "scene", n_train=40, n_test=4, size=size)
        scene = load_scene(root)
        test = RayDataset(scene, "test", background=eval_background(scene))
        for mode in MODES:
            cfg = load_config("cpu-quick", [f"geometry.normals={mode}", "data.downscale=1", "train.val_every=0",
                                            "train.ckpt_every=0", f"train.max_steps={steps}"])
            tr = Trainer(cfg, scene, Path(tmp) / mode, torch.device("cpu"), progress=False)
            t0, n = time.perf_counter(), 0
            for _ in range(steps):
                n += tr.train_step()["n_samples"]
            dt = time.perf_counter() - t0
            tr.model.eval()
            with torch.no_grad():
                psnr = float(np.mean([render_view(tr.model, test, i, scene, 4096)["psnr"] for i in range(len(test))]))
            rows.append({"normals": mode, "steps": steps, "seconds": round(dt, 1), "ms_per_step": 1000 * dt / steps,
                         "samples_per_s": n / dt, "test_psnr": psnr, **surface_errors(tr, points)})
    return {"scene": "synthetic torus+sphere" if data is None else str(data), "size": size, "rows": rows}


def format_table(result: dict[str, Any]) -> str:
    lines = [f"normals on {result['scene']} ({result['size']} px), cpu-quick, equal steps",
             f"{'normals':18s} {'steps':>5s} {'ms/step':>8s} {'samples/s':>10s} {'PSNR':>7s} {'normal err':>11s}"
             f" {'|sdf| on surface':>17s}"]
    for r in result["rows"]:
        lines.append(f"{r['normals']:18s} {r['steps']:5d} {r['ms_per_step']:8.0f} {r['samples_per_s']:10.0f} "
                     f"{r['test_psnr']:7.2f} {r['normal_err_deg']:9.2f} deg {r['surface_abs_sdf']:17.5f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--size", type=int, default=96, help="image size of the synthetic scene")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    args = parser.parse_args(argv)
    result = bench_normals(args.steps, args.size)
    print(json.dumps(result) if args.json else format_table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
