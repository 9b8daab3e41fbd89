"""Time the whole nerf-synthetic schedule would take, projected from a shorter run's log.

``python benchmarks/gpu/project.py LOG [--reference REF] [--from-step 1000] [--steps 20000]``

``LOG`` and ``REF`` are ``log.jsonl`` files of ``anisdf train --preset nerf-synthetic`` on bunny_plastic (``time``:
seconds of training, validation and checkpoints included). ``REF`` defaults to the H100 run of 2026-11-23
(``records/2026-11-23-h100``), which covered 16,711 of 20,000 steps in 15 minutes. A 15-minute device lease cannot hold
a 15-minute run besides the machine's start and the checks, so the target is judged on a projection, which this
prints two ways:

* ``rate``: LOG's own time so far, plus its mean seconds per step over its last ``--window`` steps for the rest;
* ``scaled``: REF's time for the whole schedule (its steps, extrapolated at its mean rate), times the ratio of the
  two runs' times over the steps both cover from ``--from-step`` on (after compilation and warm-up). REF's rate is
  flat from step 2000 to its end, so this carries the later phases' costs over.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

REF = Path(__file__).resolve().parent / "records" / "2026-11-23-h100" / "train_log_nerf-synthetic_15min.jsonl"


def read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Steps and times of a training log; a missing or malformed one ends the script with one line naming it."""
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        steps, times = np.array([r["step"] for r in rows], float), np.array([r["time"] for r in rows], float)
    except OSError as err:
        raise SystemExit(f"{path}: cannot read it ({err.strerror})") from None
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise SystemExit(f"{path}: not an anisdf log.jsonl ({type(err).__name__}: {err})") from None
    if len(rows) < 2:
        raise SystemExit(f"{path}: fewer than two logged steps")
    return steps, times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--reference", type=Path, default=REF)
    ap.add_argument("--from-step", type=int, default=1000)
    ap.add_argument("--window", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=20000)
    args = ap.parse_args(argv)
    s, t = read(args.log)
    rs, rt = read(args.reference)
    last = s[-1]
    lo = max(last - args.window, s[0])
    rate = (t[-1] - np.interp(lo, s, t)) / (last - lo)
    print(f"{args.log}: step {last:.0f} after {t[-1]:.0f} s; {1e3 * rate:.1f} ms/step over steps {lo:.0f}-{last:.0f}")
    print(f"rate:   {args.steps} steps in {(t[-1] + rate * (args.steps - last)) / 60:.1f} min (projected)")
    hi = min(last, rs[-1])
    if hi <= args.from_step:
        print(f"scaled: the run has not passed step {args.from_step}; no common window with the reference")
        return 0
    ratio = (np.interp(hi, s, t) - np.interp(args.from_step, s, t)) / (
        np.interp(hi, rs, rt) - np.interp(args.from_step, rs, rt))
    ref_total = rt[-1] / rs[-1] * args.steps
    print(f"scaled: steps {args.from_step}-{hi:.0f} took {ratio:.2f}x the reference's time; the reference's "
          f"{args.steps} steps ({ref_total / 60:.1f} min) x {ratio:.2f} = {ratio * ref_total / 60:.1f} min (projected)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
