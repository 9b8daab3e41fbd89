"""Seconds a test view costs ``anisdf eval``/``anisdf render`` (the rendering part), on a trained run:
``python benchmarks/eval_view_speed.py RUN [--views N] [--size PX] [--repeat K]``.

Renders the first ``--views`` test views of RUN at ``--size`` pixels on their longer side, through the same call as
``anisdf eval`` (models.views.render_view), and prints a table: wall and CPU seconds a view, rays a second, and
the SDF queries a ray. With ``--compare`` it also renders on the training grid (``fine_grid=False``), the route of
releases before the refined image grid, so both rows come from one process on one machine.
The CPU seconds are this process's own (``time.process_time``), steadier than wall time on a shared machine.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from anisdf.data.rays import RayDataset, eval_background
from anisdf.models.views import render_view
from anisdf.tasks.loading import load_run, scene_for_run
from anisdf.utils.allocator import tune_malloc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--size", type=int, default=400, help="pixels on the longer side of each view")
    ap.add_argument("--compare", action="store_true", help="also render on the training grid")
    ap.add_argument("--image-grid", type=int, default=None,
                    help="renderer.image_grid_resolution to use (default: the run's)")
    ap.add_argument("--normal-band", type=float, default=None,
                    help="renderer.eval_normal_band to use (default: the run's; 0: a normal at every sample)")
    args = ap.parse_args()
    tune_malloc()  # as every anisdf command does: blocks up to 32 MB reuse the heap (utils/allocator.py)
    cfg, model, ck = load_run(args.run)
    if args.image_grid is not None:
        cfg.renderer.image_grid_resolution = args.image_grid
    if args.normal_band is not None:
        cfg.renderer.eval_normal_band = args.normal_band
    full = scene_for_run(args.run, cfg, ck, downscale=1.0, split="test")
    long_side = max(full.images.shape[1:3])
    scene = scene_for_run(args.run, cfg, ck, downscale=long_side / args.size, split="test")
    data = RayDataset(scene, "test", device=torch.device("cpu"), background=eval_background(scene))
    n = min(args.views, len(data))
    counted = {"queries": 0}
    # with_gradient asks query (older code: with_gradient alone)
    for name in ("distance", "sdf", "query" if hasattr(model.geometry, "query") else "with_gradient"):
        fn = getattr(model.geometry, name)

        def counting(x, *a, _fn=fn, **k):
            counted["queries"] += x.shape[0]
            return _fn(x, *a, **k)

        setattr(model.geometry, name, counting)
    rows = []
    for fine in ([False, True] if args.compare else [True]):
        if fine:
            t = time.process_time()
            model.image_grid()
            print(f"refined image grid: {time.process_time() - t:.1f} CPU s (once per run)")
        counted["queries"] = 0
        wall = cpu = 0.0
        psnrs, rays = [], 0
        for i in range(n):
            t0, c0 = time.perf_counter(), time.process_time()
            res = render_view(model, data, i, scene, cfg.renderer.eval_chunk_rays, fine_grid=fine)
            wall += time.perf_counter() - t0
            cpu += time.process_time() - c0
            psnrs.append(res["psnr"])
            rays += res["hw"][0] * res["hw"][1]
        rows.append(("refined image grid" if fine else "training grid", wall / n, cpu / n, rays / wall,
                     counted["queries"] / rays, float(np.mean(psnrs))))
    hw = data.image(0)[1]
    print(f"\n{args.run}: {n} test views at {hw[1]}x{hw[0]}, torch threads {torch.get_num_threads()}")
    print("| route | wall s/view | CPU s/view | rays/s | SDF queries/ray | PSNR dB |\n|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.2f} | {r[2]:.2f} | {r[3]:.0f} | {r[4]:.1f} | {r[5]:.2f} |")


if __name__ == "__main__":
    main()
