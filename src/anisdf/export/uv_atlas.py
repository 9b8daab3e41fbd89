"""The UV atlas of a mesh: xatlas charts, computed on compact pieces of the mesh and packed into one square atlas."""

from __future__ import annotations

import math

import numpy as np

from anisdf.errors import AnisdfError

UNWRAP_PIECE_FACES = 2000
"""Faces per piece handed to xatlas: its chart computation grows faster than linearly with a mesh's size (a
200k-face mesh in one piece: 160 s on 2 CPU cores; in pieces of 2000 faces: 7-10 s, with fewer charts)."""


def _pieces(centroids: np.ndarray, idx: np.ndarray, per: int) -> list[np.ndarray]:
    """Faces ``idx`` split at the median of their centroids' widest axis, again and again, into pieces of at most
    ``per`` faces."""
    if len(idx) <= per:
        return [idx]
    p = centroids[idx]
    order = idx[np.argsort(p[:, int(np.argmax(np.ptp(p, axis=0)))], kind="stable")]
    half = len(order) // 2
    return _pieces(centroids, order[:half], per) + _pieces(centroids, order[half:], per)


def unwrap(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, size: int, padding: int,
           piece_faces: int = UNWRAP_PIECE_FACES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xatlas charts packed into one ``size`` x ``size`` atlas: ``vmapping`` (original vertex of each new one),
    triangles, UVs in [0, 1] (texel ``(i, j)`` of row ``j`` from the top covers ``[i, i + 1] / size x
    [j, j + 1] / size``).

    The mesh goes to xatlas as compact pieces of ``piece_faces`` faces (:data:`UNWRAP_PIECE_FACES`), charted each
    on its own and packed together. xatlas is asked for one atlas of whatever size a texel density aimed at ``size``
    (about 60% of the atlas covered) needs, with ``padding + 1`` texels between charts, and the UVs are scaled so
    that the atlas's longer side is ``size``; packed again, denser, only when that scale would leave less than
    ``padding`` texels between charts."""
    import xatlas

    pos = np.ascontiguousarray(vertices, dtype=np.float32)
    tris = np.asarray(faces, dtype=np.int64)
    nrm = np.ascontiguousarray(normals, dtype=np.float32)
    corner = pos[tris]
    area = 0.5 * float(np.linalg.norm(np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]), axis=1).sum())
    if not area > 0:
        raise AnisdfError("the mesh has no area to unwrap")
    pieces = []
    for part in _pieces(corner.mean(1), np.arange(len(tris)), max(int(piece_faces), 1)):
        used, local = np.unique(tris[part], return_inverse=True)
        pieces.append((used, np.ascontiguousarray(local.reshape(-1, 3), dtype=np.uint32)))
    texels_per_unit = math.sqrt(0.6 * size * size / area)
    gap = padding + 1
    for _ in range(4):
        atlas = xatlas.Atlas()
        for used, local in pieces:
            atlas.add_mesh(pos[used], local, normals=nrm[used])
        pack = xatlas.PackOptions()
        pack.resolution = 0  # one atlas, as large as the charts need at this density
        pack.padding = int(gap)
        pack.bilinear = True
        pack.texels_per_unit = float(texels_per_unit)
        atlas.generate(chart_options=xatlas.ChartOptions(), pack_options=pack)
        side = max(atlas.width, atlas.height)
        if side * padding <= size * gap:  # scaled to ``size``, the charts stay >= ``padding`` texels apart
            break
        texels_per_unit *= 0.95 * size / side
    else:
        raise AnisdfError(f"xatlas could not pack the charts into one {size}^2 atlas; use a larger --texture or "
                          "fewer --faces")
    vmaps, indices, uvs = [], [], []
    offset = 0
    for i, (used, _) in enumerate(pieces):
        vmapping, idx, uv = atlas[i]
        vmaps.append(used[vmapping.astype(np.int64)])
        indices.append(idx.astype(np.int64) + offset)
        uvs.append(uv)
        offset += len(vmapping)
    # xatlas divides by its atlas's width and height: UVs in units of the longer side, which becomes ``size``
    uv = np.concatenate(uvs) * np.array([atlas.width / side, atlas.height / side], dtype=np.float32)
    return np.concatenate(vmaps), np.concatenate(indices), uv.astype(np.float32)
