"""Evaluation reports: a small self-contained ``report.html`` and a ``report.md`` with the same numbers."""

from __future__ import annotations

import html
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from anisdf.utils.atomic import write_text_atomic

_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin-bottom: 1.5em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; }
td:first-child, th:first-child { text-align: left; }
tr.mean td { font-weight: bold; background: #f6f6f6; }
figure { margin: 0 0 1em 0; }
img { max-width: 100%; image-rendering: pixelated; }
"""


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


def flatten(d: dict[str, Any], prefix: str = "") -> list[dict[str, Any]]:
    """``{"a": {"b": 1}, "c": [1, 2]}`` -> rows ``{"setting": "a.b", "value": 1}``, ``{"setting": "c", ...}``."""
    rows: list[dict[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            rows.extend(flatten(v, key + "."))
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
) -> tuple[Path, Path]:
    """Write ``out_dir/report.html`` and ``out_dir/report.md``; returns both paths.

    ``metrics``: headline numbers (e.g. ``{"psnr": 33.4, "ssim": 0.96, "chamfer": 4.9e-3}``).
    ``per_view``: one dict per test view, e.g.
    ``{"view": "r_0", "psnr": ..., "ssim": ..., "normal_mae": ...}``
    (columns are the union of keys in first-seen order; a mean row is added for columns numeric in
    every row). ``images``: side-by-side pictures, referenced by path relative to ``out_dir``.
    ``protocol``: how the numbers were measured (nested dict, shown flattened as "a.b" rows).
    Both files are written atomically.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cols = _columns(per_view)
    mean = _mean_row(per_view, cols) if cols else None
    head_rows = [{"metric": k, "value": v} for k, v in metrics.items()]
    rels = [_rel(Path(p), out_dir) for p in images]

    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<h2>Summary</h2>",
        _html_table(head_rows, ["metric", "value"], None) if head_rows else "<p>No metrics.</p>",
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
    html_path = write_text_atomic(out_dir / "report.html", "\n".join(parts))

    md = [f"# {title}", "", "## Summary", ""]
    md.append(_md_table(head_rows, ["metric", "value"], None) if head_rows else "No metrics.")
    if proto_rows:
        md += ["", "## Protocol", "", _md_table(proto_rows, ["setting", "value"], None)]
    md += ["", "## Per view", ""]
    md.append(_md_table(per_view, cols, mean) if cols else "No per-view results.")
    if rels:
        md += ["", "## Images", ""]
        md += [f"![{Path(rel).stem}]({rel.replace(' ', '%20')})" for rel in rels]
    md_path = write_text_atomic(out_dir / "report.md", "\n".join(md) + "\n")
    return html_path, md_path
