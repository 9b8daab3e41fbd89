"""The glTF 2.0 metallic-roughness BRDF (glTF spec, appendix B) and the tables of its split-sum approximation.

With base colour ``b``, metallic ``m``, roughness ``r`` (``alpha = r^2``), unit normal ``n``, view ``v``, light
``l`` and half vector ``h``::

    f = (1 - F) c_diff / pi + F D V,   c_diff = (1 - m) b,   F = f0 + (1 - f0) (1 - v.h)^5,   f0 = 0.04 (1 - m) + m b
    D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)                                  (GGX / Trowbridge-Reitz)
    V = 0.5 / (n.l sqrt((n.v)^2 (1 - alpha^2) + alpha^2) + n.v sqrt((n.l)^2 (1 - alpha^2) + alpha^2))   (Smith)

The split sum (Karis 2013) writes the specular integral as the light prefiltered with the GGX lobe times
``f0 A + B`` (:func:`dfg_table`); the diffuse weight ``1 - F`` is averaged over the cosine lobe the same way (``C``).
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

MIN_ROUGHNESS = 0.02
"""Roughness is clamped to at least this (a perfect mirror has no lobe to sample)."""


def ggx_d(nh: Tensor, alpha: Tensor) -> Tensor:
    a2 = alpha * alpha
    den = nh * nh * (a2 - 1.0) + 1.0
    return a2 / (math.pi * den * den).clamp_min(1e-12)


def smith_v(nl: Tensor, nv: Tensor, alpha: Tensor) -> Tensor:
    """The height-correlated Smith visibility term ``G / (4 n.l n.v)``."""
    a2 = alpha * alpha
    gv = nl * torch.sqrt(nv * nv * (1.0 - a2) + a2)
    gl = nv * torch.sqrt(nl * nl * (1.0 - a2) + a2)
    return 0.5 / (gv + gl).clamp_min(1e-12)


def schlick_f(f0: Tensor, vh: Tensor) -> Tensor:
    return f0 + (1.0 - f0) * (1.0 - vh).clamp(0.0, 1.0) ** 5


def f0_and_diffuse(base: Tensor, metallic: Tensor) -> tuple[Tensor, Tensor]:
    """glTF's ``f0 = lerp(0.04, b, m)`` and ``c_diff = lerp(b, 0, m)``."""
    return 0.04 * (1.0 - metallic) + base * metallic, base * (1.0 - metallic)


def brdf(n: Tensor, v: Tensor, light: Tensor, base: Tensor, roughness: Tensor, metallic: Tensor) -> Tensor:
    """``f(v, l) n.l`` [..., 3] (zero below the horizon) for unit ``n``, ``v``, ``light`` [..., 3], base colour
    [..., 3], roughness and metallic [..., 1]: the plain definition the fast paths are checked against."""
    h = F.normalize(v + light, dim=-1)
    nl = (n * light).sum(-1, keepdim=True)
    nv = (n * v).sum(-1, keepdim=True).clamp_min(1e-4)
    nh = (n * h).sum(-1, keepdim=True).clamp_min(0.0)
    vh = (v * h).sum(-1, keepdim=True).clamp_min(0.0)
    alpha = roughness.clamp_min(MIN_ROUGHNESS) ** 2
    f0, c_diff = f0_and_diffuse(base, metallic)
    fr = schlick_f(f0, vh)
    spec = fr * ggx_d(nh, alpha) * smith_v(nl.clamp_min(0.0), nv, alpha)
    return ((1.0 - fr) * c_diff / math.pi + spec) * nl.clamp_min(0.0)


def hammersley(n: int) -> Tensor:
    """``n`` points of the Hammersley set in [0, 1)^2, [n, 2] float64."""
    i = torch.arange(n, dtype=torch.int64)
    rev = torch.zeros(n, dtype=torch.float64)
    bits, scale = i.clone(), 0.5
    while bool((bits > 0).any()):
        rev += (bits & 1).double() * scale
        bits >>= 1
        scale *= 0.5
    return torch.stack([(i.double() + 0.5) / n, rev], -1)


def sample_ggx_half(u: Tensor, alpha: Tensor) -> Tensor:
    """Half vectors in the normal's local frame (z = normal) distributed as ``D(h) n.h`` for uniform ``u`` [..., 2]."""
    a2 = alpha * alpha
    cos_t = torch.sqrt((1.0 - u[..., 0]) / (1.0 + (a2 - 1.0) * u[..., 0]).clamp_min(1e-12))
    sin_t = torch.sqrt((1.0 - cos_t * cos_t).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    return torch.stack([sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t], -1)


@functools.lru_cache(maxsize=4)
def dfg_table(size: int = 32, samples: int = 1024) -> Tensor:
    """[3, size, size] float32 over (roughness rows, n.v columns, at cell centres): ``A``, ``B`` of the split sum
    (``int F D V n.l = f0 A + B`` under a white light) and ``C = int (1 - v.h)^5 n.l / pi`` over the cosine lobe
    (the diffuse part's ``1 - F`` averages to ``1 - f0 - (1 - f0) C``)."""
    t = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    rough, nv = torch.meshgrid(t, t, indexing="ij")
    alpha = (rough.clamp_min(MIN_ROUGHNESS) ** 2)[..., None]
    nv = nv[..., None]
    v = torch.stack([torch.sqrt(1.0 - nv * nv), torch.zeros_like(nv), nv], -1)  # [S, S, 1, 3]
    u = hammersley(samples)
    h = sample_ggx_half(u, alpha)  # [S, S, N, 3]
    vh = (v * h).sum(-1)
    light = 2.0 * vh[..., None] * h - v
    nl, nh = light[..., 2].clamp_min(0.0), h[..., 2]
    # estimator of int F D V n.l with pdf(l) = D n.h / (4 v.h): F V n.l 4 v.h / n.h
    g = 4.0 * smith_v(nl, nv, alpha) * nl * vh.clamp_min(0.0) / nh.clamp_min(1e-12)
    fc = (1.0 - vh.clamp(0.0, 1.0)) ** 5
    a = ((1.0 - fc) * g).mean(-1)
    b = (fc * g).mean(-1)
    # cosine-weighted light directions for C
    r, phi = torch.sqrt(u[:, 0]), 2.0 * math.pi * u[:, 1]
    lc = torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt(1.0 - u[:, 0])], -1)  # [N, 3]
    hc = F.normalize(v + lc, dim=-1)
    c = ((1.0 - (v * hc).sum(-1).clamp(0.0, 1.0)) ** 5).mean(-1)
    return torch.stack([a, b, c]).float()


def dfg_lookup(nv: Tensor, roughness: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Bilinear lookups of :func:`dfg_table` at ``n.v`` and roughness [...]: ``A``, ``B``, ``C`` [...]."""
    table = dfg_table().to(nv.device)
    grid = torch.stack([nv.reshape(-1) * 2.0 - 1.0, roughness.reshape(-1) * 2.0 - 1.0], -1)
    out = F.grid_sample(table[None], grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    a, b, c = out[0, :, 0]
    return a.reshape(nv.shape), b.reshape(nv.shape), c.reshape(nv.shape)
