"""Multiresolution hash encoding (Mueller et al. 2022), the plain PyTorch reference.

Level ``l`` has resolution ``R_l = floor(base * s**l)`` and ``(R_l + 1)**3`` grid vertices. Coarse levels
whose vertices fit in ``2**log2_hashmap_size`` entries are indexed densely; finer levels use the spatial
hash ``(x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod T``. Features of the 8 corners are blended
trilinearly. Everything is differentiable with autograd, including the double backward that an
eikonal loss on analytic normals needs. The fast backends beside this file (``cpu_kernel``: C++ on CPU,
``triton``: CUDA) implement the same contract and are tested against it. This module imports none of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class GridSpec:
    """Shape of one multiresolution hash grid."""

    n_levels: int = 16
    features_per_level: int = 2
    log2_hashmap_size: int = 19
    base_resolution: int = 32
    per_level_scale: float = 2.0 ** 0.4

    @cached_property
    def resolutions(self) -> tuple[int, ...]:
        return tuple(
            int(math.floor(self.base_resolution * self.per_level_scale**lvl + 1e-6))
            for lvl in range(self.n_levels)
        )

    @cached_property
    def hashed(self) -> tuple[bool, ...]:
        cap = 2**self.log2_hashmap_size
        return tuple((r + 1) ** 3 > cap for r in self.resolutions)

    @cached_property
    def sizes(self) -> tuple[int, ...]:
        cap = 2**self.log2_hashmap_size
        return tuple(cap if h else int(math.ceil((r + 1) ** 3 / 8) * 8)
                     for r, h in zip(self.resolutions, self.hashed, strict=True))

    @cached_property
    def offsets(self) -> tuple[int, ...]:
        out = [0]
        for s in self.sizes:
            out.append(out[-1] + s)
        return tuple(out)

    @property
    def n_params(self) -> int:
        return self.offsets[-1]

    @property
    def output_dim(self) -> int:
        return self.n_levels * self.features_per_level


_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)


def corner_indices(x: Tensor, spec: GridSpec) -> tuple[Tensor, Tensor]:
    """Table rows ``[N, L, 8]`` of the 8 corners of each level's cell, and the fractional position ``[N, L, 3]``."""
    dev = x.device
    res = torch.tensor(spec.resolutions, device=dev, dtype=x.dtype)
    pos = x.detach()[:, None, :] * res[None, :, None]  # [N, L, 3]
    res_l = res.long()
    base = pos.floor().long().clamp_min(0)
    base = torch.minimum(base, (res_l - 1).clamp_min(0)[None, :, None])
    frac = x[:, None, :] * res[None, :, None] - base.to(x.dtype)
    c = base[:, :, None, :] + _CORNERS.to(dev)[None, None]  # [N, L, 8, 3]
    stride = (res_l + 1)[None, :, None]
    dense = c[..., 0] + c[..., 1] * stride + c[..., 2] * stride * stride
    hashed = (c[..., 0] * PRIMES[0]) ^ (c[..., 1] * PRIMES[1]) ^ (c[..., 2] * PRIMES[2])
    hashed = hashed & ((1 << spec.log2_hashmap_size) - 1)
    is_hashed = torch.tensor(spec.hashed, device=dev)[None, :, None]
    idx = torch.where(is_hashed, hashed, dense)
    idx = idx + torch.tensor(spec.offsets[:-1], device=dev)[None, :, None]
    return idx, frac


def trilinear_weights(frac: Tensor) -> Tensor:
    """Weights ``[N, L, 8]`` of the 8 corners for fractional positions ``[N, L, 3]``."""
    corners = _CORNERS.to(frac.device, frac.dtype)  # [8, 3]
    f = frac[:, :, None, :]
    w = corners * f + (1 - corners) * (1 - f)  # [N, L, 8, 3]
    return w.prod(dim=-1)


def hash_encode_reference(x: Tensor, table: Tensor, spec: GridSpec, n_levels: int | None = None) -> Tensor:
    """Encode points ``x`` in ``[0, 1]^3`` (shape ``[N, 3]``) into features ``[N, L * F]``; ``n_levels``: the
    first ``n_levels`` levels only, ``[N, n_levels * F]`` (levels not yet switched on cost nothing).

    One level at a time (about 2x faster on CPU than materialising all levels' int64 indices at once).
    Same function as :func:`corner_indices` + :func:`trilinear_weights`; differentiable to any order in x.
    """
    n = x.shape[0]
    corners = _CORNERS.to(x.device)
    cf = corners.to(x.dtype)
    mask = (1 << spec.log2_hashmap_size) - 1
    outs = []
    n_lv = spec.n_levels if n_levels is None else n_levels
    for res, hashed, off in list(zip(spec.resolutions, spec.hashed, spec.offsets[:-1], strict=True))[:n_lv]:
        pos = x * res
        base = pos.detach().floor().clamp(0, max(res - 1, 0))
        frac = pos - base
        c = base.long()[:, None, :] + corners[None]  # [N, 8, 3]
        if hashed:
            idx = ((c[..., 0] * PRIMES[0]) ^ (c[..., 1] * PRIMES[1]) ^ (c[..., 2] * PRIMES[2])) & mask
        else:
            s = res + 1
            idx = c[..., 0] + c[..., 1] * s + c[..., 2] * (s * s)
        f = frac[:, None, :]
        w = (cf * f + (1 - cf) * (1 - f)).prod(-1)  # [N, 8]
        feats = table.index_select(0, (idx + off).reshape(-1)).view(n, 8, table.shape[1])
        outs.append(torch.einsum("nc,ncf->nf", w.to(table.dtype), feats))
    return torch.cat(outs, dim=-1)


EncodeFn = Callable[[Tensor, Tensor, GridSpec, int | None], Tensor]
