"""``anisdf batch JOBS.yaml --out DIR [--ray [auto|ADDRESS]]``: train, mesh and evaluate a list of runs.

JOBS.yaml is a list of jobs::

    - name: lego                 # the run folder DIR/lego
      data: scenes/lego          # relative paths are read from the folder of JOBS.yaml
      preset: nerf-synthetic     # optional (default: the defaults)
      overrides: [train.seed=1]  # optional key=value config overrides
      minutes: 30                # optional time budget (default: the preset's schedule)

and optionally ``max_steps``, ``max_views`` (test views evaluated, 0: all), ``mesh_resolution`` and
``chamfer_points`` (default: extract-mesh's and eval's) and ``cpus`` (torch threads; the CPUs asked of Ray). Each job
trains DIR/NAME (resuming it when it holds a checkpoint), extracts DIR/NAME/mesh.ply and evaluates it into
DIR/NAME/eval.json (the Chamfer distance against DATA/gt_mesh.ply when the scene has one). DIR/batch.json lists every
job with its status, attempts and figures, rewritten atomically as each job ends; a rerun skips the jobs already
done. Jobs run one by one here, or side by side on Ray (orchestration/cluster.py).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from anisdf.errors import AnisdfError, TrainingDiverged
from anisdf.eval.paper_tables import METRICS
from anisdf.orchestration.cluster import Task, ray_option, read_attempt, require_ray, run_tasks, train_or_resume
from anisdf.tasks.evaluate import EvalOptions
from anisdf.tasks.mesh import MeshOptions
from anisdf.utils.atomic import write_text_atomic
from anisdf.utils.options import option

log = logging.getLogger("anisdf")

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


@dataclass(kw_only=True)
class BatchOptions:
    """Where ``anisdf batch`` / :func:`run_batch` runs the jobs."""

    device: str | None = option(None, "auto | cpu | cuda[:N]")
    ray: str | None = ray_option("jobs")
    progress: bool = option(True, "show progress bars (one by one here only)", cli=False)
    gpus_per_job: float | None = option(None, "GPUs each job asks of Ray", cli=False)


@dataclass
class Job:
    name: str
    data: str
    preset: str | None = None
    overrides: list[str] = field(default_factory=list)
    minutes: float | None = None
    max_steps: int | None = None
    max_views: int = EvalOptions().max_views
    mesh_resolution: int = MeshOptions().resolution
    chamfer_points: int = EvalOptions().chamfer_points
    cpus: int | None = None


_KINDS: dict[str, tuple[type, ...]] = {
    "name": (str,), "data": (str,), "preset": (str, type(None)), "overrides": (list,),
    "minutes": (int, float, type(None)), "max_steps": (int, type(None)), "max_views": (int,),
    "mesh_resolution": (int,), "chamfer_points": (int,), "cpus": (int, type(None)),
}
_LOWEST = {"minutes": 0, "max_steps": 1, "max_views": 0, "mesh_resolution": 2, "chamfer_points": 1, "cpus": 1}


def load_jobs(path: Path) -> list[Job]:
    """The jobs of a JOBS.yaml, checked: one clear error naming the job and key otherwise."""
    if not path.is_file():
        raise AnisdfError(f"{path}: jobs file not found")
    try:
        items = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise AnisdfError(f"{path}: invalid YAML ({' '.join(str(e).split())})") from None
    if not isinstance(items, list) or not items:
        raise AnisdfError(f"{path}: expected a list of jobs ({{name, data, preset, overrides, minutes}}), "
                          f"not {type(items).__name__}")
    jobs: list[Job] = []
    for i, item in enumerate(items, 1):
        where = f"{path}: job {i}"
        if not isinstance(item, dict):
            raise AnisdfError(f"{where}: expected a mapping with name and data, not {type(item).__name__}")
        unknown = sorted(set(item) - set(_KINDS))
        if unknown:
            raise AnisdfError(f"{where}: unknown key '{unknown[0]}' (keys: {', '.join(_KINDS)})")
        for key in ("name", "data"):
            if key not in item:
                raise AnisdfError(f"{where}: '{key}' is missing")
        for key, value in item.items():
            kinds = _KINDS[key]
            if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
                names = " or ".join("null" if k is type(None) else k.__name__ for k in kinds)
                raise AnisdfError(f"{where}: '{key}' must be {names}, not {value!r}")
            low = _LOWEST.get(key)
            if low is not None and value is not None and not (math.isfinite(value) and value >= low):
                raise AnisdfError(f"{where}: '{key}' must be >= {low}, not {value!r}")
        name = item["name"]
        if not NAME_RE.fullmatch(name):
            raise AnisdfError(f"{where}: name {name!r} must be a folder name (letters, digits, . _ -)")
        if name in {j.name for j in jobs}:
            raise AnisdfError(f"{where}: the name '{name}' is used twice")
        bad = [o for o in item.get("overrides", []) if not isinstance(o, str) or "=" not in o]
        if bad:
            raise AnisdfError(f"{where} ({name}): override {bad[0]!r} is not of the form key=value")
        data = Path(item["data"]).expanduser()
        data = data if data.is_absolute() else (path.parent / data)
        if not data.is_dir():
            raise AnisdfError(f"{where} ({name}): data folder {data} does not exist")
        jobs.append(Job(**{**item, "data": str(data.resolve())}))
    return jobs


def run_job(job: dict[str, Any], run: str, device: str | None = None, progress: bool = False) -> dict[str, Any]:
    """Train (or resume), mesh and evaluate one job into ``run``; its figures (what batch.json lists)."""
    from anisdf.tasks.evaluate import evaluate
    from anisdf.tasks.mesh import extract_mesh

    j, run_dir = Job(**job), Path(run)
    t0 = time.perf_counter()
    try:
        train_or_resume(Path(j.data), run_dir, j.preset, list(j.overrides), j.minutes, j.max_steps, device, progress)
    except TrainingDiverged as e:
        return {"status": "diverged", "error": str(e)}
    mesh = extract_mesh(run_dir, resolution=j.mesh_resolution, device=device, progress=progress, written_by="batch")
    gt = Path(j.data) / "gt_mesh.ply"
    metrics = evaluate(run_dir, max_views=j.max_views, gt_mesh=gt if gt.is_file() else None, device=device,
                       chamfer_points=j.chamfer_points, progress=progress)
    return {"status": "done", **{m: metrics.get(m) for m in METRICS}, "steps": metrics["steps"],
            "train_seconds": round(metrics["train_seconds"], 1), "mesh": str(mesh),
            "seconds": round(time.perf_counter() - t0, 1)}


def run_batch(jobs_file: Path, out: Path, options: BatchOptions | None = None, **changes: Any) -> dict[str, Any]:
    """Every job of ``jobs_file`` into ``out``; returns the content of OUT/batch.json. Jobs already done there are
    kept; a failed job is listed with its error, and the others go on. ``changes`` replace fields of ``options``."""
    o = dataclasses.replace(options or BatchOptions(), **changes)
    ray, device, progress = o.ray, o.device, o.progress
    jobs_file, out = Path(jobs_file), Path(out)
    jobs = load_jobs(jobs_file)
    if ray is not None:
        require_ray()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "batch.json"
    old: dict[str, dict[str, Any]] = {}
    if path.is_file():
        try:
            old = {r["name"]: r for r in json.loads(path.read_text()).get("runs", [])}
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise AnisdfError(f"{path}: not a batch.json ({e}); move it away to start afresh") from None
    result: dict[str, Any] = {"jobs": str(jobs_file.resolve()), "out": str(out.resolve()), "ray": ray,
                              "started": datetime.now(UTC).isoformat(timespec="seconds"), "runs": []}
    rows: dict[str, dict[str, Any]] = {}
    tasks: list[Task] = []
    for j in jobs:
        prev = old.get(j.name)
        if prev is not None and prev.get("status") == "done" and prev.get("job") == asdict(j):
            rows[j.name] = prev
            log.info("%s: done in %s, skipped", j.name, path)
            continue
        rows[j.name] = {"name": j.name, "status": "pending", "job": asdict(j), "run": str(out / j.name)}
        tasks.append(Task(key=j.name, run=out / j.name, fn=run_job, cpus=j.cpus,
                          kwargs={"job": asdict(j), "run": str(out / j.name), "device": device,
                                  "progress": progress and ray is None}))

    def write() -> None:
        result["runs"] = [rows[j.name] for j in jobs]
        write_text_atomic(path, json.dumps(result, indent=2))

    def on_result(task: Task, res: dict[str, Any] | None, info: dict[str, Any], err: BaseException | None) -> None:
        row = rows[task.key]
        row.update(res if res is not None else {"status": "failed", "error": str(err)})
        row.update(attempts=info.get("attempt"), host=info.get("host"), device=info.get("device"),
                   finished=datetime.now(UTC).isoformat(timespec="seconds"))
        figures = ", ".join(f"{m} {row[m]:.4g}" for m in METRICS if row.get(m) is not None)
        log.info("%s: %s%s", task.key, row["status"], f" ({figures})" if figures else f": {row.get('error', '')}")
        write()

    write()
    run_tasks(tasks, on_result, ray_address=ray, gpus_per_task=o.gpus_per_job)
    for t in tasks:  # a task that never reported (cannot happen unless Ray lost the driver): say so
        if rows[t.key]["status"] == "pending":
            rows[t.key].update(status="failed", error="no result", attempts=read_attempt(t.run).get("attempt"))
    write()
    return result
