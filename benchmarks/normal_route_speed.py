"""A training step with the analytic normal's two routes through the hash grid, alternating in one process:
``python benchmarks/normal_route_speed.py DATA [--from RUN] [--warmup N] [--rounds K]``.

"jacobian": the CPU kernel returns the features with their Jacobian (:meth:`HashGrid.encode_with_jacobian`);
"autograd": a backward pass through the encoding, and a double backward in training (the route before it, and the
route of the reference backend and of CUDA). Both routes train the same function (the tests compare them), so the
run goes on across the switches: blocks of ``--block`` steps, alternating, ``--rounds`` times; it prints the median
step of each. ``--from RUN`` starts from the run's last checkpoint with grid updates off (a late step), else from
step 0 after ``--warmup`` steps (an early step).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from anisdf.benchmarks.speed import step_timing_inputs
from anisdf.errors import AnisdfError
from anisdf.fields.hash_grid.dispatch import HashGrid
from anisdf.training.trainer import Trainer
from anisdf.utils.allocator import tune_malloc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="cpu-quick")
    ap.add_argument("--from", dest="run", type=Path, default=None, help="start from RUN/checkpoints/last.pt")
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--block", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=6)
    args = ap.parse_args(argv)
    tune_malloc()  # as every anisdf command does
    try:
        cfg, scene, ck = step_timing_inputs(args.data, args.preset, args.run,
                                            ["renderer.grid_update_every=1000000"] if args.run else [])
    except AnisdfError as err:
        ap.error(str(err))
    jacobian = HashGrid.encode_with_jacobian
    routes = {"jacobian": jacobian, "autograd": lambda *a, **k: None}
    times: dict[str, list[float]] = {name: [] for name in routes}
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), torch.device("cpu"), progress=False)
        if ck is not None:
            tr.load_state_dict(ck)
        try:
            for _ in range(args.warmup):
                tr.train_step()
            for r in range(args.rounds):
                for name in list(routes) if r % 2 == 0 else list(routes)[::-1]:
                    HashGrid.encode_with_jacobian = routes[name]  # type: ignore[method-assign]
                    for _ in range(args.block):
                        t = time.perf_counter()
                        stats = tr.train_step()
                        times[name].append(time.perf_counter() - t)
        finally:
            HashGrid.encode_with_jacobian = jacobian  # type: ignore[method-assign]
    print(f"{args.preset}, step {tr.state.step}, {stats['n_samples']:.0f} samples, {torch.get_num_threads()} threads")
    for name, ts in times.items():
        print(f"  {name:9s} median {statistics.median(ts) * 1e3:7.1f} ms a step ({len(ts)} steps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
