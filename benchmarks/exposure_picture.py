"""The picture of one held-out view under several runs of ``exposure_changes.py``: the photo, then each run's render
with the right half's PSNR (NeRF-W's protocol, which scores the right half).

    python benchmarks/exposure_picture.py docs/exposure.png --work W --view 3 \
        --runs "nothing per image=off" "a code per image=on" "a colour gain per image=gain"

Each run is ``W/run_codes_<name>``, evaluated with ``--appearance fit-left-half`` last (its ``eval/NNN.png`` sheet is
that protocol's, and ``eval_appearance_fit-left-half.json`` holds the per-view scores); the photo's exposure change
comes from ``W/exposures.json``. A red line marks the middle column.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from anisdf.utils.images import hstack_labeled

LABEL = 16  # hstack_labeled's label strip and gap (anisdf.models.views.panel)
GAP = 4


def sheet_panels(sheet: np.ndarray, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth and render panels (the first two) of an eval sheet whose panels have width/height ``aspect``."""
    h = sheet.shape[0] - LABEL
    w = int(round(h * aspect))
    return sheet[LABEL:, :w], sheet[LABEL:, w + GAP: 2 * w + GAP]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--work", type=Path, required=True, help="exposure_changes.py's work folder")
    ap.add_argument("--view", type=int, required=True, help="index of the held-out view")
    ap.add_argument("--runs", nargs="+", required=True, metavar="LABEL=NAME", help="runs W/run_codes_NAME")
    a = ap.parse_args(argv)
    changes = {c["image"]: c for c in json.loads((a.work / "exposures.json").read_text())}
    images, labels = [], []
    for item in a.runs:
        label, _, name = item.rpartition("=")
        run = a.work / f"run_codes_{name}"
        scored = run / "eval_appearance_fit-left-half.json"
        if not scored.is_file():
            raise SystemExit(f"{scored}: missing; run exposure_changes.py with --protocols fit-left-half for '{name}'")
        scores = json.loads(scored.read_text())["per_view"][a.view]
        photo = next((a.work / "data_reexposed").rglob(scores["image"]))
        ph, pw = iio.imread(photo).shape[:2]
        gt, render = sheet_panels(iio.imread(run / "eval" / f"{a.view:03d}.png")[..., :3], pw / ph)
        if not images:
            c = changes.get(scores["image"])
            images.append(gt)
            labels.append("held-out photo" + (f", {c['stops']:+.2f} stop, tinted" if c else ""))
        render = render.copy()
        render[:, render.shape[1] // 2] = (220, 0, 0)
        images.append(render)
        labels.append(f"{label}: right half {scores['psnr']:.1f} dB")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(a.out, hstack_labeled(images, labels, gap=12))
    print(f"{a.out}: view {a.view}, " + ", ".join(labels))
    return 0


if __name__ == "__main__":
    sys.exit(main())
