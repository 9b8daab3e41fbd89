"""Training steps with glibc's default malloc thresholds against :func:`anisdf.utils.allocator.tune_malloc`.

``python benchmarks/allocator_faults.py DATA [--from RUN] [--rounds 3]`` runs each arm in its own process
(alternating, ``rounds`` times), trains ``--before`` steps (or loads ``RUN/checkpoints/last.pt``), then times
``--steps`` steps and prints a table: ms a step, page faults a step and system CPU ms a step, early (from step 0)
and late (from the checkpoint or after ``--before`` steps).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def _measure(data: Path, preset: str, run: Path | None, before: int, steps: int) -> dict[str, float]:
    import torch

    from anisdf.benchmarks.speed import step_timing_inputs, time_train_steps
    from anisdf.training.trainer import Trainer

    cfg, scene, ck = step_timing_inputs(data, preset, run)
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), torch.device("cpu"), progress=False)
        if ck is not None:
            tr.load_state_dict(ck)
        for _ in range(before if run is None else 5):
            tr.train_step()
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        timed = time_train_steps(tr, steps, 0, torch.device("cpu"))
        r1 = resource.getrusage(resource.RUSAGE_SELF)
    return {"ms": timed["ms_per_step"], "faults": (r1.ru_minflt - r0.ru_minflt) / steps,
            "sys_ms": 1e3 * (r1.ru_stime - r0.ru_stime) / steps}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="cpu-quick")
    ap.add_argument("--from", dest="run", type=Path, default=None, help="late steps from RUN/checkpoints/last.pt")
    ap.add_argument("--before", type=int, default=600, help="steps trained before the late measurement")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--arm", choices=("default", "tuned"), help=argparse.SUPPRESS)
    ap.add_argument("--phase", choices=("early", "late"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.arm:  # a child: one arm, one phase
        from anisdf.utils.allocator import tune_malloc

        if args.arm == "tuned" and not tune_malloc():
            sys.exit("tune_malloc did not apply (not glibc?)")
        late = args.phase == "late"
        print(json.dumps(_measure(args.data, args.preset, args.run if late else None,
                                  args.before if late else 40, args.steps)))
        return 0
    res: dict[tuple[str, str], list[dict[str, float]]] = {}
    for _ in range(args.rounds):
        for phase in ("early", "late"):
            for arm in ("default", "tuned"):
                cmd = [sys.executable, __file__, str(args.data), "--preset", args.preset, "--arm", arm,
                       "--phase", phase, "--before", str(args.before), "--steps", str(args.steps)]
                if args.run:
                    cmd += ["--from", str(args.run)]
                env = {**os.environ, "ANISDF_MALLOC": arm}
                out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
                res.setdefault((phase, arm), []).append(json.loads(out.strip().splitlines()[-1]))
    print("| phase | malloc | ms a step (each round) | median | page faults a step | system ms a step |\n"
          "|---|---|---|---|---|---|")
    for (phase, arm), rows in res.items():
        ms = [r["ms"] for r in rows]
        faults, sys_ms = statistics.median(r["faults"] for r in rows), statistics.median(r["sys_ms"] for r in rows)
        print(f"| {phase} | {arm} | {' / '.join(f'{m:.1f}' for m in ms)} | {statistics.median(ms):.1f} | "
              f"{faults:.0f} | {sys_ms:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
