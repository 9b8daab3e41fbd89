"""Bake a trained model into a real-time asset: decimated, UV-unwrapped mesh, diffuse texture, per-texel lobes.

Steps (:func:`bake`): marching cubes on the SDF (:func:`anisdf.export.mesh.extract_mesh`, enclosed inner shells
dropped), quadric decimation to the face budget (``fast-simplification``), vertex normals from the SDF gradient, a UV
atlas (``xatlas``), and texels rasterised in UV space. Each texel is a point on the decimated surface; it is moved
onto the SDF's zero level (one Newton step) and the model's blended colour ``C = w c_view + (1 - w) c_ref``
(:class:`anisdf.fields.radiance_field.RadianceField`, with the SDF's own normal and feature there) is sampled from
many view directions ``d`` over the hemisphere of the mesh normal ``n`` the viewer shades with (cosine-weighted:
each sample stands for an equal share of projected area). With ``r = d - 2 (d . n) n`` the reflected direction:

* specular texture (``specular_texture`` texels a side): the diffuse colour ``D`` and ``K`` spherical Gaussian lobes
  fitted jointly per texel to ``C`` over ``directions`` reflected directions (:func:`anisdf.export.sg_fit.fit_lobes`);
* diffuse texture (``texture`` texels a side, the glb's base colour): the view-independent part of ``C``, i.e. the
  fitted ``D`` upsampled (bilinear) plus the finer detail of the hemisphere mean of ``C``: ``m(x) - m_low(x)`` with
  ``m`` the mean over a fixed set of ``diffuse_directions`` directions at this texel and ``m_low`` the same mean
  at the specular texels, upsampled. With ``K = 0`` the diffuse texture is that hemisphere mean alone.

Texels just outside the triangles (a 2-texel ring, so bilinear lookups never reach an unset texel) take the values
of the nearest point of their nearest triangle.
"""

from __future__ import annotations

import io
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image
from torch import Tensor
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.export import baked_format as fmt
from anisdf.export.sg_fit import (
    SHARPNESS_RANGE,
    Lobes,
    baked_color,
    fit_lobes,
    hemisphere_directions,
    reflect,
    sample_reflections,
    tangent_frames,
)
from anisdf.utils.atomic import atomic_path

log = logging.getLogger("anisdf")

MAX_LOBES = 8


@dataclass
class BakeOptions:
    """Settings of :func:`bake` (``anisdf export``'s options)."""

    faces: int = 200_000
    """Triangle budget of the decimated mesh."""
    texture: int = 1024
    """Diffuse texture size (texels a side)."""
    specular_texture: int = 0
    """Lobe texture size; 0: half the diffuse texture's."""
    lobes: int = 3
    """Spherical Gaussian lobes per texel (0: diffuse only)."""
    directions: int = 64
    """Reflected directions each specular texel's fit sees."""
    diffuse_directions: int = 16
    """Directions of the hemisphere mean at each diffuse texel."""
    resolution: int = 512
    """Marching cubes resolution before decimation."""
    fit_iters: int = 60
    padding: int = 2
    """Texels between charts in the specular texture (twice as many in a diffuse texture twice as large)."""
    seed: int = 0
    chunk: int = 1 << 16
    """Colour evaluations per model call."""

    @property
    def spec_size(self) -> int:
        return self.specular_texture or max(self.texture // 2, 1)

    def validate(self) -> None:
        if self.faces < 4:
            raise AnisdfError(f"--faces must be at least 4, got {self.faces}")
        if not 16 <= self.texture <= 8192:
            raise AnisdfError(f"--texture must be between 16 and 8192 texels, got {self.texture}")
        if self.specular_texture and not 16 <= self.specular_texture <= self.texture:
            raise AnisdfError(f"--specular-texture must be between 16 and --texture ({self.texture}), "
                              f"got {self.specular_texture}")
        if self.texture % self.spec_size:
            raise AnisdfError(f"--texture ({self.texture}) must be a multiple of the specular texture "
                              f"({self.spec_size})")
        if not 0 <= self.lobes <= MAX_LOBES:
            raise AnisdfError(f"--lobes must be between 0 and {MAX_LOBES}, got {self.lobes}")
        if self.directions < max(2 * self.lobes + 2, 4):
            raise AnisdfError(f"--directions must be at least {max(2 * self.lobes + 2, 4)} for {self.lobes} lobes, "
                              f"got {self.directions}")


# ------------------------------------------------------------------------------------------------ mesh
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
def sdf_normals(model, points: Tensor, chunk: int = 1 << 16) -> Tensor:
    """Unit SDF gradients at ``points`` [M, 3] (normalised frame)."""
    out = []
    for s in range(0, len(points), chunk):
        _, _, g = model.geometry.with_gradient(points[s:s + chunk], create_graph=False, fd_eps=model.fd_eps())
        out.append(F.normalize(g, dim=-1))
    return torch.cat(out) if out else points.new_zeros(0, 3)


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


# ------------------------------------------------------------------------------------------------ texels
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


# ------------------------------------------------------------------------------------------------ model queries
@torch.no_grad()
def surface_points(model, x: Tensor, chunk: int = 1 << 16) -> tuple[Tensor, Tensor, Tensor]:
    """Points ``x`` [M, 3] (normalised frame) moved onto the SDF's zero level by one Newton step along the gradient,
    with the SDF feature and unit normal there."""
    xs, feats, normals = [], [], []
    eps = model.fd_eps()
    for s in range(0, len(x), chunk):
        p = x[s:s + chunk]
        sdf, _, g = model.geometry.with_gradient(p, create_graph=False, fd_eps=eps)
        step = sdf[:, None] * g / (g * g).sum(-1, keepdim=True).clamp_min(1e-12)
        p = p - step.clamp(-0.05, 0.05)
        _, feat, g = model.geometry.with_gradient(p, create_graph=False, fd_eps=eps)
        xs.append(p)
        feats.append(feat)
        normals.append(F.normalize(g, dim=-1))
    return torch.cat(xs), torch.cat(feats), torch.cat(normals)


@torch.no_grad()
def model_colors(model, x: Tensor, feat: Tensor, normal: Tensor, view_dirs: Tensor, chunk: int = 1 << 16) -> Tensor:
    """The model's blended colour ``C`` [B, N, 3] at surface points ``x`` [B, 3] (feature, SDF normal) seen along
    unit ``view_dirs`` [B, N, 3]."""
    b, n, _ = view_dirs.shape
    out = torch.empty(b, n, 3, device=x.device)
    per = max(1, chunk // n)
    for s in range(0, b, per):
        e = min(s + per, b)
        m = (e - s) * n
        xs, fs, ns = (t[s:e, None, :].expand(e - s, n, t.shape[-1]).reshape(m, -1) for t in (x, feat, normal))
        col = model.appearance(xs / model.radius, fs, ns, view_dirs[s:e].reshape(m, 3))
        out[s:e] = col["rgb"].reshape(e - s, n, 3).float()
    return out


# ------------------------------------------------------------------------------------------------ baking
@dataclass
class Baked:
    """Everything :func:`write_asset` writes, in the normalised frame."""

    vertices: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    diffuse: np.ndarray
    """[T, T, 3] uint8."""
    lobe: np.ndarray
    """[K, S, S, 3] uint8."""
    amplitude: np.ndarray
    """[K, S, S, 3] uint8."""
    stats: dict


def _upsample(values: Tensor, tex_lo: Texels, tex_hi: Texels) -> Tensor:
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


def _fixed_hemisphere(normals: Tensor, n: int) -> Tensor:
    """The same ``n`` cosine-weighted reflected directions for every texel (no random spin: a mean over them is
    smooth across the texture), about unit ``normals`` [B, 3]: [B, n, 3]."""
    base = hemisphere_directions(n).to(normals)
    t, b = tangent_frames(normals)
    return (base[None, :, 0:1] * t[:, None] + base[None, :, 1:2] * b[:, None] + base[None, :, 2:3] * normals[:, None])


@dataclass
class _Surface:
    """The decimated, unwrapped mesh the texels lie on (normalised frame)."""

    verts: Tensor
    normals: Tensor
    faces: Tensor

    def texel_points(self, tex: Texels, sl: slice) -> tuple[Tensor, Tensor]:
        """Points and interpolated (shading) normals of texels ``sl`` of ``tex``."""
        tri = self.faces[tex.face[sl]]
        b = tex.bary[sl, :, None]
        x = (b * self.verts[tri]).sum(1)
        return x, F.normalize((b * self.normals[tri]).sum(1), dim=-1)


def _device(model) -> torch.device:
    return next(model.parameters()).device


def _colors_at(model, surf: _Surface, tex: Texels, sl: slice, reflections: Callable[[Tensor], Tensor],
               chunk: int) -> tuple[Tensor, Tensor]:
    """Reflected directions [B, N, 3] about the shading normals of texels ``sl`` and the model's colours there."""
    dev = _device(model)
    x, shading = surf.texel_points(tex, sl)
    r = reflections(shading)
    xs, feat, n_sdf = surface_points(model, x.to(dev), chunk)
    d = reflect(r, shading[:, None, :])
    return r, model_colors(model, xs, feat, n_sdf, d.to(dev), chunk).cpu()


def _mean_color(model, surf: _Surface, tex: Texels, opts: BakeOptions, progress: bool, desc: str) -> Tensor:
    """The mean colour of each texel over the same ``diffuse_directions`` cosine-weighted directions (no random spin:
    the mean is smooth across the texture)."""
    n_dirs = opts.diffuse_directions
    out = torch.empty(len(tex.index), 3)
    per = max(1, (opts.chunk * 4) // n_dirs)
    for s in tqdm(range(0, len(tex.index), per), desc=desc, disable=not progress, leave=False, unit="chunk"):
        sl = slice(s, s + per)
        _, c = _colors_at(model, surf, tex, sl, lambda n: _fixed_hemisphere(n, n_dirs), opts.chunk)
        out[sl] = c.mean(1)
    return out


def _fit_specular(model, surf: _Surface, tex: Texels, opts: BakeOptions, progress: bool) -> tuple[Lobes, dict]:
    """Diffuse colour and lobes of each texel, fitted to the model's colours over ``directions`` reflected
    directions (cosine-weighted, spun randomly per texel)."""
    gen = torch.Generator().manual_seed(opts.seed)
    parts: list[Lobes] = []
    err = torch.zeros(2, dtype=torch.float64)
    per = max(1, (opts.chunk * 4) // opts.directions)
    t_model = t_fit = 0.0
    for s in tqdm(range(0, len(tex.index), per), desc="bake lobes", disable=not progress, leave=False, unit="chunk"):
        sl = slice(s, s + per)
        t0 = time.perf_counter()
        r, target = _colors_at(model, surf, tex, sl, lambda n: sample_reflections(n, opts.directions, gen), opts.chunk)
        t1 = time.perf_counter()
        lobes = fit_lobes(r, target, opts.lobes, iters=opts.fit_iters)
        t_model += t1 - t0
        t_fit += time.perf_counter() - t1
        resid = baked_color(r, lobes) - target
        spread = target - target.mean(1, keepdim=True)
        err += torch.stack([resid.double().pow(2).mean(-1).sum(), spread.double().pow(2).mean(-1).sum()])
        parts.append(lobes)
    cat = Lobes(*(torch.cat([getattr(p, k) for p in parts]) for k in ("diffuse", "axis", "sharpness", "amplitude")))
    n = len(tex.index) * opts.directions
    stats = {"fit_rmse": math.sqrt(float(err[0]) / n), "view_dependence_rms": math.sqrt(float(err[1]) / n),
             "model_seconds": round(t_model, 2), "fit_seconds": round(t_fit, 2)}
    return cat, stats


def bake(model, mesh: trimesh.Trimesh, opts: BakeOptions, progress: bool = True,
         timer: Callable[[str], None] | None = None) -> Baked:
    """Decimate, unwrap and texture ``mesh`` (normalised frame, from the model's SDF) with ``model``'s colours."""
    opts.validate()
    tick = timer or (lambda _name: None)
    mesh = decimate(mesh, opts.faces)
    tick("decimate")
    verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    vnormals = sdf_normals(model, verts.to(_device(model))).cpu()
    bad = ~torch.isfinite(vnormals).all(-1)
    if bad.any():  # no gradient there: the mesh's own normal
        vnormals[bad] = torch.as_tensor(np.asarray(mesh.vertex_normals)[bad.numpy()], dtype=torch.float32)
    spec, tex = opts.spec_size, opts.texture
    ratio = tex // spec
    vmap, faces, uvs = unwrap(mesh.vertices, mesh.faces, vnormals.numpy(), spec, opts.padding)
    tick("unwrap")
    vmap_t = torch.as_tensor(vmap)
    surf = _Surface(verts[vmap_t], vnormals[vmap_t], torch.as_tensor(faces))
    tex_s = rasterize_uv(uvs, faces, spec)
    tex_d = rasterize_uv(uvs, faces, tex) if ratio > 1 else tex_s
    tick("rasterize")
    stats: dict = {"texels_specular": int(tex_s.inside.sum()), "texels_diffuse": int(tex_d.inside.sum()),
                   "atlas_use": round(int(tex_s.inside.sum()) / spec**2, 4)}
    if opts.lobes > 0:
        lobes, fit_stats = _fit_specular(model, surf, tex_s, opts, progress)
        stats.update(fit_stats)
        tick("specular")
        if ratio > 1:  # the fitted diffuse colour, with the finer detail of the hemisphere mean
            m_d = _mean_color(model, surf, tex_d, opts, progress, "bake diffuse")
            m_s = _mean_color(model, surf, tex_s, opts, progress, "bake diffuse (coarse)")
            diffuse_vals = m_d + _upsample(lobes.diffuse - m_s, tex_s, tex_d)
        else:
            diffuse_vals = lobes.diffuse
    else:
        diffuse_vals = _mean_color(model, surf, tex_d, opts, progress, "bake diffuse")
    tick("diffuse")
    diffuse = np.zeros((tex * tex, 3), np.uint8)
    diffuse[tex_d.index.numpy()] = fmt.to_byte(diffuse_vals.numpy())
    k = opts.lobes
    lobe_img = np.zeros((k, spec * spec, 3), np.uint8)
    amp_img = np.zeros((k, spec * spec, 3), np.uint8)
    idx = tex_s.index.numpy()
    for i in range(k):
        lobe_img[i, idx, :2] = fmt.oct_bytes(lobes.axis[:, i].numpy())
        lobe_img[i, idx, 2] = fmt.to_byte(fmt.encode_sharpness(lobes.sharpness[:, i].numpy(), SHARPNESS_RANGE))
        amp_img[i, idx] = fmt.to_byte(lobes.amplitude[:, i].numpy())
    return Baked(surf.verts.numpy(), surf.normals.numpy(), uvs, faces, diffuse.reshape(tex, tex, 3),
                 lobe_img.reshape(k, spec, spec, 3), amp_img.reshape(k, spec, spec, 3), stats)


# ------------------------------------------------------------------------------------------------ files
def png_bytes(img: np.ndarray) -> bytes:
    """An RGB uint8 image as PNG bytes (no gamma or colour profile chunk: the bytes are the values)."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img), "RGB").save(buf, format="PNG", optimize=False, compress_level=9)
    return buf.getvalue()


def write_bytes(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def glb_bytes(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray, diffuse_png: bytes,
              extras: dict | None = None) -> bytes:
    """A glb of one textured triangle mesh: POSITION, NORMAL, TEXCOORD_0, uint32 indices and the diffuse PNG as the
    base colour of a PBR material (metallic 0, roughness 1) that also asks for ``KHR_materials_unlit`` (the colours
    are baked: viewers that know the extension show them as they are)."""
    import pygltflib as g

    arrays = [np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(normals, np.float32),
              np.ascontiguousarray(uvs, np.float32), np.ascontiguousarray(faces, np.uint32).reshape(-1)]
    blob = b""
    views = []
    for a in [*arrays, diffuse_png]:
        data = a if isinstance(a, bytes) else a.tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob += data + b"\0" * (-len(data) % 4)
    for i in range(3):
        views[i].target = g.ARRAY_BUFFER
    views[3].target = g.ELEMENT_ARRAY_BUFFER
    pos = arrays[0]
    accessors = [
        g.Accessor(bufferView=0, componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                   min=pos.min(0).tolist(), max=pos.max(0).tolist()),
        g.Accessor(bufferView=1, componentType=g.FLOAT, count=len(pos), type=g.VEC3),
        g.Accessor(bufferView=2, componentType=g.FLOAT, count=len(pos), type=g.VEC2),
        g.Accessor(bufferView=3, componentType=g.UNSIGNED_INT, count=int(arrays[3].size), type=g.SCALAR),
    ]
    material = g.Material(
        pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorTexture=g.TextureInfo(index=0), metallicFactor=0.0,
                                                    roughnessFactor=1.0),
        extensions={"KHR_materials_unlit": {}}, name="baked")
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="anisdf export"),
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name="anisdf")],
        meshes=[g.Mesh(primitives=[g.Primitive(attributes=g.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
                                               indices=3, material=0)])],
        accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))],
        materials=[material], textures=[g.Texture(source=0, sampler=0)],
        samplers=[g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE,
                            wrapT=g.CLAMP_TO_EDGE)],
        images=[g.Image(bufferView=4, mimeType="image/png")],
        extensionsUsed=["KHR_materials_unlit"], extras=extras or {})
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


def write_asset(out: Path, baked: Baked, to_world: np.ndarray, manifest: dict) -> dict[str, int]:
    """Write model.glb (mesh moved to the dataset's frame by ``to_world``), specular_*.png, index.html and
    export.json (``manifest`` plus the file sizes) into ``out``; returns the sizes in bytes."""
    from anisdf.export.web_page import page_html

    out.mkdir(parents=True, exist_ok=True)
    T = np.asarray(to_world, dtype=np.float64)
    lin = T[:3, :3]
    verts = np.asarray(baked.vertices, np.float64) @ lin.T + T[:3, 3]
    normals = np.asarray(baked.normals, np.float64) @ np.linalg.inv(lin)  # normals transform by the inverse transpose
    normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    faces = np.asarray(baked.faces)
    if np.linalg.det(lin) < 0:  # a reflection: keep the triangles wound counter-clockwise seen from outside
        faces = faces[:, ::-1]
    glb = glb_bytes(verts, normals, baked.uvs, faces, png_bytes(baked.diffuse),
                    extras={"anisdf": {"format": fmt.FORMAT, "manifest": fmt.MANIFEST}})
    lobe_pngs = [png_bytes(baked.lobe[k]) for k in range(len(baked.lobe))]
    rgb_pngs = [png_bytes(baked.amplitude[k]) for k in range(len(baked.amplitude))]
    files: dict[str, bytes] = {fmt.GLB: glb}
    for k in range(len(lobe_pngs)):
        files[fmt.lobe_png(k)] = lobe_pngs[k]
        files[fmt.rgb_png(k)] = rgb_pngs[k]
    # stale lobe textures of an earlier export with more lobes would contradict the manifest
    for old in out.glob("specular_*.png"):
        if old.name not in files:
            old.unlink()
    for name, data in files.items():
        write_bytes(out / name, data)
    page = page_html(manifest, glb, lobe_pngs, rgb_pngs).encode("utf-8")
    write_bytes(out / fmt.PAGE, page)
    sizes = {name: len(data) for name, data in files.items()}
    sizes[fmt.PAGE] = len(page)
    return sizes
