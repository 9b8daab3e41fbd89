"""How much of a run's test error is pixel noise of the ground truth: ``python benchmarks/noise_floor.py RUN
[--views 0,10,20,30,40]``.

Path-traced test images (bunny_plastic: Mitsuba 3 at 64 samples a pixel) carry noise no model can predict. With the
error of a render split into a part ``b`` that is smooth over 2x2 pixels and independent pixel noise of variance
``s2``, the MSE at full resolution is ``b2 + s2`` and after averaging both images over 2x2 blocks ``b2 + s2 / 4``,
so ``s2 = 4/3 (MSE - MSE_2x2)``. Prints a table a view: the PSNR, the share of the MSE that is pixel noise, the PSNR
of the noise alone (what a perfect model would score) and of the rest. Error the model leaves at the pixel scale
(fine texture it missed) counts as noise here, so the floor is an upper bound on what a better model could gain.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from anisdf.data.rays import RayDataset, eval_background
from anisdf.models.views import render_view
from anisdf.tasks.loading import load_run, scene_for_run


def _pool(x: np.ndarray) -> np.ndarray:
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    return x[:h, :w].reshape(h // 2, 2, w // 2, 2, -1).mean((1, 3))


def _db(mse: float) -> float:
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--views", default="0,10,20,30,40", help="test views, comma-separated")
    args = ap.parse_args()
    cfg, model, ck = load_run(args.run)
    scene = scene_for_run(args.run, cfg, ck, downscale=1, split="test")
    data = RayDataset(scene, "test", background=eval_background(scene))
    rows, sums = [], np.zeros(2)
    for i in (int(v) for v in args.views.split(",")):
        res = render_view(model, data, i, scene, 8192, fine_grid=True)
        render, truth = np.clip(res["maps"]["rgb"], 0, 1), res["gt"]
        mse = float(np.mean((render - truth) ** 2))
        mse2 = float(np.mean((_pool(render) - _pool(truth)) ** 2))
        noise = 4.0 / 3.0 * (mse - mse2)
        sums += (mse, noise)
        rows.append((str(i), _db(mse), noise / mse, _db(noise), _db(mse - noise)))
    mse, noise = sums / len(rows)
    rows.append(("mean MSE", _db(mse), noise / mse, _db(noise), _db(mse - noise)))
    print(f"{args.run}: test views at "
          f"{res['hw'][1]}x{res['hw'][0]} px, step {ck['state']['step']}")
    print("| view | PSNR | pixel-noise share of the MSE | noise alone (the floor) | the rest |")
    print("|---|---|---|---|---|")
    for name, p, share, floor, rest in rows:
        print(f"| {name} | {p:.2f} dB | {share:.2f} | {floor:.2f} dB | {rest:.2f} dB |")


if __name__ == "__main__":
    main()
