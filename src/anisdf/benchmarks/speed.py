"""``anisdf bench`` (the CLI calls :func:`run_bench`): encoding and training-step throughput (reference vs fast),
peak memory, time to quality.

Speed targets live here, never in timed tests. Results are recorded in benchmarks/RESULTS.md.
"""

from __future__ import annotations

import dataclasses
import json
import platform
import resource
import tempfile
import time
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from anisdf.benchmarks.encoding import sync
from anisdf.config import Config, load_config
from anisdf.utils.allocator import tune_malloc
from anisdf.utils.options import float_at_least, option

if TYPE_CHECKING:
    from anisdf.data.scene import Scene

DEFAULT_DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "bunny_plastic"
"""The scene of the time-to-PSNR run when ``--data`` is not given and the folder is there (else a synthetic one)."""


@dataclass(kw_only=True)
class BenchOptions:
    """What ``anisdf bench`` / :func:`run_bench` measures and how it reports it."""

    as_json: bool = option(False, "print one JSON object", flag="--json")
    quick: bool = option(False, "skip the time-to-PSNR run")
    data: Path | None = option(None, "scene of the time-to-PSNR run (default: bunny_plastic in the shared data folder "
                               "beside the repository when there is one, else a synthetic scene)", Path)
    minutes: float = option(10.0, "training time of the time-to-PSNR run", float_at_least(0.0, strict=True))
    device: str = option("auto", "auto (CUDA if available) | cpu | cuda[:N]")
    preset: str = option("cpu-quick", "configuration of the training-step and time-to-PSNR runs")


def _scene(data: Path | None, preset: str):
    """The scene at the size ``preset`` trains it (its ``data.downscale`` and ``data.min_size``)."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.data.synthetic import make_synthetic_scene

    d = load_config(preset).data
    if data is None:
        data = DEFAULT_DATA if DEFAULT_DATA.is_dir() else None
    if data is None:
        data = Path(tempfile.mkdtemp(prefix="anisdf-bench-"))
        make_synthetic_scene(data, n_train=40, n_test=8, size=128)
        return load_scene(data)
    return load_scene(data, downscale=d.downscale, min_size=d.min_size, alpha=d.alpha)


def bench_train_step(scene, backend: str, steps: int = 20, warmup: int = 20, device: torch.device | None = None,
                     preset: str = "cpu-quick") -> dict[str, Any]:
    """Samples per second of whole training steps of ``preset``, after ``warmup`` steps."""
    from anisdf.training.trainer import Trainer
    from anisdf.utils.devices import pick_device

    device = device or pick_device("auto")
    cfg = load_config(preset, [f"geometry.encoding_backend={backend}", "train.val_every=0",
                               "train.ckpt_every=0"])
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), device, progress=False)
        return {"backend": backend, **time_train_steps(tr, steps, warmup, device)}


def step_timing_inputs(data: Path, preset: str, run: Path | None,
                       overrides: list[str] | tuple[str, ...] = ()) -> tuple[Config, Scene, dict[str, Any] | None]:
    """The configuration, scene and optional checkpoint (``run``'s last) of a step-timing benchmark: ``preset`` with
    validation, checkpoints and the time budget off, then ``overrides``; the scene as the preset trains it."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.training.checkpoint import load_checkpoint

    cfg = load_config(preset, ["train.val_every=0", "train.ckpt_every=0", "train.max_minutes=0", *overrides])
    scene = load_scene(data, downscale=cfg.data.downscale, min_size=cfg.data.min_size, alpha=cfg.data.alpha)
    return cfg, scene, (load_checkpoint(run / "checkpoints" / "last.pt") if run is not None else None)


def time_train_steps(tr, steps: int, warmup: int, device: torch.device) -> dict[str, Any]:
    """Run ``warmup`` steps of trainer ``tr``, then time ``steps`` more (device-synchronised)."""
    t0 = time.perf_counter()
    for _ in range(warmup):
        tr.train_step()
    sync(device)
    warmup_s = time.perf_counter() - t0
    n, t0 = 0, time.perf_counter()
    for _ in range(steps):
        stats = tr.train_step()
        n += stats["n_samples"]
    sync(device)
    dt = time.perf_counter() - t0
    return {"steps": steps, "samples": n, "seconds": dt, "samples_per_s": n / dt, "ms_per_step": 1000 * dt / steps,
            "warmup_s": warmup_s, "last_n_rays": stats["n_rays"]}


def time_to_psnr(scene, minutes: float, targets: tuple[float, ...] = (30.0, 34.0), eval_every_s: float = 30.0,
                 n_views: int = 4, device: torch.device | None = None, preset: str = "cpu-quick") -> dict[str, Any]:
    """Train ``preset`` and record when the mean test PSNR (first ``n_views`` views) first reaches each target.

    Evaluation time is excluded from the clock.
    """
    import numpy as np

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.models.views import render_view
    from anisdf.training.trainer import Trainer
    from anisdf.utils.devices import pick_device

    device = device or pick_device("auto")
    cfg = load_config(preset, ["train.val_every=0", "train.ckpt_every=0"])
    # a preset whose schedule is laid on time (cpu-quick) is laid on this run's minutes, as `anisdf train
    # --max-minutes M` lays it; its clock is the training time, evaluations excluded
    timed = cfg.train.max_minutes > 0
    if timed:
        cfg.train.max_minutes = minutes
    reached: dict[str, float | None] = {f"{t:g}": None for t in targets}
    curve: list[tuple[float, int, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, scene, Path(tmp), device, progress=False)
        test = RayDataset(scene, "test", device=device, background=eval_background(scene))
        clock, next_eval = 0.0, eval_every_s
        while clock < minutes * 60 and (timed or tr.state.step < cfg.train.max_steps):
            t0 = time.perf_counter()
            tr.state.train_seconds = clock  # the schedule's position (Trainer.schedule_step)
            tr.train_step()
            sync(device)
            clock += time.perf_counter() - t0
            if clock >= next_eval or clock >= minutes * 60 or tr.state.step == cfg.train.max_steps:
                next_eval += eval_every_s
                tr.model.eval()
                psnr = float(np.mean([render_view(tr.model, test, i, scene, 4096)["psnr"]
                                      for i in range(min(n_views, len(test)))]))
                curve.append((round(clock, 1), tr.state.step, round(psnr, 2)))
                for t in targets:
                    if reached[f"{t:g}"] is None and psnr >= t:
                        reached[f"{t:g}"] = round(clock, 1)
        position = tr.state.schedule_step
    return {"minutes": minutes, "seconds_to_psnr": reached, "curve": curve, "schedule_step": position,
            "schedule_steps": cfg.train.max_steps}


def run_bench(options: BenchOptions | None = None, **changes: Any) -> dict:
    """Encoding, training-step and time-to-quality figures on ``device`` (auto: CUDA if there is one); prints them
    (``as_json``: as one JSON object) and returns them. ``changes`` replace fields of ``options``."""
    from anisdf.benchmarks.encoding import bench_encoding, format_table
    from anisdf.fields.hash_grid import load_fast_encoder
    from anisdf.utils.devices import pick_device

    o = dataclasses.replace(options or BenchOptions(), **changes)
    as_json, quick, data, minutes, preset = o.as_json, o.quick, o.data, o.minutes, o.preset
    dev = pick_device(o.device)
    on_cuda = dev.type == "cuda"
    result: dict[str, Any] = {"date": date.today().isoformat(), "machine": platform.machine(),
                              "cpu_threads": torch.get_num_threads(), "torch": torch.__version__,
                              "malloc": "fixed" if tune_malloc() else "default",  # utils/allocator.py
                              "device": str(dev), "preset": preset,
                              "cuda": torch.cuda.get_device_name(dev) if on_cuda else None}
    enc = bench_encoding(n_points=1 << (18 if on_cuda else 16), repeats=3, device=dev)
    result["encoding"] = enc
    row = enc["settings"][0]
    result["encoding_fwd_bwd_speedup"] = row.get("speedup", {}).get("fwd+bwd")
    scene = _scene(data, preset)
    ref = bench_train_step(scene, "torch", device=dev, preset=preset)
    fast_available = load_fast_encoder(device=dev) is not None
    fast = bench_train_step(scene, "auto", device=dev, preset=preset) if fast_available else None
    result["train_step"] = {"reference": ref, "fast": fast}
    result["train_samples_per_s"] = (fast or ref)["samples_per_s"]
    result["train_step_speedup"] = fast["samples_per_s"] / ref["samples_per_s"] if fast else None
    result["peak_memory_mb"] = (torch.cuda.max_memory_allocated(dev) / 2**20 if on_cuda
                                else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    if not quick:
        # a GPU reaches the targets in seconds, not minutes: evaluate more often there
        every = 5.0 if on_cuda else max(5.0, min(30.0, minutes * 6.0))  # about 10 evaluations, at most every 30 s
        result["time_to_psnr"] = time_to_psnr(scene, minutes, eval_every_s=every, device=dev, preset=preset)
    if as_json:
        print(json.dumps(result))
        return result
    print(format_table(enc))
    print()
    print(f"training step ({preset} on {result['cuda'] or 'cpu'}, samples per second after 20 warm-up steps)")
    print(f"  reference  {ref['samples_per_s'] / 1e3:8.1f} k/s   {ref['ms_per_step']:7.0f} ms/step")
    if fast:
        print(f"  fast       {fast['samples_per_s'] / 1e3:8.1f} k/s   {fast['ms_per_step']:7.0f} ms/step"
              f"   speedup {result['train_step_speedup']:.2f}x")
    else:
        print(f"  fast       (no fast kernel for {dev})")
    print(f"peak memory {result['peak_memory_mb']:.0f} MB")
    if "time_to_psnr" in result:
        ttp = result["time_to_psnr"]
        for k, v in ttp["seconds_to_psnr"].items():
            print(f"time to {k} dB test PSNR: {'not reached' if v is None else f'{v:.0f} s'} "
                  f"(within {ttp['minutes']:g} min)")
    return result
