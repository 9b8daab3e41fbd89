"""``anisdf reproduce TABLE``: train and evaluate every scene of one of the paper's tables, our figures beside the
paper's, in OUT/reproduce.json and OUT/reproduce.md.

Each (scene, configuration, seed) is one run folder, ``OUT/<scene>/<config>`` (``-seed<s>`` added for seeds other
than 0), trained with :func:`anisdf.tasks.train.train` and scored with :func:`~anisdf.tasks.evaluate.evaluate`.
A call resumes where the previous one stopped: rows already in reproduce.json are kept, an unfinished run is
continued with ``--resume``, and reproduce.json (written atomically) and reproduce.md are rewritten after each row.
With ``ray`` the runs go to a Ray cluster side by side (orchestration/cluster.py); the rows keep the table's order.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import shlex
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from anisdf.errors import AnisdfError, TrainingDiverged
from anisdf.eval.paper_tables import METRICS, PaperTable, find_scenes, get_table
from anisdf.orchestration.cluster import machine_info, ray_option
from anisdf.run_dir import RunDir
from anisdf.tasks.evaluate import EvalOptions
from anisdf.tasks.mesh import MeshOptions
from anisdf.utils.atomic import write_text_atomic
from anisdf.utils.options import comma_list, float_at_least, int_at_least, option, positional

log = logging.getLogger("anisdf")

CPU_PRESET = "cpu-quick"
SCALES = ("paper", "cpu")
CPU_MINUTES = 10.0
"""Each run's time budget at the cpu scale unless ``minutes`` or ``max_steps`` is given."""


@dataclass(kw_only=True)
class ReproduceOptions:
    """How ``anisdf reproduce`` / :func:`reproduce` trains and scores a table's runs."""

    scale: str = option("paper", "paper: the table's preset; cpu: cpu-quick with the table's data settings, "
                        "--minutes per run", choices=SCALES)
    scenes: list[str] | None = option(None, "comma-separated scene folder names (default: the paper's)",
                                      comma_list(str))
    minutes: float | None = option(
        None, f"time budget per run (0: none; cpu scale: {CPU_MINUTES:g} unless --max-steps is given)",
        float_at_least(0.0))
    configs: list[str] | None = option(None, "comma-separated configurations of the table (default: all; the "
                                       "ablation has full, no-asg, no-fusion, no-asg-no-fusion)", comma_list(str))
    seeds: list[int] | str | None = option(
        None, "comma-separated seeds (train.seed), e.g. 0,1 (default 0)")
    max_steps: int | None = option(
        None, "steps per run instead of the preset's (step-based: no time budget unless --minutes)", int_at_least(1))
    max_views: int = option(EvalOptions().max_views, "evaluate on at most this many test views (0: all)",
                            int_at_least(0))
    mesh_resolution: int = option(MeshOptions().resolution, "marching cubes resolution for the Chamfer",
                                  int_at_least(2))
    chamfer_points: int = option(EvalOptions().chamfer_points, "points sampled on each mesh for the Chamfer "
                                 "distance", int_at_least(1))
    dtu_eval: Path | None = option(
        None, "folder with DTU's official ObsMask/ and Points/stl/ (default: beside the scenes)", Path)
    device: str | None = option(None, "auto | cpu | cuda[:N]")
    ray: str | None = ray_option("runs")
    cpus_per_run: int | None = option(
        None, "torch threads of each run, and the CPUs each asks of Ray (default: all here, 1 on Ray)",
        int_at_least(1))
    overrides: list[str] = positional("config overrides for every run", metavar="key=value", nargs="*", default=[])
    command: str | None = option(None, "the command line recorded in reproduce.md", cli=False)
    progress: bool = option(True, "show progress bars", cli=False)


def _seeds(seeds: list[int] | str | None) -> list[int]:
    """The seeds to run (``"0,1"`` is read as [0, 1]); [0] when none are given."""
    if isinstance(seeds, str):
        try:
            seeds = [int(s) for s in seeds.split(",")]
        except ValueError:
            raise AnisdfError(f"--seeds must be comma-separated integers, not '{seeds}'") from None
    seeds = list(seeds) if seeds else [0]
    if len(set(seeds)) != len(seeds):
        raise AnisdfError(f"--seeds lists a seed twice: {','.join(map(str, seeds))}")
    return seeds


def _configs(table: PaperTable, configs: list[str] | None) -> list[str]:
    """The table's configurations to run, in the table's order; all when none are named."""
    if not configs:
        return list(table.configs)
    unknown = [c for c in configs if c not in table.configs]
    if unknown:
        raise AnisdfError(f"--configs: {', '.join(unknown)} not in table {table.name} "
                          f"(it has {', '.join(table.configs)})")
    return [c for c in table.configs if c in configs]


def _data_overrides(preset: str) -> list[str]:
    """The data settings of ``preset`` that differ from the defaults, other than the image downscale (the CPU scale
    keeps cpu-quick's): DTU trains on all views, Mip-NeRF 360 reads images_4, ..."""
    from anisdf.config import DataConfig, load_config

    data, default = load_config(preset).data, DataConfig()
    return [f"data.{f.name}={getattr(data, f.name)}" for f in dataclasses.fields(DataConfig)
            if f.name != "downscale" and getattr(data, f.name) != getattr(default, f.name)]


def run_settings(table: PaperTable, scene: str, config: str, scale: str, seed: int,
                 extra: list[str] | tuple[str, ...] = ()) -> tuple[str, list[str]]:
    """Preset and overrides of one run: the table's preset (``paper``) or cpu-quick with the table's data settings
    (``cpu``), then the scene's protocol (Mip-NeRF 360 indoor: images_2), the configuration, the seed and ``extra``."""
    if scale not in SCALES:
        raise AnisdfError(f"--scale must be one of {', '.join(SCALES)}, not '{scale}'")
    preset = table.preset if scale == "paper" else CPU_PRESET
    base = [] if scale == "paper" else _data_overrides(table.preset)
    return preset, [*base, *table.overrides_for(scene), *table.configs[config], f"train.seed={seed}", *extra]


def _run_dir(out: Path, scene: str, config: str, seed: int) -> Path:
    return out / scene / (config if seed == 0 else f"{config}-seed{seed}")


def _dtu_chamfer(run: Path, scene_dir: Path, scene: str, dtu_eval: Path | None,
                 mesh_resolution: int) -> tuple[dict[str, Any] | None, str | None]:
    """The official DTU Chamfer (mm) of the run's mesh when ``anisdf.eval.dtu`` and the official evaluation files
    (ObsMask/, Points/stl/) are there; else None and a note saying what is missing."""
    try:
        from anisdf.eval.dtu import dtu_chamfer
    except ImportError:
        return None, "DTU Chamfer not measured: this version has no anisdf.eval.dtu"
    m = re.search(r"scan_?(\d+)$", scene.lower())
    if m is None:
        return None, f"DTU Chamfer not measured: no scan number in the folder name '{scene}'"
    scan = int(m.group(1))
    root = dtu_eval or scene_dir.parent
    needed = [root / "ObsMask" / f"ObsMask{scan}_10.mat", root / "Points" / "stl" / f"stl{scan:03d}_total.ply"]
    missing = [str(p) for p in needed if not p.is_file()]
    if missing:
        return None, f"DTU Chamfer not measured: official evaluation files missing ({', '.join(missing)}; --dtu-eval)"
    from anisdf.tasks.mesh import extract_mesh

    mesh = RunDir(run).mesh("ply")
    if not mesh.is_file():
        mesh = extract_mesh(run, resolution=mesh_resolution, progress=False)
    # the mesh is already in DTU's world frame (mm): extract_mesh undoes the scene's scale_mat, so none is passed
    return dtu_chamfer(mesh, root, scan, scale_mat=None), None


def _train_and_eval(data: Path, run: Path, preset: str, overrides: list[str], table: PaperTable, scene: str,
                    max_minutes: float | None, max_steps: int | None, device: str | None, progress: bool,
                    eval_opts: dict[str, Any], dtu_eval: Path | None) -> dict[str, Any]:
    from anisdf.orchestration.cluster import train_or_resume
    from anisdf.tasks.evaluate import evaluate

    notes: list[str] = []
    try:
        train_or_resume(data, run, preset, overrides, max_minutes, max_steps, device, progress)
    except TrainingDiverged as e:
        return {"status": "diverged", "notes": [str(e)]}
    t0 = time.perf_counter()
    # DTU is scored by the official protocol only (below), never against a mesh of the scene folder
    gt = data / "gt_mesh.ply" if table.name != "dtu" else None
    has_gt = gt is not None and gt.is_file()
    # mesh options choose the mesh that is scored: without a reference mesh there is none to choose
    mesh_keys = ("mesh_resolution", "chamfer_points")
    opts = eval_opts if has_gt else {k: v for k, v in eval_opts.items() if k not in mesh_keys}
    metrics = evaluate(run, gt_mesh=gt if has_gt else None, device=device, progress=progress, **opts)
    if gt is not None and not has_gt and any(p["chamfer"] is not None for p in table.scenes.values()):
        notes.append(f"Chamfer not measured: no {gt.name} in {data}")
    if table.name == "dtu":
        cd, note = _dtu_chamfer(run, data, scene, dtu_eval, eval_opts["mesh_resolution"])
        if cd is not None:
            metrics["chamfer"] = cd["chamfer"]
        if note:
            notes.append(note)
    eval_seconds = time.perf_counter() - t0
    return {**{m: metrics.get(m) for m in METRICS}, "status": "done", "steps": metrics["steps"],
            "train_seconds": round(metrics["train_seconds"], 1), "eval_seconds": round(eval_seconds, 1),
            "seconds": round(metrics["train_seconds"] + eval_seconds, 1), "notes": notes}


def reproduce(table_name: str, data: Path, out: Path, options: ReproduceOptions | None = None,
              **changes: Any) -> dict[str, Any]:
    """Train and evaluate every (scene, configuration, seed) of table ``table_name`` found under ``data``; returns
    the content of OUT/reproduce.json; ``changes`` replace fields of ``options``. ``minutes`` is each run's time
    budget (0: none; cpu scale: :data:`CPU_MINUTES` unless given or ``max_steps`` is, which makes the runs
    step-based; paper scale: the preset's step schedule unless given); ``overrides`` and ``max_steps`` apply to every
    run. ``ray`` (``local``, ``auto`` or an address) runs them on Ray, ``cpus_per_run`` threads each (and CPUs asked
    of Ray)."""
    o = dataclasses.replace(options or ReproduceOptions(), **changes)
    scale, scenes, minutes, device, overrides = o.scale, o.scenes, o.minutes, o.device, o.overrides
    max_steps, dtu_eval, command, progress, ray = o.max_steps, o.dtu_eval, o.command, o.progress, o.ray
    data, out = Path(data), Path(out)
    table = get_table(table_name)
    if ray is not None:
        from anisdf.orchestration.cluster import require_ray

        require_ray()
    if scale not in SCALES:
        raise AnisdfError(f"--scale must be one of {', '.join(SCALES)}, not '{scale}'")
    seeds = _seeds(o.seeds)
    if scale == "cpu" and minutes is None and max_steps is None:
        minutes = CPU_MINUTES
    if not minutes:  # 0: no time budget
        minutes = None
    found = find_scenes(table, data, scenes)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "reproduce.json"
    old_rows: list[dict[str, Any]] = []
    if json_path.is_file():
        try:
            old = json.loads(json_path.read_text())
        except json.JSONDecodeError as e:
            raise AnisdfError(f"{json_path}: not valid JSON ({e}); move it away to start afresh") from None
        for key, want in (("table", table.name), ("scale", scale)):
            if old.get(key) != want:
                raise AnisdfError(f"{json_path}: made with {key} '{old.get(key)}', not '{want}'; choose another --out")
        old_rows = old.get("rows", [])
    done = {(r["scene"], r["config"], r.get("seed", 0)): r for r in old_rows}
    command = command or "anisdf reproduce " + shlex.join(
        [table.name, "--data", str(data), "--out", str(out), "--scale", scale])
    result: dict[str, Any] = {
        "table": table.name, "source": table.source, "scale": scale,
        "preset": table.preset if scale == "paper" else CPU_PRESET, "minutes": minutes, "max_steps": max_steps,
        "chamfer_unit": table.chamfer_unit, "command": command, "machine": machine_info(device),
        "rows": list(old_rows), "means": {}}
    configs = _configs(table, o.configs)
    plan = [(name, path, config, seed) for name, path in found for config in configs for seed in seeds]
    _write(out, table, result)
    eval_opts = {"max_views": o.max_views, "mesh_resolution": o.mesh_resolution, "chamfer_points": o.chamfer_points}
    from anisdf.orchestration.cluster import Task, run_tasks

    tasks: list[Task] = []
    meta: dict[str, tuple[int, str, str, int]] = {}
    for i, (name, path, config, seed) in enumerate(plan, 1):
        tag = f"[{i}/{len(plan)}] {name} {config} seed {seed}"
        if (name, config, seed) in done:
            log.info("%s: already in %s, skipped", tag, json_path)
            continue
        preset, ovr = run_settings(table, name, config, scale, seed, overrides or [])
        run = _run_dir(out, name, config, seed)
        log.info("%s: %s %s (preset %s %s)", tag, "submitting" if ray else "training", run, preset, " ".join(ovr))
        meta[tag] = (i, name, config, seed)
        tasks.append(Task(key=tag, run=run, fn=_train_and_eval, cpus=o.cpus_per_run, kwargs={
            "data": path, "run": run, "preset": preset, "overrides": ovr, "table": table, "scene": name,
            "max_minutes": minutes, "max_steps": max_steps, "device": device, "progress": progress and not ray,
            "eval_opts": eval_opts, "dtu_eval": dtu_eval}))
    order: dict[int, dict[str, Any]] = {}
    errors: list[BaseException] = []

    def on_result(task: Task, res: dict[str, Any] | None, info: dict[str, Any], err: BaseException | None) -> None:
        if err is not None:
            if not ray:
                raise err
            log.error("%s: %s", task.key, err)  # on Ray the other runs go on; the row is left for a rerun
            errors.append(err)
            return
        i, name, config, seed = meta[task.key]
        where = info.get("device") if info.get("ray") else None
        row = {"scene": name, "config": config, "seed": seed, "paper": table.paper_row(name, config),
               "run": str(task.run), "device": where or result["machine"]["gpu"] or result["machine"]["cpu"], **res}
        row["finished"] = datetime.now(UTC).isoformat(timespec="seconds")
        row = {k: row.get(k) for k in ("scene", "config", "seed", *METRICS, "paper", "seconds", "train_seconds",
                                       "eval_seconds", "steps", "status", "device", "run", "finished", "notes")}
        order[i] = row
        result["rows"] = list(old_rows) + [order[k] for k in sorted(order)]
        log.info("%s: %s", task.key, ", ".join(f"{m} {row[m]:.4g}" for m in METRICS if row[m] is not None)
                 or row["status"])
        _write(out, table, result)

    run_tasks(tasks, on_result, ray_address=ray)
    _write(out, table, result)
    if errors:
        raise AnisdfError(f"{len(errors)} of {len(tasks)} runs failed (rerun to retry them); first: {errors[0]}")
    return result


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else None


def means(table: PaperTable, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per configuration: our mean over its rows (scenes and seeds), the paper's mean over the same scenes (where it
    gives a figure for each) and the paper's own mean (Table 4 for the ablation; the tables' average rows)."""
    res: dict[str, Any] = {}
    for config in table.configs:
        rs = [r for r in rows if r["config"] == config]
        if not rs:
            continue
        scenes = sorted({r["scene"] for r in rs})
        papers = [table.paper_row(s, config) for s in scenes]
        same = {m: _mean([p[m] for p in papers]) if all(p and p[m] is not None for p in papers) else None
                for m in METRICS}
        own = table.means.get(config) if table.name == "ablation" else table.means.get("all")
        res[config] = {"n_rows": len(rs), "scenes": scenes, "ours": {m: _mean([r[m] for r in rs]) for m in METRICS},
                       "paper_same_scenes": same, "paper_table_mean": own}
    return res


def _fmt(metric: str, value: Any, unit: str) -> str:
    if value is None:
        return "-"
    if metric == "chamfer" and unit != "mm":
        return f"{value * 1e3:.2f}"
    return f"{value:.3f}" if metric == "ssim" else f"{value:.2f}"


def markdown(table: PaperTable, result: dict[str, Any]) -> str:
    """reproduce.md: one line per row (ours | paper for each metric), the means per configuration, the machine and
    the command line."""
    rows, unit = result["rows"], table.chamfer_unit
    shown = [m for m in METRICS if any(r[m] is not None or (r["paper"] or {}).get(m) is not None for r in rows)]
    names = {"psnr": "PSNR dB", "ssim": "SSIM", "normal_mae_deg": "normal MAE deg",
             "chamfer": "Chamfer mm" if unit == "mm" else "Chamfer 1e-3"}
    m = result["machine"]
    lines = [f"# Reproducing {table.source}", "",
             f"Command: `{result['command']}`  ",
             f"Machine: {m['gpu'] or 'no GPU'}; CPU {m['cpu']} ({m['cpu_threads']} threads); torch {m['torch']}  ",
             f"Scale: {result['scale']} (preset {result['preset']}"
             + (f", {result['minutes']:g} min per run" if result["minutes"] else "")
             + (f", {result['max_steps']} steps per run" if result.get("max_steps") else "")
             + (")" if result["minutes"] or result.get("max_steps") else ", the preset's step schedule)"),
             ""]
    head = ["scene", "config", "seed", *[f"{names[x]} {w}" for x in shown for w in ("ours", "paper")], "minutes",
            "status"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        paper = r["paper"] or {}
        cells = [r["scene"], r["config"], str(r["seed"])]
        for x in shown:
            cells += [_fmt(x, r[x], unit), _fmt(x, paper.get(x), unit)]
        cells += [f"{r['seconds'] / 60:.1f}" if r["seconds"] is not None else "-", r["status"]]
        lines.append("| " + " | ".join(cells) + " |")
    mean = result["means"]
    if mean:
        lines += ["", "Means over scenes" + (" and seeds" if len({r["seed"] for r in rows}) > 1 else "")
                  + " per configuration (paper: over the same scenes, and the paper's own mean"
                  + (", Table 4, over its 8 scenes)" if table.name == "ablation" else " over all its scenes)"), ""]
        head = ["config", "rows", *[f"{names[x]} {w}" for x in shown for w in ("ours", "paper same", "paper all")]]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for config, s in mean.items():
            cells = [config, str(s["n_rows"])]
            for x in shown:
                cells += [_fmt(x, s["ours"][x], unit), _fmt(x, s["paper_same_scenes"][x], unit),
                          _fmt(x, (s["paper_table_mean"] or {}).get(x), unit)]
            lines.append("| " + " | ".join(cells) + " |")
        groups = {g: v for g, v in table.means.items() if g != "all"} if table.name != "ablation" else {}
        if groups:
            lines += ["", "The paper's means per group: " + "; ".join(
                f"{g} " + ", ".join(f"{names[x]} {_fmt(x, v, unit)}" for x, v in ms.items())
                for g, ms in groups.items())]
    notes = [f"- {r['scene']} {r['config']} seed {r['seed']}: {n}" for r in rows for n in r.get("notes") or []]
    if notes:
        lines += ["", "Notes:", "", *notes]
    return "\n".join(lines) + "\n"


def _write(out: Path, table: PaperTable, result: dict[str, Any]) -> None:
    result["means"] = means(table, result["rows"])
    write_text_atomic(out / "reproduce.json", json.dumps(result, indent=2))
    write_text_atomic(out / "reproduce.md", markdown(table, result))
