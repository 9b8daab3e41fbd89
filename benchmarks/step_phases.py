"""Where a training step's time goes, by part of the model: ``python benchmarks/step_phases.py DATA [--from RUN]``.

Wraps timers around the march, the no-grad SDF queries (pruning pass, occupancy updates), the SDF with its gradient,
the colour heads, the losses, backward and the optimiser, then times ``--steps`` steps. ``--from RUN`` starts from a
run's last checkpoint (every level active, a pruned occupancy grid: a late step), else from step 0 after
``--warmup`` steps. Parts nest: the losses include the curvature term's SDF query. CPU timings; on a GPU the parts
would need synchronising.
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

import anisdf.models.anisdf as model_module
from anisdf.benchmarks.speed import step_timing_inputs
from anisdf.errors import AnisdfError
from anisdf.training.trainer import Trainer
from anisdf.utils.allocator import tune_malloc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="cpu-quick")
    ap.add_argument("--from", dest="run", type=Path, default=None, help="start from RUN/checkpoints/last.pt")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("overrides", nargs="*", help="config overrides key=value")
    args = ap.parse_intermixed_args(argv)
    tune_malloc()  # as every anisdf command does: blocks up to 32 MB reuse the heap (utils/allocator.py)
    try:
        cfg, scene, ck = step_timing_inputs(args.data, args.preset, args.run, args.overrides)
    except AnisdfError as err:
        ap.error(str(err))
    spent: collections.Counter[str] = collections.Counter()

    def timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def wrapper(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t
        return wrapper

    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), torch.device("cpu"), progress=False)
        if ck is not None:
            tr.load_state_dict(ck)
        m = tr.model
        march = model_module.march
        model_module.march = timed("march", march)
        m.geometry.sdf = timed("SDF, no grad (pruning, grid)", m.geometry.sdf)  # older code's route
        m.geometry.distance = timed("SDF, no grad (pruning, grid)", m.geometry.distance)
        route = "query" if hasattr(m.geometry, "query") else "with_gradient"  # older code: with_gradient
        setattr(m.geometry, route, timed("SDF with gradient", getattr(m.geometry, route)))
        m.color_fn = timed("colour heads", m.color_fn)
        m.losses = timed("losses (with curvature's SDF)", m.losses)
        tr.opt.step = timed("optimiser", tr.opt.step)
        backward = torch.Tensor.backward
        torch.Tensor.backward = timed("backward", backward)
        try:
            for _ in range(args.warmup):
                tr.train_step()
            spent.clear()
            t0 = time.perf_counter()
            for _ in range(args.steps):
                stats = tr.train_step()
            total = time.perf_counter() - t0
        finally:
            torch.Tensor.backward = backward
            model_module.march = march
    print(f"{args.preset}, step {tr.state.step}, {stats['n_samples']:.0f} samples of {tr.state.n_rays} rays: "
          f"{total / args.steps * 1e3:.0f} ms a step, {torch.get_num_threads()} threads")
    for name, sec in spent.most_common():
        print(f"  {name:32s} {sec / args.steps * 1e3:7.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
