"""The report's figures, drawn with matplotlib into PNG bytes: the training curve, PSNR per view, a mesh turntable.

Figures are made with :class:`matplotlib.figure.Figure` and saved by the Agg renderer, without pyplot: nothing
changes matplotlib's global state (a notebook's backend stays as it is) and no window opens.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure

TURNTABLE_VIEWS = 8
TURNTABLE_FACES = 20_000
"""A larger mesh is decimated to about this many faces before it is drawn (matplotlib sorts and fills each one)."""
_MESH_COLOR = np.array([0.72, 0.76, 0.84])


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def _time_axis(seconds: Sequence[float]) -> tuple[float, str]:
    """Divisor and label of the time axis: seconds, minutes or hours by the run's length."""
    longest = max(seconds, default=0.0)
    if longest >= 3 * 3600:
        return 3600.0, "training time (h)"
    if longest >= 180:
        return 60.0, "training time (min)"
    return 1.0, "training time (s)"


def training_curve(train: Sequence[dict[str, Any]], val: Sequence[dict[str, Any]]) -> bytes:
    """PSNR (train, and validation where present) and loss against steps (left) and training time (right)."""
    fig = Figure(figsize=(10, 6), layout="constrained")
    axes = fig.subplots(2, 2, sharex="col")
    scale, time_label = _time_axis([float(r["time"]) for r in [*train, *val] if "time" in r])
    for col, x_key in enumerate(("step", "time")):
        div = 1.0 if x_key == "step" else scale

        def series(rows: Sequence[dict[str, Any]], key: str, x_key: str = x_key, div: float = div):
            pts = [(float(r[x_key]) / div, float(r[key])) for r in rows if x_key in r and key in r]
            return ([p[0] for p in pts], [p[1] for p in pts]) if pts else ([], [])

        ax_psnr, ax_loss = axes[0, col], axes[1, col]
        x, y = series(train, "psnr")
        if x:
            ax_psnr.plot(x, y, lw=1.0, color="tab:blue", label="train (batch)")
        x, y = series(val, "val_psnr")
        if x:
            ax_psnr.plot(x, y, "o-", ms=3, lw=1.2, color="tab:orange", label="validation (first test view)")
        ax_psnr.set_ylabel("PSNR (dB)")
        ax_psnr.grid(alpha=0.3)
        if ax_psnr.has_data():
            ax_psnr.legend(loc="lower right", fontsize=8)
        x, y = series(train, "total")
        if x:
            ax_loss.plot(x, y, lw=1.0, color="tab:green")
            if min(y) > 0:
                ax_loss.set_yscale("log")
        ax_loss.set_ylabel("training loss (total)")
        ax_loss.set_xlabel("step" if x_key == "step" else time_label)
        ax_loss.grid(alpha=0.3, which="both")
    return png_bytes(fig)


def per_view_psnr(per_view: Sequence[dict[str, Any]], worst: Sequence[int]) -> bytes:
    """PSNR of each view as a bar (the ``worst`` views' bars in red) and the mean as a dashed line."""
    values = [float(r["psnr"]) for r in per_view]
    n = len(values)
    fig = Figure(figsize=(min(max(6.0, 0.28 * n + 2.0), 16.0), 3.4), layout="constrained")
    ax = fig.subplots()
    colors = ["tab:red" if i in set(worst) else "tab:blue" for i in range(n)]
    finite = [v for v in values if math.isfinite(v)]
    ax.bar(range(n), [v if math.isfinite(v) else 0.0 for v in values], color=colors, width=0.8)
    mean = float(np.mean(values))
    ax.axhline(mean, color="k", ls="--", lw=1.0, label=f"mean {mean:.2f} dB")
    if finite:
        lo, hi = min(finite), max(finite)
        pad = max(0.5, 0.15 * (hi - lo))
        ax.set_ylim(max(0.0, lo - 3 * pad), hi + pad)
    ax.set_xlabel("view")
    ax.set_ylabel("PSNR (dB)")
    if n <= 40:
        ax.set_xticks(range(n), [str(r.get("view", i)) for i, r in enumerate(per_view)], fontsize=8)
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    ax.grid(axis="y", alpha=0.3)
    return png_bytes(fig)


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering on a grid, coarsened until at most ``max_faces`` faces remain (the decimation used when
    fast-simplification is not installed)."""
    lo = vertices.min(0)
    extent = float((vertices.max(0) - lo).max()) or 1.0
    cells = max(int(math.sqrt(max_faces / 3.0)), 2)
    while True:
        key = np.floor((vertices - lo) / extent * (cells - 1e-6)).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        f = inverse[faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)  # faces merged into one
        f = f[np.sort(keep)]
        if len(f) <= max_faces or cells <= 2:
            sums = np.zeros((len(first), 3))
            np.add.at(sums, inverse, vertices)
            return sums / np.bincount(inverse, minlength=len(first))[:, None], f
        cells = max(int(cells * 0.8), 2)


def decimate(mesh, max_faces: int = TURNTABLE_FACES):
    """``mesh`` (trimesh) with at most about ``max_faces`` faces: the export's quadric decimation
    (:func:`anisdf.export.mesh.decimate`) when fast-simplification is installed (anisdf[export]), else vertex
    clustering."""
    import trimesh

    from anisdf.export.mesh import decimate as quadric_decimate

    if len(mesh.faces) <= max_faces:
        return mesh
    try:
        return quadric_decimate(mesh, max_faces)
    except ImportError:
        v, f = cluster_vertices(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), max_faces)
        return trimesh.Trimesh(v, f, process=False)


def _upright(vertices: np.ndarray, up: np.ndarray | None) -> np.ndarray:
    """``vertices`` in a frame whose z axis is ``up`` (None: z already is)."""
    if up is None:
        return vertices
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - np.dot(helper, u) * u
    e1 /= np.linalg.norm(e1)
    return vertices @ np.stack([e1, np.cross(u, e1), u]).T


def turntable(mesh, up: np.ndarray | None = None, n_views: int = TURNTABLE_VIEWS, elevation: float = 20.0,
              max_faces: int = TURNTABLE_FACES) -> bytes:
    """``n_views`` views of ``mesh`` around its vertical axis ``up`` (None: +z) as one strip, each face shaded by
    its normal against a light beside the eye."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    mesh = decimate(mesh, max_faces)
    verts = _upright(np.asarray(mesh.vertices, dtype=np.float64), up)
    faces = np.asarray(mesh.faces)
    tris = verts[faces]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    lo, hi = verts.min(0), verts.max(0)
    centre, half = (lo + hi) / 2.0, float((hi - lo).max()) / 2.0 or 1.0
    fig = Figure(figsize=(2.4 * n_views, 2.6))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1, wspace=0)
    el = math.radians(elevation)
    for k in range(n_views):
        azim = 360.0 * k / n_views
        az = math.radians(azim)
        eye = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        light = eye + np.array([-math.sin(az), math.cos(az), 0.0]) * 0.4 + np.array([0.0, 0.0, 0.5])
        shade = 0.2 + 0.8 * np.abs(normals @ (light / np.linalg.norm(light)))  # two-sided
        ax = fig.add_subplot(1, n_views, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(tris, facecolors=shade[:, None] * _MESH_COLOR, edgecolors="none",
                                             linewidths=0.0, antialiased=False))
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            setter(c - half, c + half)
        ax.view_init(elev=elevation, azim=azim)
        ax.set_box_aspect((1, 1, 1), zoom=1.25)
        ax.set_axis_off()
    return png_bytes(fig)
