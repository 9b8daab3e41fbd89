"""Held-out cameras fitted to their images (``anisdf eval --cameras fit``), against the Adam fit used before:
``python benchmarks/camera_fit.py RUN [--views N] [--eval-downscale D] [--methods given,adam,lm]``.

For each of the first ``--views`` test views: ``given`` renders from the dataset's pose; ``lm`` fits the pose as
``anisdf eval`` does now (Levenberg-Marquardt, evaluate/view_cameras.py); ``adam`` fits it as releases before
did (150 Adam steps of 2048 fresh random pixels, learning rate 2e-3 cosine to a tenth of it, kept only when it lowers
the error on a fixed draw of 8192 pixels). Each fitted pose is rendered and scored through ``render_view`` (the call
``anisdf eval`` makes). Prints a row per view and method (fit seconds, the correction, PSNR) and the means.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from anisdf.data.rays import RayDataset, eval_background
from anisdf.models.per_image import CameraRefinement, pose_changes
from anisdf.models.views import render_view
from anisdf.tasks.evaluate import view_cameras
from anisdf.tasks.evaluate.view_fit import fit_to_view, photometric_error, view_pixels
from anisdf.tasks.loading import load_run, scene_for_run
from anisdf.utils.allocator import tune_malloc


def adam_fit(model, data, i: int, seed: int) -> torch.Tensor:
    """View ``i``'s pose fitted as releases before 2026-12-06 did (the module doc)."""
    batch, (h, w) = data.image(i)
    pixels = view_pixels(h, w, batch.rgb.device)
    index = int(data.indices[i])
    cam = CameraRefinement(data.cameras.c2w[index : index + 1], torch.ones(1, dtype=torch.bool), anchor=False)
    grid = model.image_grid()

    def render(b):
        return model.render_rays(*cam(b.origins, b.directions, torch.zeros_like(b.cam_idx)), b.background, grid=grid)

    check = batch[pixels[torch.randperm(pixels.numel(), generator=torch.Generator().manual_seed(seed + 1_000_003))
                         [:8192]]]
    with torch.no_grad():
        before = float(photometric_error(render, check))
    fit_to_view(model, batch, pixels, list(cam.parameters()), render, 150, 2048, 2e-3, seed, final_lr=0.1)
    with torch.no_grad():
        if float(photometric_error(render, check)) >= before:
            cam.delta.zero_()
    return cam.refined_poses()[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--views", type=int, default=7)
    ap.add_argument("--eval-downscale", type=float, default=1.0)
    ap.add_argument("--methods", default="given,adam,lm")
    args = ap.parse_args()
    tune_malloc()  # as every anisdf command does
    cfg, model, ck = load_run(args.run)
    scene = scene_for_run(args.run, cfg, ck, downscale=args.eval_downscale, split="test")
    data = RayDataset(scene, "test", background=eval_background(scene))
    model.image_grid()
    methods = args.methods.split(",")
    fits = {"given": lambda i: data.cameras.c2w[int(data.indices[i])].clone(),
            "adam": lambda i: adam_fit(model, data, i, seed=i),
            "lm": lambda i: view_cameras.fit_camera(model, data, i, seed=i)[0]}
    totals = {m: [] for m in methods}
    print(f"{'view':>4} {'method':>6} {'fit s':>7} {'deg':>6} {'move':>7} {'PSNR':>7}")
    for i in range(min(args.views, len(data))):
        index = int(data.indices[i])
        given = data.cameras.c2w[index].clone()
        for m in methods:
            t0 = time.perf_counter()
            pose = fits[m](i).detach()
            seconds = time.perf_counter() - t0
            deg, move = pose_changes(given[None].double().numpy(), pose[None].double().numpy())
            cams, scene_cams = data.cameras, data.scene.cameras
            data.cameras, data.scene.cameras = (dataclasses.replace(c, c2w=c.c2w.index_put(
                (torch.tensor([index]),), pose.to(c.c2w)[None])) for c in (cams, scene_cams))
            try:
                psnr = render_view(model, data, i, scene, 4096, fine_grid=True)["psnr"]
            finally:
                data.cameras, data.scene.cameras = cams, scene_cams
            totals[m].append((seconds, psnr))
            print(f"{i:>4} {m:>6} {seconds:>7.1f} {deg[0]:>6.3f} {move[0]:>7.4f} {psnr:>7.3f}", flush=True)
    for m, rows in totals.items():
        sec, psnr = np.array(rows).T
        print(f"{m}: fit {sec.sum():.1f} s in all, mean PSNR {psnr.mean():.3f} dB over {len(rows)} views")


if __name__ == "__main__":
    main()
