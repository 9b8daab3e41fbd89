"""Per-image appearance codes on a capture whose training photos change exposure and white balance.

    python benchmarks/exposure_changes.py SCENES/maryrose [--work DIR] [--steps 1500 | --minutes 10] [--stops 1]
        [--tint 0.1] [--test-too] [--runs off,on,affine,gain]

The bundled real captures share one exposure, so codes have nothing to absorb there. This benchmark writes a copy of
a capture (any format whose images sit in one folder; everything else linked) in which every training photo is
re-exposed as a camera's auto exposure and white balance would: in linear light, times ``2^u`` with ``u`` uniform in
``[-stops, stops]`` and times a per-channel gain ``exp(g)``, ``g`` normal with deviation ``tint`` (a fixed
``--seed``), clipped and re-encoded (JPEG quality 98 for JPEG files). The held-out photos are left as they are, so
every run is scored against the same images; with ``--test-too`` they are re-exposed as well (their own draws, so
the training photos are the same either way), as every photo of a capture made with auto exposure is. It trains
cpu-quick with ``appearance.embedding=off``, ``on`` (a code per image that the heads take), ``affine`` or ``gain``
(on, with that ``embedding_kind``: a colour transform per image) and scores them under eval's appearance protocols
(``--protocols``): the mean code over whole images, and NeRF-W's (a code fitted to each test view's left half, the
right half scored; a run without codes scores the same right halves).
Runs already done in ``--work`` are reused.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from cpu_quick_runs import train_and_score

from anisdf.data.dataparsers import parse_dataset


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(np.maximum(c, 0.0031308), 1 / 2.4) - 0.055)


def reexpose(data: Path, out: Path, stops: float, tint: float, seed: int, test_too: bool = False) -> list[dict]:
    """``out``: a copy of ``data`` (files linked) whose training images, and with ``test_too`` the others, are
    re-exposed (module doc). Returns each changed image's name, split, exposure (stops) and channel gains."""
    parsed = parse_dataset(data)
    train = set(parsed.splits["train"])
    folders = {p.parent for p in parsed.image_paths}
    if len(folders) != 1:
        raise SystemExit(f"{data}: the images are in {len(folders)} folders; this benchmark needs them in one")
    image_dir = folders.pop()
    rel = image_dir.resolve().relative_to(data.resolve())
    out.mkdir(parents=True, exist_ok=True)
    for entry in data.iterdir():  # everything but the image folder is linked
        if entry.resolve() != image_dir.resolve() and not (out / entry.name).exists():
            (out / entry.name).symlink_to(entry.resolve())
    (out / rel).mkdir(parents=True, exist_ok=True)
    rng, rng_test = np.random.default_rng(seed), np.random.default_rng(seed + 1000)
    changes = []
    for i, path in enumerate(parsed.image_paths):
        dst = out / rel / path.name
        if i not in train and not test_too:
            if not dst.exists():
                dst.symlink_to(path.resolve())
            continue
        r = rng if i in train else rng_test
        u, g = float(r.uniform(-stops, stops)), r.normal(0.0, tint, size=3)
        changes.append({"image": path.name, "split": "train" if i in train else "held out", "stops": u,
                        "gains": np.exp(g).round(4).tolist()})
        if dst.exists():
            continue
        img = iio.imread(path)
        rgb = img[..., :3].astype(np.float64) / 255.0
        lin = srgb_to_linear(rgb) * (2.0**u) * np.exp(g)
        out_img = img.copy()
        out_img[..., :3] = np.round(linear_to_srgb(np.clip(lin, 0.0, 1.0)) * 255.0).astype(np.uint8)
        tmp = dst.with_name(f".{dst.stem}.tmp{dst.suffix}")
        jpeg = path.suffix.lower() in (".jpg", ".jpeg")
        iio.imwrite(tmp, out_img, **({"quality": 98} if jpeg else {}))
        tmp.replace(dst)
    return changes


def run_one(data: Path, out: Path, steps: int, codes: str, overrides: list[str], protocols: list[str],
            eval_downscale: float, minutes: float | None = None) -> dict[str, dict]:
    """Train (unless done) and score a run under each appearance protocol (``RUN/eval_appearance_<p>.json``)."""
    evals = {f"appearance_{p}": {"appearance": p, "eval_downscale": eval_downscale} for p in protocols}
    switch = (["appearance.embedding=on", f"appearance.embedding_kind={codes}"] if codes in ("affine", "gain")
              else [f"appearance.embedding={codes}"])
    scores = train_and_score(data, out, steps, [*overrides, *switch], evals, minutes)
    return {p: scores[f"appearance_{p}"] for p in protocols}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--work", type=Path, default=None, help="folder of the re-exposed copy and the runs (default: a "
                    "new temporary folder, kept)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--minutes", type=float, default=None, help="train each run for this many minutes (the --steps "
                    "schedule laid on them) instead of --steps steps")
    ap.add_argument("--stops", type=float, default=1.0, help="exposure changes uniform in +-STOPS")
    ap.add_argument("--tint", type=float, default=0.1, help="deviation of the log channel gains")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-too", action="store_true", help="re-expose the held-out photos as well")
    ap.add_argument("--runs", default="off,on,affine", help="the runs: appearance.embedding off, on (a code the heads "
                    "take), affine or gain (on, with that embedding_kind: a colour transform per image)")
    ap.add_argument("--protocols", default="mean,fit-left-half", help="eval's appearance protocols to score")
    ap.add_argument("--eval-downscale", type=float, default=1.0)
    ap.add_argument("--set", nargs="*", default=[], metavar="key=value", help="config overrides of every run")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="exposure_changes_"))
    changed = work / "data_reexposed"
    changes = reexpose(a.data, changed, a.stops, a.tint, a.seed, a.test_too)
    (work / "exposures.json").write_text(json.dumps(changes, indent=1) + "\n")
    rows = []
    for codes in a.runs.split(","):
        scores = run_one(changed, work / f"run_codes_{codes}", a.steps, codes, a.set, a.protocols.split(","),
                         a.eval_downscale, a.minutes)
        mean, half = scores.get("mean", {}), scores.get("fit-left-half", {})
        any_eval = mean or half
        rows.append({"codes": codes, "psnr": mean.get("psnr", float("nan")), "ssim": mean.get("ssim", float("nan")),
                     "psnr_right_half": half.get("psnr", float("nan")),
                     "ssim_right_half": half.get("ssim", float("nan")),
                     "steps": any_eval.get("steps"), "train_seconds": any_eval.get("train_seconds")})
    which = "photos" if a.test_too else "training photos"
    print(f"work folder: {work}; {len(changes)} {which} re-exposed by +-{a.stops:g} stops, tint {a.tint:g}")
    print(f"{'codes':6s} {'PSNR':>7s} {'SSIM':>6s} {'PSNR right half':>15s} {'SSIM':>6s} {'steps':>5s} {'minutes':>7s}")
    for r in rows:
        print(f"{r['codes']:6s} {r['psnr']:7.2f} {r['ssim']:6.3f} {r['psnr_right_half']:15.2f} "
              f"{r['ssim_right_half']:6.3f} {r['steps']:5d} {r['train_seconds'] / 60:7.1f}")
    (work / "table.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
