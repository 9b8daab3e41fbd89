"""Bake a trained model into a real-time asset: decimated, UV-unwrapped mesh, diffuse texture, per-texel lobes.

Steps (:func:`bake`): marching cubes on the SDF (:func:`anisdf.export.mesh.extract_mesh`, enclosed inner shells
dropped), quadric decimation to the face budget (:func:`anisdf.export.mesh.decimate`), vertex normals from the SDF
gradient, a UV atlas (:mod:`anisdf.export.uv_atlas`), and texels rasterised in UV space (:mod:`anisdf.export.texels`).
Each texel is a point on the decimated surface; it is moved onto the SDF's zero level (one Newton step) and the
model's blended colour ``C = w c_view + (1 - w) c_ref`` (:class:`anisdf.fields.radiance_field.RadianceField`, with
the SDF's own normal and feature there) is sampled from many view directions ``d`` over the hemisphere of the mesh
normal ``n`` the viewer shades with (cosine-weighted: each sample stands for an equal share of projected area).
With ``r = d - 2 (d . n) n`` the reflected direction:

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

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor
from tqdm.auto import tqdm

from anisdf.errors import AnisdfError
from anisdf.export import baked_format as fmt
from anisdf.export.asset_files import Baked
from anisdf.export.mesh import decimate, sdf_normals
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
from anisdf.export.texels import Texels, rasterize_uv, upsample
from anisdf.export.uv_atlas import unwrap


@dataclass(kw_only=True)
class BakeOptions:
    """Settings of :func:`bake`. The first five are ``anisdf export``'s options, with their defaults in
    :class:`anisdf.tasks.export.ExportOptions`; the others are fixed by the bake."""

    faces: int
    """Triangle budget of the decimated mesh."""
    texture: int
    """Diffuse texture size (texels a side)."""
    specular_texture: int
    """Lobe texture size; 0: half the diffuse texture's."""
    lobes: int
    """Spherical Gaussian lobes per texel (0: diffuse only)."""
    directions: int
    """Reflected directions each specular texel's fit sees."""
    diffuse_directions: int = 16
    """Directions of the hemisphere mean at each diffuse texel."""
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
        if not 0 <= self.lobes <= fmt.MAX_LOBES:
            raise AnisdfError(f"--lobes must be between 0 and {fmt.MAX_LOBES}, got {self.lobes}")
        if self.directions < max(2 * self.lobes + 2, 4):
            raise AnisdfError(f"--directions must be at least {max(2 * self.lobes + 2, 4)} for {self.lobes} lobes, "
                              f"got {self.directions}")


# ------------------------------------------------------------------------------------------------ model queries
@torch.no_grad()
def surface_points(model, x: Tensor, chunk: int = 1 << 16) -> tuple[Tensor, Tensor, Tensor]:
    """Points ``x`` [M, 3] (normalised frame) moved onto the SDF's zero level by one Newton step along the gradient,
    with the SDF feature and unit normal there."""
    xs, feats, normals = [], [], []
    eps = model.fd_eps()
    for s in range(0, len(x), chunk):
        p = x[s:s + chunk]
        q = model.geometry.query(p, create_graph=False, fd_eps=eps)
        sdf, g = q.sdf, q.grad
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
    unit ``view_dirs`` [B, N, 3] (with the mean appearance code when the model has per-image codes)."""
    b, n, _ = view_dirs.shape
    out = torch.empty(b, n, 3, device=x.device)
    per = max(1, chunk // n)
    for s in range(0, b, per):
        e = min(s + per, b)
        m = (e - s) * n
        xs, fs, ns = (t[s:e, None, :].expand(e - s, n, t.shape[-1]).reshape(m, -1) for t in (x, feat, normal))
        col = model.appearance(xs / model.radius, fs, ns, view_dirs[s:e].reshape(m, 3), *model.codes_for(None, m))
        out[s:e] = col["rgb"].reshape(e - s, n, 3).float()
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
            diffuse_vals = m_d + upsample(lobes.diffuse - m_s, tex_s, tex_d)
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
