"""Texels of a texture that lie on a UV-mapped mesh: rasterisation in UV space, barycentrics, closest points of
triangles for the ring of texels just outside them, and bilinear lookups of one texture at another's texels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from anisdf.errors import AnisdfError


@dataclass
class Texels:
    """Texels of a ``size`` x ``size`` texture that lie on (or next to) a triangle: flat indices ``row * size +
    col``, the triangle, barycentrics [M, 3] (of the texel centre, or of the nearest point of the triangle for the
    ring outside it), and whether the centre lies inside."""

    size: int
    index: Tensor
    face: Tensor
    bary: Tensor
    inside: Tensor


def _bary2d(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = torch.where(den.abs() < 1e-20, torch.full_like(den, 1e-20), den)
    l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    return torch.stack([1.0 - l1 - l2, l1, l2], -1)


def _closest_on_triangle(p: Tensor, a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Barycentrics of the point of triangle (a, b, c) nearest to ``p`` (2D, batched)."""
    bary = _bary2d(p, a, b, c)
    inside = (bary >= 0).all(-1)
    best = bary.clone()
    best_d = torch.full((len(p),), float("inf"), dtype=p.dtype)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        va, vb = (a, b, c)[i], (a, b, c)[j]
        e = vb - va
        t = (((p - va) * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-20)).clamp(0, 1)
        q = va + t[:, None] * e
        d = ((p - q) ** 2).sum(-1)
        w = torch.zeros_like(bary)
        w[:, i], w[:, j] = 1.0 - t, t
        upd = (d < best_d) & ~inside
        best[upd], best_d[upd] = w[upd], d[upd]
    return best


def rasterize_uv(uvs: np.ndarray, faces: np.ndarray, size: int, ring: int = 2, chunk: int = 1 << 22) -> Texels:
    """The texels whose centres lie inside a UV triangle, plus those within ``ring`` texels of one."""
    from scipy import ndimage

    p = torch.as_tensor(uvs, dtype=torch.float64) * size
    f = torch.as_tensor(faces, dtype=torch.long)
    tri = p[f]  # [F, 3, 2]
    lo = torch.ceil(tri.min(1).values - 0.5).clamp(0, size - 1).long()
    hi = torch.floor(tri.max(1).values - 0.5).clamp(0, size - 1).long()
    nc, nr = (hi[:, 0] - lo[:, 0] + 1).clamp_min(0), (hi[:, 1] - lo[:, 1] + 1).clamp_min(0)
    counts = nc * nr
    face_of = torch.full((size * size,), -1, dtype=torch.long)
    bary_of = torch.zeros(size * size, 3, dtype=torch.float64)
    ends = torch.cumsum(counts, 0)
    start = 0
    while start < len(f):
        base = int(ends[start - 1]) if start else 0
        stop = max(int(torch.searchsorted(ends, torch.tensor(base + chunk), right=True)), start + 1)
        cnt = counts[start:stop]
        owner = torch.repeat_interleave(torch.arange(start, stop), cnt)
        local = torch.arange(int(cnt.sum())) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
        col = lo[owner, 0] + local % nc[owner]
        row = lo[owner, 1] + local // nc[owner]
        centre = torch.stack([col, row], -1).double() + 0.5
        t = tri[owner]
        bary = _bary2d(centre, t[:, 0], t[:, 1], t[:, 2])
        ok = (bary >= -1e-9).all(-1)
        idx = (row * size + col)[ok]
        face_of[idx] = owner[ok]
        bary_of[idx] = bary[ok]
        start = stop
    # triangles too thin to hold a texel centre get the texel under their centroid (when no other triangle has it),
    # so that a small chart is never left to the texels of its neighbour across the padding
    holds = torch.zeros(len(f), dtype=torch.bool)
    holds[face_of[face_of >= 0]] = True
    thin = (~holds).nonzero()[:, 0]
    if len(thin):
        centroid = tri[thin].mean(1)
        cell = torch.floor(centroid).clamp(0, size - 1).long()
        idx = cell[:, 1] * size + cell[:, 0]
        free = face_of[idx] < 0
        thin, idx, cell = thin[free], idx[free], cell[free]
        t = tri[thin]
        face_of[idx] = thin
        bary_of[idx] = _closest_on_triangle(cell.double() + 0.5, t[:, 0], t[:, 1], t[:, 2])
    covered = (face_of >= 0).reshape(size, size).numpy()
    inside_idx = torch.from_numpy(np.flatnonzero(covered))
    if not len(inside_idx):
        raise AnisdfError("the UV atlas covers no texel centre; use a larger --texture")
    dist, nearest = ndimage.distance_transform_edt(~covered, return_indices=True)
    ring_mask = (~covered) & (dist <= ring + 1e-6)
    ring_idx = torch.from_numpy(np.flatnonzero(ring_mask))
    near_flat = torch.from_numpy((nearest[0] * size + nearest[1]).reshape(-1))
    ring_face = face_of[near_flat[ring_idx]]
    centre = torch.stack([ring_idx % size, ring_idx // size], -1).double() + 0.5
    t = tri[ring_face]
    ring_bary = _closest_on_triangle(centre, t[:, 0], t[:, 1], t[:, 2])
    index = torch.cat([inside_idx, ring_idx])
    inside = torch.arange(len(index)) < len(inside_idx)
    return Texels(size, index, torch.cat([face_of[inside_idx], ring_face]),
                  torch.cat([bary_of[inside_idx], ring_bary]).float(), inside)


def upsample(values: Tensor, tex_lo: Texels, tex_hi: Texels) -> Tensor:
    """Bilinear lookups (the viewer's) of per-texel ``values`` [M_lo, C] of the low texture at the centres of the
    high texture's texels: [M_hi, C]."""
    s_lo, s_hi = tex_lo.size, tex_hi.size
    img = torch.zeros(s_lo * s_lo, values.shape[1])
    img[tex_lo.index] = values
    img = img.reshape(s_lo, s_lo, -1)
    col = (tex_hi.index % s_hi).double() + 0.5
    row = (tex_hi.index // s_hi).double() + 0.5
    px = col / s_hi * s_lo - 0.5
    py = row / s_hi * s_lo - 0.5
    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = (px - x0).float()[:, None], (py - y0).float()[:, None]
    x0, y0 = x0.long(), y0.long()
    out = torch.zeros(len(tex_hi.index), values.shape[1])
    for ox, oy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        qx = (x0 + ox).clamp(0, s_lo - 1)
        qy = (y0 + oy).clamp(0, s_lo - 1)
        w = (fx if ox else 1 - fx) * (fy if oy else 1 - fy)
        out += w * img[qy, qx]
    return out
