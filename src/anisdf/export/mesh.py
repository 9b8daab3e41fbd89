"""Mesh extraction from an SDF by marching cubes, clean-up, vertex colours and export.

Conventions: the SDF is negative inside; the extracted meshes are in the normalised frame the SDF is
queried in (use :func:`to_world` to go back to the dataset frame); triangles are wound counter-clockwise
seen from outside, so face normals point outward and the enclosed volume is positive.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import mcubes
import numpy as np
import torch
import trimesh
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.export.atomic import atomic_path

MeshFormat = Literal["ply", "obj", "glb"]


def _grid_axes(lo: np.ndarray, hi: np.ndarray, resolution: int) -> tuple[np.ndarray, list[int]]:
    """Cubic voxels: the longest side of the box [lo, hi] gets ``resolution`` samples."""
    extent = hi - lo
    step = float(extent.max()) / (resolution - 1)
    counts = [max(2, int(math.ceil(float(e) / step - 1e-9)) + 1) for e in extent]
    return np.array([step, step, step]), counts


@torch.no_grad()
def _eval_grid(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    lo: np.ndarray,
    step: np.ndarray,
    counts: list[int],
    device: str | torch.device,
    chunk: int,
    progress: bool,
    desc: str,
) -> np.ndarray:
    """SDF values on the grid ``lo + step * (i, j, k)``, shape ``counts`` (indexing 'ij': x, y, z)."""
    nx, ny, nz = counts
    plane = ny * nz
    out = np.empty(nx * plane, dtype=np.float32)
    axes = [
        float(lo[a]) + torch.arange(n, device=device, dtype=torch.float32) * float(step[a])
        for a, n in enumerate(counts)
    ]
    yz = torch.stack(torch.meshgrid(axes[1], axes[2], indexing="ij"), dim=-1).reshape(-1, 2)
    # batches of whole x-slices when a slice fits in a chunk, else pieces of one slice
    if plane <= chunk:
        per = chunk // plane
        batches = [(x0, min(x0 + per, nx), 0, plane) for x0 in range(0, nx, per)]
    else:
        batches = [(x0, x0 + 1, s, min(s + chunk, plane)) for x0 in range(nx) for s in range(0, plane, chunk)]
    for x0, x1, s, e in tqdm(batches, desc=desc, disable=not progress, leave=False, unit="chunk"):
        k = x1 - x0
        xs = axes[0][x0:x1].repeat_interleave(e - s)[:, None]
        pts = torch.cat([xs, yz[s:e].repeat(k, 1)], dim=-1)
        val = sdf_fn(pts).reshape(-1)
        if val.shape[0] != pts.shape[0]:
            raise ValueError(f"sdf_fn returned {val.shape[0]} values for {pts.shape[0]} points")
        out[x0 * plane + s : (x1 - 1) * plane + e] = val.float().cpu().numpy()
    vol = out.reshape(nx, ny, nz)
    if not np.all(np.isfinite(vol)):
        bad = int((~np.isfinite(vol)).sum())
        raise AnisdfError(f"mesh extraction: the SDF is not finite at {bad} of {vol.size} grid points")
    return vol


def _crossing_bounds(vol: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Index bounds (lo corner, hi corner) of the grid cells whose corners change sign, or None."""
    inside = vol < 0
    if inside.all() or not inside.any():
        return None
    # a cell (i, j, k) crosses the surface when its 8 corners are not all inside or all outside
    any_in = np.zeros(tuple(n - 1 for n in vol.shape), dtype=bool)
    all_in = np.ones_like(any_in)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                c = inside[dx : dx + any_in.shape[0], dy : dy + any_in.shape[1], dz : dz + any_in.shape[2]]
                any_in |= c
                all_in &= c
    cells = np.argwhere(any_in & ~all_in)
    if len(cells) == 0:
        return None
    return cells.min(axis=0), cells.max(axis=0) + 1


def extract_mesh(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    radius: float = 1.0,
    resolution: int = 512,
    device: str | torch.device = "cpu",
    chunk: int = 2**18,
    two_pass: bool = True,
    margin: float = 0.1,
    progress: bool = True,
) -> trimesh.Trimesh:
    """Marching-cubes mesh of the zero level set of ``sdf_fn`` inside the box [-radius, radius]^3.

    ``sdf_fn`` maps [M, 3] points to [M] (or [M, 1]) signed distances, negative inside; it is called
    under ``torch.no_grad`` on chunks of ``chunk`` points on ``device``.

    Two passes (``two_pass=True``): the whole box at ``max(64, resolution // 4)`` samples per side finds
    the bounding box of the cells the surface crosses; pass 2 samples that box, padded by ``margin`` of
    its largest side (and clipped to the box), with cubic voxels and ``resolution`` samples along its
    longest side. Surface parts thinner than a pass-1 voxel that show no sign change at pass 1 and lie
    outside the padded box are lost; use ``two_pass=False`` to sample the whole box at ``resolution``.

    Raises :class:`AnisdfError` if the SDF has no sign change in the box or is not finite.
    """
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2, got {resolution}")
    box_lo = np.full(3, -float(radius))
    box_hi = np.full(3, float(radius))
    res1 = min(resolution, max(64, resolution // 4)) if two_pass else resolution
    step, counts = _grid_axes(box_lo, box_hi, res1)
    vol = _eval_grid(sdf_fn, box_lo, step, counts, device, chunk, progress, f"mesh pass 1 ({res1}^3)")
    bounds = _crossing_bounds(vol)
    if bounds is None:
        lo_v, hi_v = float(vol.min()), float(vol.max())
        raise AnisdfError(
            f"mesh extraction: no surface found in the box [-{radius}, {radius}]^3 "
            f"(the SDF does not change sign; its values range from {lo_v:.4g} to {hi_v:.4g})"
        )
    lo = box_lo
    if two_pass and res1 < resolution:
        lo = box_lo + bounds[0] * step
        hi = box_lo + bounds[1] * step
        pad = margin * float((hi - lo).max())
        lo = np.maximum(lo - pad, box_lo)
        hi = np.minimum(hi + pad, box_hi)
        step, counts = _grid_axes(lo, hi, resolution)
        vol = _eval_grid(sdf_fn, lo, step, counts, device, chunk, progress, f"mesh pass 2 ({resolution})")
        if _crossing_bounds(vol) is None:  # cannot happen for a deterministic SDF; keep the message clear
            raise AnisdfError("mesh extraction: the surface found in pass 1 vanished in pass 2")
    # mcubes on the negated SDF (positive inside) gives outward (counter-clockwise) triangles.
    verts, faces = mcubes.marching_cubes(-vol, 0.0)
    if len(faces) == 0:
        raise AnisdfError("mesh extraction: marching cubes produced no triangles")
    verts = lo[None, :] + verts * step[None, :]
    return trimesh.Trimesh(vertices=verts, faces=faces.astype(np.int64), process=False)


def remove_floaters(mesh: trimesh.Trimesh, min_fraction: float = 0.01) -> trimesh.Trimesh:
    """Keep the connected components with at least ``min_fraction`` of the largest one's face count.

    Components are found through shared edges (vertex indices), so the mesh must have merged vertices,
    as marching cubes meshes do. Vertex colours are kept. Returns a new mesh.
    """
    n_faces = len(mesh.faces)
    if n_faces == 0:
        return mesh.copy()
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=n_faces)
    sizes = np.bincount(labels)
    keep_labels = sizes >= min_fraction * sizes.max()
    out = mesh.copy()
    out.update_faces(keep_labels[labels])
    out.remove_unreferenced_vertices()
    return out


@torch.no_grad()
def color_vertices(
    mesh: trimesh.Trimesh,
    color_fn: Callable[[torch.Tensor], torch.Tensor] | None,
    chunk: int = 2**18,
    device: str | torch.device = "cpu",
) -> trimesh.Trimesh:
    """Return a copy of ``mesh`` with uint8 RGBA vertex colours from ``color_fn``.

    ``color_fn`` maps [M, 3] vertex positions (in the frame the mesh is in, normally the normalised
    frame before :func:`to_world`) to [M, 3] RGB in [0, 1] (values outside are clipped). With
    ``color_fn=None`` the mesh is returned unchanged (as a copy).
    """
    out = mesh.copy()
    if color_fn is None:
        return out
    verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    rgb = np.empty((len(verts), 3), dtype=np.float32)
    for s in range(0, len(verts), chunk):
        c = color_fn(verts[s : s + chunk].to(device))
        rgb[s : s + chunk] = c.reshape(-1, 3).float().cpu().numpy()
    rgba = np.full((len(verts), 4), 255, dtype=np.uint8)
    rgba[:, :3] = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0).astype(np.uint8)
    out.visual = trimesh.visual.ColorVisuals(mesh=out, vertex_colors=rgba)
    return out


def to_world(mesh: trimesh.Trimesh, T: np.ndarray) -> trimesh.Trimesh:
    """Return a copy of ``mesh`` transformed by the 4x4 similarity ``T`` (normalised -> world).

    A transform with negative determinant (a reflection) reverses the triangle winding so that face
    normals stay outward; positive scale keeps it as it is.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"expected a 4x4 transform, got shape {T.shape}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("the transform's last row must be [0, 0, 0, 1]")
    out = mesh.copy()
    out.apply_transform(T)  # trimesh inverts the winding itself when det(T[:3, :3]) < 0
    return out


def save_mesh(mesh: trimesh.Trimesh, path: str | Path, fmt: MeshFormat | None = None) -> Path:
    """Write ``mesh`` to ``path`` as ply (binary), obj or glb, atomically; returns the path.

    ``fmt`` defaults to the file suffix. Vertex colours are written in all three formats (ply vertex
    properties, glTF COLOR_0, obj ``v x y z r g b``).
    """
    path = Path(path)
    fmt_s = (fmt or path.suffix.lstrip(".")).lower()
    if fmt_s not in ("ply", "obj", "glb"):
        raise AnisdfError(f"{path}: unsupported mesh format {fmt_s!r} (use ply, obj or glb)")
    with atomic_path(path) as tmp:
        if fmt_s == "obj":
            data = trimesh.exchange.obj.export_obj(mesh, include_color=True, include_normals=False)
            tmp.write_text(data, encoding="utf-8")
        else:
            mesh.export(tmp, file_type=fmt_s)
    return path
