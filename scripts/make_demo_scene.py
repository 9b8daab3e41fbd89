"""Make the demo scene bundled with anisdf (src/anisdf/demo/bunny_plastic) from ``shared/data/bunny_plastic``.

Halves the images (straight colour, alpha-weighted area average, as the loader does), keeps every training view and
every ``--test-every``-th test view with its normal map (coverage-weighted), and copies the reference mesh. Run once by
a maintainer; the result is committed (about 2.5 MB). Usage: ``python scripts/make_demo_scene.py SRC DST``.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from anisdf.data.images import read_normal, read_rgb
from anisdf.data.loader import alpha_convention


def _half_rgba(src: Path, dst: Path, premultiplied: bool) -> None:
    rgb, alpha, _ = read_rgb(src, premultiplied=premultiplied)  # straight colour (Mitsuba writes premultiplied)
    a = np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float64) / 255.0
    pre = np.concatenate([a[..., :3] * a[..., 3:], a[..., 3:]], axis=-1)
    h, w = pre.shape[0] // 2, pre.shape[1] // 2
    small = pre[: 2 * h, : 2 * w].reshape(h, 2, w, 2, 4).mean(axis=(1, 3))
    alpha = small[..., 3:]
    rgb = np.where(alpha > 0, small[..., :3] / np.maximum(alpha, 1e-8), 0.0)
    out = np.concatenate([rgb, alpha], axis=-1)
    Image.fromarray(np.round(out * 255).clip(0, 255).astype(np.uint8), "RGBA").save(dst, optimize=True)


def _half_normal(src: Path, dst: Path) -> None:
    n, _ = read_normal(src, downscale=2.0)
    rgb = np.where(n[..., 3:] > 0, (n[..., :3] + 1.0) / 2.0, 0.0)
    out = np.concatenate([rgb, n[..., 3:]], axis=-1)
    Image.fromarray(np.round(out * 255).clip(0, 255).astype(np.uint8), "RGBA").save(dst, optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--test-every", type=int, default=10)
    args = ap.parse_args()
    convention, evidence = alpha_convention(sorted((args.src / "train").glob("*.png")), "auto")
    print(f"{args.src}: {convention} colour ({evidence}); the demo's is straight")
    for split, every in (("train", 1), ("test", args.test_every)):
        meta = json.loads((args.src / f"transforms_{split}.json").read_text())
        meta["frames"] = meta["frames"][::every]
        (args.dst / split).mkdir(parents=True, exist_ok=True)
        for frame in meta["frames"]:
            rel = frame["file_path"].removeprefix("./") + ".png"
            _half_rgba(args.src / rel, args.dst / rel, convention == "premultiplied")
            normal = (args.src / rel).with_name(Path(rel).stem + "_normal.png")
            if normal.is_file():
                _half_normal(normal, (args.dst / rel).with_name(normal.name))
        (args.dst / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    shutil.copy(args.src / "gt_mesh.ply", args.dst / "gt_mesh.ply")


if __name__ == "__main__":
    main()
