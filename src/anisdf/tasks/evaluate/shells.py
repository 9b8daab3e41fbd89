"""The inner-shell check of eval: the share of a mesh's area in connected components no camera outside the mesh
can see, closed shells enclosed by other components.

An SDF learned from images is unconstrained inside the object, where no ray reaches, and can cross zero there;
marching cubes then adds closed shells that count against accuracy (extraction drops them with ``remove_inner``,
:func:`anisdf.export.mesh.fill_cavities`). The same detector runs here on the mesh: its surface is rasterised into a
voxel grid, the empty voxels not connected to the grid's faces are the enclosed pockets (``fill_cavities``), and a
component is an inner shell when none of its surface voxels touches the open outside.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

GRID = 256
"""Voxels along the longest side of the mesh's bounding box: shells closer than about 3 voxels (1.2% of that side)
to the surface around them count as seen."""


def component_labels(mesh: trimesh.Trimesh) -> tuple[np.ndarray, int]:
    """Connected component of each face through shared vertices (coincident vertices merged first, so a mesh with
    split vertices, e.g. read from a glb, gives the same components), and their count."""
    _, vid = np.unique(np.asarray(mesh.vertices), axis=0, return_inverse=True)
    f = vid.reshape(-1)[np.asarray(mesh.faces)]
    n = int(f.max()) + 1
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, vlabel = connected_components(graph, directed=False)
    _, labels = np.unique(vlabel[f[:, 0]], return_inverse=True)  # only components that have faces
    return labels.reshape(-1), int(labels.max()) + 1 if len(labels) else 0


def surface_points(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on every triangle on a barycentric grid of ``k`` steps per edge, ``k`` such that neighbouring points are
    at most ``spacing`` apart (so every point of the surface lies within ``spacing`` of one); returns the points and
    the index of the face each lies on."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    longest = np.max(np.linalg.norm(np.stack([e1, e2, e2 - e1], axis=1), axis=-1), axis=1)
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
    points, owners = [], []
    for k in np.unique(steps):
        ids = np.flatnonzero(steps == k)
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = i + j <= k
        a, b = i[keep] / k, j[keep] / k
        p = tri[ids, None, 0] + a[None, :, None] * e1[ids, None] + b[None, :, None] * e2[ids, None]
        points.append(p.reshape(-1, 3))
        owners.append(np.repeat(ids, len(a)))
    return np.concatenate(points), np.concatenate(owners)


def inner_shells(mesh: trimesh.Trimesh, grid: int = GRID) -> dict[str, float | int]:
    """How much of ``mesh`` lies in closed components that other components enclose, unseen from outside.

    Returns ``share`` (their area / the mesh's area), ``components`` (count) and ``inner_components``. The mesh is
    rasterised at ``grid`` voxels along its bounding box's longest side: every voxel the surface passes through is
    marked (points at most 0.9 voxel apart, each marked voxel grown by one), the unmarked voxels not connected to the
    grid's faces (6-connected) are enclosed (:func:`anisdf.export.mesh.fill_cavities`), and a component is seen when
    one of its marked voxels is a face-neighbour of the open outside.
    """
    from anisdf.export.mesh import fill_cavities

    labels, count = component_labels(mesh)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    result: dict[str, float | int] = {"share": 0.0, "components": count, "inner_components": 0}
    if count <= 1 or area.sum() <= 0:
        return result
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    pitch = float((hi - lo).max()) / grid
    pad = 3
    shape = tuple(int(n) for n in np.ceil((hi - lo) / pitch).astype(np.int64) + 1 + 2 * pad)
    points, owner = surface_points(mesh.vertices, mesh.faces, 0.9 * pitch)
    idx = np.clip(np.floor((points - lo) / pitch).astype(np.int64) + pad, 0, np.array(shape) - 1)
    marked = np.zeros(shape, dtype=bool)
    marked[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    full = np.ones((3, 3, 3), dtype=bool)
    wall = ndimage.binary_dilation(marked, structure=full)
    vol = np.where(wall, -1, 1).astype(np.int8)
    enclosed = fill_cavities(vol) < 0
    open_out = ~enclosed  # empty voxels connected to the grid's faces
    # a marked voxel whose grown wall touches the open outside by a face: within a face step then a 3x3x3 step of it
    face_step = ndimage.binary_dilation(open_out, structure=ndimage.generate_binary_structure(3, 1))
    reach = ndimage.binary_dilation(face_step, structure=full)
    seen = np.bincount(labels[owner], weights=reach[idx[:, 0], idx[:, 1], idx[:, 2]], minlength=count) > 0
    inner = ~seen
    result["share"] = float(area[inner[labels]].sum() / area.sum())
    result["inner_components"] = int(inner.sum())
    return result


def inner_shells_record(result: dict[str, float | int], grid: int = GRID) -> dict[str, object]:
    """eval.json's protocol entry for :func:`inner_shells`."""
    return {
        "components": result["components"], "inner_components": result["inner_components"], "grid": grid,
        "share": "area of the connected components no camera outside the mesh sees (closed shells enclosed by "
                 "other components: their surface voxels do not touch the outside of a voxel grid of the mesh's "
                 f"bounding box, {grid} voxels along its longest side) / the mesh's area",
    }
