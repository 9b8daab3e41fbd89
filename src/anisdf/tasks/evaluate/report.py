"""Evaluation reports: ``report.html`` (tables, and the figures people look at) and a ``report.md`` with the same
numbers.

The figures (:mod:`.figures`) are embedded in the page as PNG data; the per-view panels it shows are linked by
paths relative to the page, so the run folder can be moved or copied whole.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.atomic import write_text_atomic

log = logging.getLogger("anisdf")

WORST_VIEWS = 3

_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin-bottom: 1.5em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; }
td:first-child, th:first-child { text-align: left; }
tr.mean td { font-weight: bold; background: #f6f6f6; }
figure { margin: 0 0 1em 0; }
img { max-width: 100%; image-rendering: pixelated; }
img.plot { image-rendering: auto; }
div.panels { display: flex; flex-wrap: wrap; gap: 1em; }
"""


@dataclass
class FigureSection:
    """A report section: a heading, a figure (PNG bytes, embedded; None: the note alone says why there is none),
    a note under it, and panels (image file, caption) shown below, linked relative to the report."""

    title: str
    anchor: str
    png: bytes | None
    note: str
    panels: list[tuple[Path, str]] = field(default_factory=list)


def format_value(v: Any) -> str:
    """Numbers for tables: floats with 4 decimals, tiny ones (|v| < 0.01, e.g. Chamfer) in scientific form."""
    if isinstance(v, bool) or v is None:
        return "-" if v is None else str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if v != 0.0 and abs(v) < 0.01:
            return f"{v:.4e}"
        return f"{v:.4f}"
    try:  # numpy / torch scalars
        return format_value(v.item())
    except AttributeError:
        return str(v)


def _columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    cols: list[str] = []
    for r in rows:
        cols.extend(k for k in r if k not in cols)
    return cols


def _mean_row(rows: Sequence[dict[str, Any]], cols: list[str]) -> dict[str, Any] | None:
    """Means of the numeric columns present in every row (the first column is labelled 'mean')."""
    if len(rows) < 2:
        return None
    out: dict[str, Any] = {cols[0]: "mean"}
    found = False
    for c in cols[1:]:
        vals = [r.get(c) for r in rows]
        if all(isinstance(v, int | float) and not isinstance(v, bool) for v in vals):
            out[c] = sum(float(v) for v in vals) / len(vals)
            found = True
    return out if found else None


def _rel(path: Path, out_dir: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), out_dir.resolve())).as_posix()


def _html_table(rows: Sequence[dict[str, Any]], cols: list[str], mean: dict[str, Any] | None) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    lines = [f"<table>\n<tr>{head}</tr>"]
    for r in rows:
        lines.append(
            "<tr>" + "".join(f"<td>{html.escape(format_value(r.get(c)))}</td>" for c in cols) + "</tr>"
        )
    if mean is not None:
        cells = "".join(f"<td>{html.escape(format_value(mean.get(c)))}</td>" for c in cols)
        lines.append(f'<tr class="mean">{cells}</tr>')
    lines.append("</table>")
    return "\n".join(lines)


def _md_table(rows: Sequence[dict[str, Any]], cols: list[str], mean: dict[str, Any] | None) -> str:
    def esc(s: str) -> str:
        return s.replace("|", "\\|")

    lines = ["| " + " | ".join(esc(c) for c in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in [*rows, *([mean] if mean is not None else [])]:
        lines.append("| " + " | ".join(esc(format_value(r.get(c))) for c in cols) + " |")
    return "\n".join(lines)


def _html_section(section: FigureSection, out_dir: Path) -> str:
    parts = [f'<section id="{html.escape(section.anchor, quote=True)}">', f"<h2>{html.escape(section.title)}</h2>"]
    if section.png is not None:
        data = base64.b64encode(section.png).decode("ascii")
        parts.append(f'<figure><img class="plot" src="data:image/png;base64,{data}" '
                     f'alt="{html.escape(section.title, quote=True)}"><figcaption>{html.escape(section.note)}'
                     "</figcaption></figure>")
    else:
        parts.append(f"<p>{html.escape(section.note)}</p>")
    if section.panels:
        parts.append('<div class="panels">')
        for path, caption in section.panels:
            src = html.escape(_rel(path, out_dir), quote=True)
            parts.append(f'<figure><img src="{src}" alt="{src}"><figcaption>{html.escape(caption)}</figcaption>'
                         "</figure>")
        parts.append("</div>")
    parts.append("</section>")
    return "\n".join(parts)


def flatten(d: dict[str, Any], prefix: str = "") -> list[dict[str, Any]]:
    """``{"a": {"b": 1}, "c": [1, 2]}`` -> rows ``{"setting": "a.b", "value": 1}``, ``{"setting": "c", ...}``; a list
    of objects ``{"d": [{"e": 1}]}`` gives ``d.0.e``."""
    rows: list[dict[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            rows.extend(flatten(v, key + "."))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, x in enumerate(v):
                rows.extend(flatten(x, f"{key}.{i}."))
        else:
            rows.append({"setting": key, "value": ", ".join(map(str, v)) if isinstance(v, list | tuple) else v})
    return rows


def write_report(
    out_dir: Path,
    metrics: dict[str, Any],
    per_view: list[dict[str, Any]],
    images: list[Path],
    title: str = "anisdf evaluation",
    protocol: dict[str, Any] | None = None,
    figures: Sequence[FigureSection] = (),
    paths: tuple[Path, Path] | None = None,
) -> tuple[Path, Path]:
    """Write ``out_dir/report.html`` and ``out_dir/report.md`` (or the two ``paths`` in ``out_dir``); returns both
    paths.

    ``metrics``: headline numbers (e.g. ``{"psnr": 33.4, "ssim": 0.96, "chamfer": 4.9e-3}``).
    ``per_view``: one dict per test view, e.g.
    ``{"view": "r_0", "psnr": ..., "ssim": ..., "normal_mae": ...}``
    (columns are the union of keys in first-seen order; a mean row is added for columns numeric in
    every row). ``images``: side-by-side pictures, referenced by path relative to ``out_dir``.
    ``protocol``: how the numbers were measured (nested dict, shown flattened as "a.b" rows).
    ``figures``: sections shown in report.html after the summary (report.md keeps to the tables).
    Both files are written atomically.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cols = _columns(per_view)
    mean = _mean_row(per_view, cols) if cols else None
    head_rows = [{"metric": k, "value": v} for k, v in metrics.items() if not isinstance(v, dict)]
    head_rows += [{"metric": r["setting"], "value": r["value"]}  # nested scores (relight) as "relight.studio.psnr"
                  for r in flatten({k: v for k, v in metrics.items() if isinstance(v, dict)})]
    html_path, md_path = paths or (out_dir / "report.html", out_dir / "report.md")
    rels = [_rel(Path(p), out_dir) for p in images]

    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<h2>Summary</h2>",
        _html_table(head_rows, ["metric", "value"], None) if head_rows else "<p>No metrics.</p>",
        *(_html_section(f, out_dir) for f in figures),
    ]
    proto_rows = flatten(protocol) if protocol else []
    if proto_rows:
        parts += ["<h2>Protocol</h2>", _html_table(proto_rows, ["setting", "value"], None)]
    parts += [
        "<h2>Per view</h2>",
        _html_table(per_view, cols, mean) if cols else "<p>No per-view results.</p>",
    ]
    if rels:
        parts.append("<h2>Images</h2>")
        for rel in rels:
            src = html.escape(rel, quote=True)
            parts.append(
                f'<figure><img src="{src}" alt="{src}"><figcaption>{html.escape(rel)}</figcaption></figure>'
            )
    parts.append("</body></html>\n")
    html_path = write_text_atomic(html_path, "\n".join(parts))

    md = [f"# {title}", "", "## Summary", ""]
    md.append(_md_table(head_rows, ["metric", "value"], None) if head_rows else "No metrics.")
    if proto_rows:
        md += ["", "## Protocol", "", _md_table(proto_rows, ["setting", "value"], None)]
    md += ["", "## Per view", ""]
    md.append(_md_table(per_view, cols, mean) if cols else "No per-view results.")
    if rels:
        md += ["", "## Images", ""]
        md += [f"![{Path(rel).stem}]({rel.replace(' ', '%20')})" for rel in rels]
    md_path = write_text_atomic(md_path, "\n".join(md) + "\n")
    return html_path, md_path


def read_log(path: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The training lines (``psnr`` / ``total`` of the step's batch) and validation lines (``val_psnr``) of a
    log.jsonl, each by step; a step logged twice (a resumed run repeats the steps after its last checkpoint) keeps
    its last line, and lines that are not JSON objects (one cut short by a kill) are skipped."""
    train: dict[float, dict[str, Any]] = {}
    val: dict[float, dict[str, Any]] = {}
    for line in path.read_text(errors="replace").splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(row, dict) or not isinstance(row.get("step"), int | float):
            continue
        if "val_psnr" in row:
            val[row["step"]] = row
        if "psnr" in row or "total" in row:
            train[row["step"]] = row
    return [train[k] for k in sorted(train)], [val[k] for k in sorted(val)]


def training_section(run: Path) -> FigureSection:
    """The training curve from RUN/log.jsonl and RUN/val/psnr.jsonl, or a line saying why there is none."""
    from anisdf.tasks.evaluate.figures import training_curve

    rd = RunDir(run)
    path, val_path = rd.log, rd.validation_log
    title, anchor = "Training", "training-curve"
    if not path.is_file():
        return FigureSection(title, anchor, None, f"No training curve: this run has no {path.name}.")
    train, val = read_log(path)
    if val_path.is_file():
        val = read_log(val_path)[1]
    if not train and not val:
        return FigureSection(title, anchor, None, f"No training curve: {path.name} has no training lines.")
    note = f"Train PSNR (of each logged step's batch) and loss from {path.name}, {len(train)} lines; "
    note += (f"validation: PSNR of the first test view ({val_path.parent.name}/{val_path.name}), {len(val)} lines."
             if val else "no validation yet.")
    return FigureSection(title, anchor, training_curve(train, val), note)


def worst_views(per_view: Sequence[dict[str, Any]], k: int = WORST_VIEWS) -> list[int]:
    """Indices of the ``k`` views with the lowest PSNR, worst first."""
    return sorted(range(len(per_view)), key=lambda i: float(per_view[i]["psnr"]))[:k]


def per_view_section(per_view: Sequence[dict[str, Any]], images: Sequence[Path]) -> FigureSection | None:
    """PSNR per view as a bar chart, with the worst views' panels under it; None without views."""
    from anisdf.tasks.evaluate.figures import per_view_psnr

    if not per_view or not all("psnr" in r for r in per_view):
        return None
    worst = worst_views(per_view)
    mean = float(np.mean([float(r["psnr"]) for r in per_view]))
    panels = [(Path(images[i]), f"view {per_view[i].get('view', i)} ({per_view[i].get('image', '')}): PSNR "
               f"{float(per_view[i]['psnr']):.2f} dB") for i in worst if i < len(images)]
    note = (f"PSNR of each of the {len(per_view)} views, mean {mean:.2f} dB (dashed); in red the "
            f"{len(worst)} lowest, whose panels follow.")
    return FigureSection("PSNR per view", "per-view-psnr", per_view_psnr(per_view, worst), note, panels)


def mesh_section(run: Path, mesh_path: Path | None, up: np.ndarray | None,
                 inner_shell_share: float | None = None) -> FigureSection:
    """A turntable of the mesh eval scored, else of the one in the run folder, else a line saying there is none;
    the note gives the scored mesh's ``inner_shell_share`` when known."""
    from anisdf.eval.metrics import load_mesh
    from anisdf.tasks.evaluate.figures import TURNTABLE_VIEWS, turntable

    title, anchor = "Mesh", "mesh-turntable"
    path = mesh_path if mesh_path is not None else RunDir(run).existing_mesh()
    if path is None:
        return FigureSection(title, anchor, None, "No mesh in this run folder (anisdf extract-mesh RUN writes one).")
    try:
        mesh = load_mesh(path)
    except AnisdfError as e:
        log.warning("report: no turntable of %s (%s)", path, e)
        return FigureSection(title, anchor, None, f"No turntable: {path.name} could not be read.")
    scored = "scored by eval" if mesh_path is not None else "in the run folder, not scored"
    note = (f"{path.name} ({scored}; {len(mesh.faces):,} faces), {TURNTABLE_VIEWS} views around the cameras' "
            "vertical axis, shaded by face normal.")
    if inner_shell_share is not None:
        note += (f" Inner shells (closed components no camera outside sees): {100.0 * inner_shell_share:.1f}% of its "
                 "area.")
    return FigureSection(title, anchor, turntable(mesh, up), note)


def write_run_report(run: Path, metrics: dict[str, Any], per_view: list[dict[str, Any]], images: list[Path],
                     protocol: dict[str, Any] | None = None, up: np.ndarray | None = None) -> tuple[Path, Path]:
    """RUN/report.html and RUN/report.md of an evaluation: :func:`write_report`'s tables, with the training curve
    (RUN/log.jsonl), PSNR per view with the worst views' panels (``images``, one per row of ``per_view``) and a
    turntable of the mesh (``metrics["mesh"]``, the one eval scored, else the run folder's) around ``up`` (None:
    +z)."""
    run = Path(run)
    rd = RunDir(run)
    sections = [training_section(run), per_view_section(per_view, images),
                mesh_section(run, Path(metrics["mesh"]) if metrics.get("mesh") else None, up,
                             metrics.get("inner_shell_share"))]
    return write_report(run, metrics, per_view, images, protocol=protocol,
                        figures=[s for s in sections if s is not None], paths=(rd.report_html, rd.report_md))
