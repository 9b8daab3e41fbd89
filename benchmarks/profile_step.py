"""Where does a training step's time go? ``python benchmarks/profile_step.py DATA [--preset P] [--device D]``.

Trains ``--warmup`` steps, times ``--steps`` more (device-synchronised), then runs torch.profiler over
``--profile`` steps and prints the operators that take the most device time and the most host time, and the
number of kernel launches per step: a step dominated by host time is launch-bound, not compute-bound.

``--count`` (any device, also CPU) counts instead the operators one step dispatches that would launch a kernel
on a GPU (views and allocations excluded), by phase: forward (with the normals' ``autograd.grad``), backward and
optimiser (unfused on CPU, one fused kernel on CUDA); ``train.amp``'s casts are counted wherever it runs. It also
counts reads of device values to the host (``.item()``, ``.tolist()``, ``nonzero``, boolean-mask indexing), each
of which waits for a GPU's queue to drain. It needs no GPU, so a launch budget can be tracked on any machine.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
from pathlib import Path

import torch

from anisdf.benchmarks.encoding import sync
from anisdf.benchmarks.opcount import count_step
from anisdf.benchmarks.speed import time_train_steps
from anisdf.config import load_config
from anisdf.data.dataparsers import load_scene
from anisdf.errors import AnisdfError
from anisdf.training.trainer import Trainer
from anisdf.utils.allocator import tune_malloc
from anisdf.utils.devices import pick_device


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--preset", default="nerf-synthetic")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--warmup", type=int, default=30)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--profile", type=int, default=5)
    ap.add_argument("--rows", type=int, default=25)
    ap.add_argument("--count", action="store_true", help="count operators and host reads of one step instead")
    ap.add_argument("overrides", nargs="*", help="config overrides key=value")
    args = ap.parse_intermixed_args(argv)  # overrides may follow options
    tune_malloc()  # as every anisdf command does: blocks up to 32 MB reuse the heap (utils/allocator.py)
    try:  # bad device, preset, override or dataset: one line naming it, not a traceback
        dev = pick_device(args.device)
        cfg = load_config(args.preset, ["train.val_every=0", "train.ckpt_every=0", *args.overrides])
        scene = load_scene(args.data, downscale=cfg.data.downscale, min_size=cfg.data.min_size)
    except AnisdfError as err:
        ap.error(str(err))
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), dev, progress=False)
        if args.count:
            tr.use_amp = cfg.train.amp  # the autocast casts of a CUDA step are counted on any device
            for _ in range(args.warmup):
                tr.train_step()
            c = count_step(tr)
            phases: collections.Counter[str] = collections.Counter()
            for (phase, _), n in c.kernels.items():
                phases[phase] += n
            reads = ", ".join(f"{name} {n} ({phase})" for (phase, name), n in c.host_reads.most_common())
            print(f"{args.preset} on {dev}, step {tr.state.step}: {sum(phases.values())} kernel-launching operators "
                  f"({', '.join(f'{p} {n}' for p, n in phases.items())}); "
                  f"host reads: {sum(c.host_reads.values())} ({reads})")
            for (phase, name), n in c.kernels.most_common(args.rows):
                print(f"{n:6d}  {phase:<15} {name}")
            return 0
        t = time_train_steps(tr, args.steps, args.warmup, dev)
        print(f"warm-up: {args.warmup} steps in {t['warmup_s']:.1f} s")
        print(f"{args.preset} on {dev}: {t['ms_per_step']:.1f} ms/step, {t['samples_per_s'] / 1e6:.2f} M samples/s, "
              f"{t['samples'] / args.steps / 1e3:.0f}k samples and {t['last_n_rays']} rays per step")
        acts = [torch.profiler.ProfilerActivity.CPU]
        if dev.type == "cuda":
            acts.append(torch.profiler.ProfilerActivity.CUDA)
        with torch.profiler.profile(activities=acts) as prof:
            for _ in range(args.profile):
                tr.train_step()
            sync(dev)
    avg = prof.key_averages()
    if dev.type == "cuda":
        launches = sum(e.count for e in avg if e.key in ("cudaLaunchKernel", "cuLaunchKernel", "cuLaunchKernelEx"))
        print(f"kernel launches per step: {launches / args.profile:.0f}")
        print(avg.table(sort_by="self_cuda_time_total", row_limit=args.rows))
    print(avg.table(sort_by="self_cpu_time_total", row_limit=args.rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
