"""A time budget replayed at a fixed pace: ``python benchmarks/paced_budget.py DATA --steps N [--minutes M] [k=v ...]``.

A time-budgeted run's schedule follows the clock, so its outcome depends on the machine's speed of the moment and no
two runs are alike. This trains ``N`` steps of cpu-quick with ``M`` minutes' budget as if every step took ``M / N`` of
it: the same schedule, pace and learning rates as a machine that runs ``N`` steps in ``M`` minutes, and the same
result for the same seed. It prints the training PSNR and NeuS sharpness (inv_s) every 50 steps and the mean
training PSNR of the last 50 steps: a run that lost its surface reads about 22 dB there, a healthy 90-s bunny 34-37.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from anisdf.benchmarks.speed import step_timing_inputs
from anisdf.errors import AnisdfError
from anisdf.training.trainer import Trainer
from anisdf.utils.allocator import tune_malloc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--steps", type=int, required=True, help="optimiser steps the emulated machine runs in the budget")
    ap.add_argument("--minutes", type=float, default=1.5, help="the budget (default 1.5)")
    ap.add_argument("--preset", default="cpu-quick")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value, e.g. train.seed=1")
    args = ap.parse_intermixed_args(argv)
    tune_malloc()
    try:  # the step benchmarks' configuration (no validation, no checkpoints), with this budget
        cfg, scene, _ = step_timing_inputs(args.data, args.preset, None,
                                           [f"train.max_minutes={args.minutes}", *args.overrides])
    except AnisdfError as err:
        ap.error(str(err))
    seconds_per_step = 60.0 * args.minutes / args.steps
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), torch.device("cpu"), progress=False)
        last = []
        try:
            while tr.state.step < args.steps:
                tr.state.train_seconds = tr.state.step * seconds_per_step  # what the clock would have read
                stats = tr.train_step()
                if tr.state.step % 50 == 0:
                    print(f"step {tr.state.step:5d}  schedule {tr.state.schedule_step:5d}  "
                          f"PSNR {stats['psnr']:5.2f} dB  inv_s {stats['inv_s']:7.1f}", flush=True)
                if tr.state.step > args.steps - 50:
                    last.append(stats["psnr"])
        except AnisdfError as err:
            print(f"stopped: {err}")
            return 1
    print(f"{args.steps} steps in {args.minutes} min ({', '.join(args.overrides) or 'preset'}): last 50 steps "
          f"{statistics.mean(last):.2f} dB training PSNR, inv_s {stats['inv_s']:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
