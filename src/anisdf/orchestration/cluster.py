"""Many runs, one by one here or side by side on a Ray cluster (``anisdf batch``, ``anisdf reproduce --ray``).

A :class:`Task` is one run: a module-level function called with keyword arguments, whose run folder holds its
checkpoint. Without Ray the tasks run in this process in order. With Ray each task is a Ray task asking for one GPU
when the cluster has GPUs (CPUs otherwise); a task whose worker dies (node lost, process killed, out of memory) is run
again by Ray (``max_retries``) and, since the function resumes from the run's checkpoint, goes on from there on
whichever node takes it. That needs the run folders on storage every node sees (docs/distributed.md). While tasks
run, the driver prints each run's last logged step every ``PROGRESS_SECONDS``.

Each attempt writes ``RUN/job.json`` (attempt number, host, pid, start time), so a restarted run can be told apart.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.allocator import tune_malloc
from anisdf.utils.options import option

log = logging.getLogger("anisdf")

PROGRESS_SECONDS = 30.0
"""How often the driver reports the progress of the runs under way (Ray)."""
MAX_RETRIES = 3
"""Times Ray runs a task again after its worker died."""
LOCAL = "local"
"""``--ray`` without an address: start a Ray instance on this machine (or use the one this process already has)."""



def machine_info(device: str | None = None) -> dict[str, Any]:
    """CPU model, GPU name (when CUDA is used), torch version and thread count of this machine."""
    from anisdf.utils.devices import pick_device

    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    dev = pick_device(device or "auto")
    return {"cpu": cpu, "cpu_threads": torch.get_num_threads(), "device": str(dev),
            "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None, "torch": torch.__version__}


@dataclass
class Task:
    key: str
    """Name in logs and progress lines."""
    run: Path
    """The run folder (checkpoint, log.jsonl, job.json)."""
    fn: Callable[..., dict[str, Any]]
    """A module-level function (Ray imports it by name on the worker)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    cpus: int | None = None
    """CPU cores: torch's thread count in the task and the CPUs it asks of Ray (None: torch's default here, one on
    Ray)."""


OnResult = Callable[[Task, dict[str, Any] | None, dict[str, Any], BaseException | None], None]
"""Called once per task: (task, result or None, attempt info from job.json, the error or None)."""


def train_or_resume(data: Path, run: Path, preset: str | None, overrides: list[str], max_minutes: float | None,
                    max_steps: int | None, device: str | None, progress: bool) -> str:
    """Train ``run`` until its schedule is done, resuming it when it holds a checkpoint (a rerun, or a task run again
    after its worker died); a run already done is left as it is. Returns the status: done, diverged; an interrupted
    run raises KeyboardInterrupt, one that ended otherwise an AnisdfError."""
    from anisdf.tasks import train as train_task

    status = read_status(run)
    if status == "done":
        return status
    resume = RunDir(run).has_checkpoint()
    if resume:
        log.info("  resuming the unfinished run %s (%s)", run, status)
    summary = train_task.train(data, run, preset=None if resume else preset, overrides=None if resume else overrides,
                             max_steps=max_steps, max_minutes=None if resume else max_minutes, device=device,
                             resume=resume, progress=progress)
    status = summary["status"]
    if status == "interrupted":
        raise KeyboardInterrupt
    if status != "done":
        raise AnisdfError(f"{run}: training ended with status '{status}'; rerun to resume it")
    return status


def read_status(run: Path) -> str | None:
    return RunDir(run).status()


def read_attempt(run: Path) -> dict[str, Any]:
    path = RunDir(run).job
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except json.JSONDecodeError:
        return {}


def attempt(fn: Callable[..., dict[str, Any]], run: Path, kwargs: dict[str, Any], cpus: int | None = None,
            remote: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """One attempt of a task: count it in RUN/job.json, use ``cpus`` threads, call ``fn``. This is what a Ray worker
    runs; returns the result and the attempt's record."""
    import torch

    if remote and not logging.getLogger().handlers:  # a Ray worker: its log lines go to the driver
        logging.basicConfig(level=logging.INFO, format="%(message)s")
    if remote:  # a Ray worker did not start through the command line, which sets these
        tune_malloc()
    run = Path(run)
    run.mkdir(parents=True, exist_ok=True)
    info = {"attempt": int(read_attempt(run).get("attempt", 0)) + 1, "host": socket.gethostname(), "pid": os.getpid(),
            "started": datetime.now(UTC).isoformat(timespec="seconds"), "ray": remote}
    if remote:  # where the run went: the worker's GPU, else its CPU model

        m = machine_info()
        info["device"] = m["gpu"] or m["cpu"]
    RunDir(run).write_json(RunDir(run).job, info)
    threads = torch.get_num_threads()
    if cpus:
        torch.set_num_threads(cpus)
    try:
        return fn(**kwargs), info
    finally:
        torch.set_num_threads(threads)


def run_tasks(tasks: list[Task], on_result: OnResult, ray_address: str | None = None,
              gpus_per_task: float | None = None, max_retries: int = MAX_RETRIES) -> None:
    """Run every task and report each to ``on_result``: here, one after another (``ray_address`` None; an error
    other than an AnisdfError, or Ctrl-C, stops there), or on Ray (``ray_address``: ``local``, ``auto`` or an address),
    where every task's outcome is reported as it ends. ``gpus_per_task``: None asks one GPU per task when the cluster
    has GPUs."""
    if ray_address is None:
        for t in tasks:
            try:
                result, info = attempt(t.fn, t.run, t.kwargs, t.cpus)
            except AnisdfError as e:
                on_result(t, None, read_attempt(t.run), e)
                continue
            on_result(t, result, info, None)
        return
    _run_on_ray(tasks, on_result, ray_address, gpus_per_task, max_retries)


def read_ray_address(text: str) -> str:
    """``--ray``'s value: local, auto, or a cluster address (not a key=value override)."""
    if "=" in text:
        raise ValueError(f"{text!r} is not a Ray address; put key=value overrides before --ray, or write --ray local")
    return text


read_ray_address.__name__ = "Ray address"


def ray_option(what: str) -> Any:
    """The ``ray`` option of a many-run task: ``what`` (runs, jobs) go to Ray as tasks (None: one by one here)."""
    return option(None, f"run the {what} as tasks on Ray: alone (or 'local') starts Ray on this machine, 'auto' joins "
                  "the cluster this machine belongs to, else ray://HOST:10001 or HOST:6379 (anisdf[cluster])",
                  read_ray_address, metavar="auto|ADDRESS")


def require_ray():
    """The ``ray`` module, or an AnisdfError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise AnisdfError("--ray needs Ray, which is not installed: pip install 'anisdf[cluster]'") from None
    return ray


def connect_ray(address: str) -> bool:
    """Join the Ray cluster at ``address`` (``auto``: the one this machine belongs to) or, for ``local``, start one
    here unless this process already has one. Returns whether this call started or joined it (then the caller shuts
    it down)."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    try:
        if address == LOCAL:
            ray.init(include_dashboard=False, log_to_driver=True)
        else:
            ray.init(address=address, log_to_driver=True)
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise AnisdfError(f"--ray {address}: cannot connect to a Ray cluster ({str(e).splitlines()[0]})") from None
    return True


def _run_on_ray(tasks: list[Task], on_result: OnResult, address: str, gpus_per_task: float | None,
                max_retries: int) -> None:
    started = connect_ray(address)
    import ray
    from ray.exceptions import RayError, RayTaskError

    try:
        gpus = gpus_per_task
        if gpus is None:
            gpus = 1.0 if ray.cluster_resources().get("GPU", 0) >= 1 else 0.0
        remote = ray.remote(attempt)
        pending: dict[Any, Task] = {}
        for t in tasks:
            cpus = t.cpus or 1
            ref = remote.options(num_cpus=cpus, num_gpus=gpus, max_retries=max_retries, retry_exceptions=False,
                                 name=f"anisdf {t.key}").remote(t.fn, str(t.run), t.kwargs, cpus, True)
            pending[ref] = t
        log.info("ray: %d task(s) submitted (%d CPU%s each) to a cluster with %s", len(tasks),
                 max((t.cpus or 1) for t in tasks) if tasks else 1, f", {gpus:g} GPU" if gpus else "",
                 {k: v for k, v in ray.cluster_resources().items() if k in ("CPU", "GPU")})
        last_report = time.monotonic()
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=PROGRESS_SECONDS)
            for ref in done:
                t = pending.pop(ref)
                try:
                    result, info = ray.get(ref)
                except RayTaskError as e:  # the function raised: no retry, the run is reported as failed
                    cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
                    if not isinstance(cause, AnisdfError):
                        cause = AnisdfError(f"{t.key}: {type(cause).__name__}: {str(cause).splitlines()[0]}")
                    on_result(t, None, read_attempt(t.run), cause)
                    continue
                except RayError as e:  # the worker died more often than max_retries
                    msg = str(e).splitlines()[0] if str(e) else type(e).__name__
                    on_result(t, None, read_attempt(t.run),
                              AnisdfError(f"{t.key}: its worker died {max_retries + 1} times ({msg})"))
                    continue
                on_result(t, result, info, None)
            if pending and time.monotonic() - last_report >= PROGRESS_SECONDS:
                last_report = time.monotonic()
                for t in pending.values():
                    log.info("  %s: %s", t.key, progress_line(t.run))
    finally:
        if started:
            ray.shutdown()


def progress_line(run: Path) -> str:
    """Where a run stands, from its log.jsonl and job.json: 'step 120 psnr 24.31 (attempt 2 on host)'."""
    where = read_attempt(run)
    tail = f" (attempt {where['attempt']} on {where.get('host')})" if where else ""
    log_path = RunDir(run).log
    if not log_path.is_file():
        return "starting" + tail
    lines = log_path.read_text().strip().splitlines()
    try:
        last = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        last = {}
    if not last:
        return "starting" + tail
    return f"step {last.get('step')} psnr {last.get('psnr', float('nan')):.2f}" + tail

