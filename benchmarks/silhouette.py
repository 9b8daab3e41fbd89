"""Whether a run's surface reaches its object's outline: ``python benchmarks/silhouette.py RUN [RUN ...] [--view 15]``.

For the test view's pixels that the object covers only in part (ground-truth alpha in (0.05, 0.95)), the SDF is
sampled densely along each pixel's ray inside the unit sphere, and the least value kept. A ray whose pixel the object
covers more than half should reach a negative SDF about half the time or more; a surface lying inside the true one
along the outline (an eroded silhouette, too transparent in the renders) shows as a low share of such rays and a
positive median of the least SDF. Prints a row per coverage band: rays, median least SDF, share reaching SDF < 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from anisdf.data.rays import RayDataset
from anisdf.tasks.loading import load_run, scene_for_run

BANDS = ((0.05, 0.3), (0.3, 0.7), (0.7, 0.95))


def least_sdf(model, origins: torch.Tensor, dirs: torch.Tensor, samples: int = 4000, chunk: int = 256) -> np.ndarray:
    """The least SDF along each ray within the unit sphere (``samples`` points over t in [0, 8])."""
    t = torch.linspace(0.0, 8.0, samples)
    out = []
    with torch.no_grad():
        for k in range(0, origins.shape[0], chunk):
            x = origins[k : k + chunk, None] + dirs[k : k + chunk, None] * t[None, :, None]
            sdf = model.geometry.sdf(x.reshape(-1, 3)).reshape(x.shape[:2])
            out.append(torch.where(x.norm(dim=-1) < 1.0, sdf, torch.full_like(sdf, np.inf)).min(1).values)
    return torch.cat(out).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--view", type=int, default=15, help="test view (index into the test split)")
    args = ap.parse_args()
    print("| run | coverage | rays | median least SDF | reach SDF < 0 | 1 / inv_s |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        cfg, model, ck = load_run(run)
        scene = scene_for_run(run, cfg, ck, downscale=1.0, split="test")
        if scene.alpha is None:
            raise SystemExit(f"{run}: the test images have no alpha to tell the outline by")
        alpha = scene.alpha[scene.splits["test"][args.view]].reshape(-1).float().numpy() / 255.0
        batch, _ = RayDataset(scene, "test", device="cpu", background="white").image(args.view)
        rows = np.nonzero((alpha > BANDS[0][0]) & (alpha < BANDS[-1][1]))[0]
        least = least_sdf(model, batch.origins[rows], batch.directions[rows])
        width = 1.0 / float(model.variance().detach())
        for lo, hi in BANDS:
            band = (alpha[rows] >= lo) & (alpha[rows] < hi)
            print(f"| {run.name} | {lo}-{hi} | {int(band.sum())} | {np.median(least[band]):+.2e} | "
                  f"{np.mean(least[band] < 0):.2f} | {width:.2e} |")


if __name__ == "__main__":
    main()
