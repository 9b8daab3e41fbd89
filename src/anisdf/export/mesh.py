"""Mesh operations: extraction from an SDF by marching cubes, clean-up, decimation, SDF normals, vertex colours
and saving.

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
import torch.nn.functional as F
import trimesh
from scipy import ndimage
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.model_components.interior import enclosed_pockets
from anisdf.utils.atomic import atomic_path

MeshFormat = Literal["ply", "obj", "glb"]
_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


def _grid_axes(lo: np.ndarray, hi: np.ndarray, resolution: int) -> tuple[np.ndarray, list[int]]:
    """Cubic voxels: the longest side of the box [lo, hi] gets ``resolution`` samples."""
    extent = hi - lo
    step = float(extent.max()) / (resolution - 1)
    counts = [max(2, int(math.ceil(float(e) / step - 1e-9)) + 1) for e in extent]
    return np.array([step, step, step]), counts


def _query(sdf_fn: Callable[[torch.Tensor], torch.Tensor], pts: torch.Tensor) -> torch.Tensor:
    val = sdf_fn(pts).reshape(-1)
    if val.shape[0] != pts.shape[0]:
        raise ValueError(f"sdf_fn returned {val.shape[0]} values for {pts.shape[0]} points")
    return val


def _check_finite(vol: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(vol)):
        bad = int((~np.isfinite(vol)).sum())
        raise AnisdfError(f"mesh extraction: the SDF is not finite at {bad} of {vol.size} grid points")
    return vol


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
        val = _query(sdf_fn, pts)
        out[x0 * plane + s : (x1 - 1) * plane + e] = val.float().cpu().numpy()
    vol = out.reshape(nx, ny, nz)
    return _check_finite(vol)


def _crossing_cells(vol: np.ndarray) -> np.ndarray:
    """[nx-1, ny-1, nz-1] bool: grid cells whose 8 corners are not all on one side of the surface."""
    inside = vol < 0
    any_in = np.zeros(tuple(n - 1 for n in vol.shape), dtype=bool)
    all_in = np.ones_like(any_in)
    for dx, dy, dz in _CORNERS:
        c = inside[dx : dx + any_in.shape[0], dy : dy + any_in.shape[1], dz : dz + any_in.shape[2]]
        any_in |= c
        all_in &= c
    return any_in & ~all_in


def _crossing_bounds(vol: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Index bounds (lo corner, hi corner) of the grid cells whose corners change sign, or None."""
    cells = np.argwhere(_crossing_cells(vol))
    if len(cells) == 0:
        return None
    return cells.min(axis=0), cells.max(axis=0) + 1


def _near_blocks(vol1: np.ndarray, lo1: np.ndarray, h1: float, lo: np.ndarray, step: np.ndarray,
                 counts: list[int], block: int) -> np.ndarray:
    """[bx, by, bz] bool: the ``block``^3 blocks of the fine grid that may hold the surface, judged from the
    coarse grid ``vol1`` (origin ``lo1``, spacing ``h1``): blocks that overlap a coarse point within 2 coarse
    cells of the zero level or a corner of a sign-changing coarse cell, dilated by one coarse cell."""
    near = np.abs(vol1) < 2.0 * h1
    cross = _crossing_cells(vol1)
    for dx, dy, dz in _CORNERS:
        near[dx : dx + cross.shape[0], dy : dy + cross.shape[1], dz : dz + cross.shape[2]] |= cross
    near = ndimage.binary_dilation(near, iterations=1)
    # summed-area table: "any near point in a box" in O(1) per block
    sat = np.pad(near.astype(np.int32).cumsum(0).cumsum(1).cumsum(2), ((1, 0), (1, 0), (1, 0)))
    ranges = []
    for a in range(3):
        i0 = np.arange(0, counts[a], block)
        i1 = np.minimum(i0 + block, counts[a]) - 1
        c0 = np.clip(np.floor((lo[a] + i0 * step[a] - lo1[a]) / h1), 0, vol1.shape[a] - 1).astype(np.int64)
        c1 = np.clip(np.ceil((lo[a] + i1 * step[a] - lo1[a]) / h1), 0, vol1.shape[a] - 1).astype(np.int64) + 1
        shape = [1, 1, 1]
        shape[a] = -1
        ranges.append((c0.reshape(shape), c1.reshape(shape)))
    (x0, x1), (y0, y1), (z0, z1) = ranges
    total = (sat[x1, y1, z1] - sat[x0, y1, z1] - sat[x1, y0, z1] - sat[x1, y1, z0]
             + sat[x0, y0, z1] + sat[x0, y1, z0] + sat[x1, y0, z0] - sat[x0, y0, z0])
    return total > 0


@torch.no_grad()
def _eval_grid_near(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    lo: np.ndarray,
    step: np.ndarray,
    counts: list[int],
    coarse: tuple[np.ndarray, np.ndarray, float],
    device: str | torch.device,
    chunk: int,
    progress: bool,
    desc: str,
    block: int = 4,
) -> np.ndarray:
    """Like :func:`_eval_grid`, but the SDF is queried only in blocks near the surface found by the coarse
    grid ``coarse = (vol1, lo1, h1)``; far blocks take the coarse value at their centre, whose sign is right
    there, so marching cubes finds the same cells and vertices as on the dense grid."""
    vol1, lo1, h1 = coarse
    near = _near_blocks(vol1, lo1, h1, lo, step, counts, block)
    nb = near.shape
    # far fill: nearest coarse value at each block's centre
    centres = []
    for a in range(3):
        c = lo[a] + (np.arange(nb[a]) * block + (block - 1) / 2) * step[a]
        centres.append(np.clip(np.rint((c - lo1[a]) / h1), 0, vol1.shape[a] - 1).astype(np.int64))
    fill = vol1[np.ix_(*centres)].astype(np.float32)
    vol = np.repeat(np.repeat(np.repeat(fill, block, 0), block, 1), block, 2)
    offs = torch.stack(torch.meshgrid(*[torch.arange(block)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    blocks = torch.from_numpy(np.argwhere(near))
    lo_t = torch.as_tensor(lo, dtype=torch.float32, device=device)
    step_t = torch.as_tensor(step, dtype=torch.float32, device=device)
    per = max(1, chunk // block**3)
    for b0 in tqdm(range(0, len(blocks), per), desc=desc, disable=not progress, leave=False, unit="chunk"):
        idx = (blocks[b0 : b0 + per, None, :] * block + offs[None]).reshape(-1, 3)
        pts = lo_t + idx.to(device).float() * step_t
        val = _query(sdf_fn, pts)
        i = idx.numpy()
        vol[i[:, 0], i[:, 1], i[:, 2]] = val.float().cpu().numpy()
    vol = np.ascontiguousarray(vol[: counts[0], : counts[1], : counts[2]])
    return _check_finite(vol)


def fill_cavities(vol: np.ndarray) -> np.ndarray:
    """Make enclosed pockets solid: outside voxels (SDF > 0) not connected to the grid's faces flip sign.

    An SDF learned from images is unconstrained inside the object, where no ray reaches, and can cross zero
    there; marching cubes then adds closed shells around such pockets that no camera outside can see, and that
    count against accuracy (on bunny_plastic, nerf-synthetic preset on an H100: a 130k-face inner shell and
    Chamfer 0.023). Pockets open to the outside, through any hole, are kept. Returns ``vol`` or a copy.
    """
    pocket = enclosed_pockets(vol > 0)  # 6-connected, so a pocket is not joined to the outside across an edge
    if not pocket.any():
        return vol
    out = vol.copy()
    out[pocket] = -out[pocket]
    return out


def _clip_to_sphere(vol: np.ndarray, lo: np.ndarray, step: np.ndarray, radius: float) -> np.ndarray:
    """The sampled SDF intersected with the ball of ``radius``: ``max(sdf, |x| - radius)`` (in place, by slabs)."""
    axes = [(lo[k] + np.arange(vol.shape[k]) * step[k]).astype(np.float32) for k in range(3)]
    yz2 = axes[1][:, None] ** 2 + axes[2][None, :] ** 2
    for i, x in enumerate(axes[0]):
        np.maximum(vol[i], np.sqrt(yz2 + x * x) - radius, out=vol[i])
    return vol


def extract_mesh(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    radius: float = 1.0,
    resolution: int = 512,
    device: str | torch.device = "cpu",
    chunk: int = 2**18,
    two_pass: bool = True,
    margin: float = 0.1,
    progress: bool = True,
    sparse: bool = True,
    keep_inner: bool = False,
    region: Literal["sphere", "box"] = "sphere",
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> trimesh.Trimesh:
    """Marching-cubes mesh of the zero level set of ``sdf_fn`` inside the box [-radius, radius]^3 (and inside the box
    ``bounds`` = (lo, hi) when given: the mesh is open where the surface crosses it).

    ``region="sphere"`` (default) keeps only the part inside the sphere of ``radius``, the region training marches
    rays through (ray_marching.py): the SDF is read as ``max(sdf, |x| - radius)``, so the box's corners, which no
    ray ever supervised, cannot carry floaters, and a surface cut by the sphere is closed by a cap on it.
    ``region="box"`` meshes the whole box as it is.

    ``sdf_fn`` maps [M, 3] points to [M] (or [M, 1]) signed distances, negative inside; it is called
    under ``torch.no_grad`` on chunks of ``chunk`` points on ``device``.

    Two passes (``two_pass=True``): the whole box at ``max(64, resolution // 4)`` samples per side finds
    the bounding box of the cells the surface crosses; pass 2 samples that box, padded by ``margin`` of
    its largest side (and clipped to the box), with cubic voxels and ``resolution`` samples along its
    longest side. Surface parts thinner than a pass-1 voxel that show no sign change at pass 1 and lie
    outside the padded box are lost; use ``two_pass=False`` to sample the whole box at ``resolution``.
    ``sparse`` (pass 2 only) queries the SDF only in 4^3 blocks near the pass-1 surface, several times fewer
    points for the same triangles; ``sparse=False`` is the dense reference.
    Surfaces around pockets enclosed inside the object are dropped (:func:`fill_cavities`) unless
    ``keep_inner=True``.

    Raises :class:`AnisdfError` if the SDF has no sign change in the box or is not finite.
    """
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2, got {resolution}")
    if region not in ("sphere", "box"):
        raise ValueError(f"region must be 'sphere' or 'box', got {region!r}")
    sphere = region == "sphere"
    box_lo = np.full(3, -float(radius))
    box_hi = np.full(3, float(radius))
    crop = bounds
    if crop is not None:
        box_lo = np.maximum(box_lo, np.asarray(crop[0], dtype=np.float64))
        box_hi = np.minimum(box_hi, np.asarray(crop[1], dtype=np.float64))
        if not np.all(box_hi > box_lo):
            raise AnisdfError("mesh extraction: the box to mesh does not overlap the region of interest")
    res1 = min(resolution, max(64, resolution // 4)) if two_pass else resolution
    step, counts = _grid_axes(box_lo, box_hi, res1)
    vol = _eval_grid(sdf_fn, box_lo, step, counts, device, chunk, progress, f"mesh pass 1 ({res1}^3)")
    if sphere:
        inside = _clip_to_sphere(np.zeros_like(vol), box_lo, step, radius) <= 0
        seen = vol[inside] if inside.any() else vol
        vol = _clip_to_sphere(vol, box_lo, step, radius)
    else:
        seen = vol
    bounds = _crossing_bounds(vol)
    if bounds is None or not float(seen.min()) < 0.0 < float(seen.max()):
        lo_v, hi_v = float(seen.min()), float(seen.max())
        where = f"the sphere of radius {radius}" if sphere else f"the box [-{radius}, {radius}]^3"
        if crop is not None:
            where = f"the box {np.round(box_lo, 4).tolist()} - {np.round(box_hi, 4).tolist()}" + (
                f" within the sphere of radius {radius}" if sphere else "")
        raise AnisdfError(
            f"mesh extraction: no surface found in {where} "
            f"(the SDF does not change sign; its values range from {lo_v:.4g} to {hi_v:.4g})"
        )
    lo = box_lo
    if two_pass and res1 < resolution:
        lo = box_lo + bounds[0] * step
        hi = box_lo + bounds[1] * step
        pad = margin * float((hi - lo).max())
        lo = np.maximum(lo - pad, box_lo)
        hi = np.minimum(hi + pad, box_hi)
        coarse = (vol, box_lo, float(step[0]))
        step, counts = _grid_axes(lo, hi, resolution)
        desc = f"mesh pass 2 ({resolution})"
        vol = (_eval_grid_near(sdf_fn, lo, step, counts, coarse, device, chunk, progress, desc) if sparse
               else _eval_grid(sdf_fn, lo, step, counts, device, chunk, progress, desc))
        if sphere:
            vol = _clip_to_sphere(vol, lo, step, radius)
        if _crossing_bounds(vol) is None:  # cannot happen for a deterministic SDF; keep the message clear
            raise AnisdfError("mesh extraction: the surface found in pass 1 vanished in pass 2")
    if not keep_inner:
        vol = fill_cavities(vol)
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


def decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """Quadric edge-collapse decimation to about ``faces`` triangles (fast-simplification, which refuses collapses
    that flip a triangle, so thin parts keep their volume); meshes already small enough are returned as they are."""
    if len(mesh.faces) <= faces:
        return mesh
    import fast_simplification

    v, f = fast_simplification.simplify(np.asarray(mesh.vertices, dtype=np.float32),
                                        np.asarray(mesh.faces, dtype=np.int64), target_count=int(faces))
    out = trimesh.Trimesh(vertices=v, faces=f, process=True)
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    return out


@torch.no_grad()
def sdf_normals(model, points: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
    """Unit SDF gradients of ``model`` at ``points`` [M, 3] (normalised frame)."""
    out = []
    for s in range(0, len(points), chunk):
        g = model.geometry.query(points[s:s + chunk], create_graph=False, fd_eps=model.fd_eps()).grad
        out.append(F.normalize(g, dim=-1))
    return torch.cat(out) if out else points.new_zeros(0, 3)


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
