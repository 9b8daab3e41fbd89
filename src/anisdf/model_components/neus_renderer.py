"""NeuS volume rendering on packed samples (paper Eqs. 1 and 3).

Discrete opacity from the SDF at both ends of each section (NeuS Eq. 13, with the cos-annealed slope of
instant-nsr-pl): ``alpha = max((Phi_s(f_prev) - Phi_s(f_next)) / Phi_s(f_prev), 0)``, transmittance
``T_i = prod_{j<i} (1 - alpha_j)`` per ray, weights ``w_i = T_i alpha_i``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from anisdf.model_components.ray_marching import Samples


class Variance(nn.Module):
    """Learned inverse standard deviation ``s = exp(scale * v)`` of the logistic density."""

    def __init__(self, init: float = 0.3, scale: float = 10.0, max_inv_s: float = 1e4) -> None:
        super().__init__()
        self.variance = nn.Parameter(torch.tensor(float(init)))
        self.scale = scale
        self.max_inv_s = max_inv_s

    def forward(self) -> Tensor:
        return torch.exp(self.variance * self.scale).clamp(1e-6, self.max_inv_s)

    @torch.no_grad()
    def project_(self) -> None:
        """Keep ``s <= max_inv_s`` after an optimiser step by projecting ``v`` (a few ulps inside, where the clamp in
        :meth:`forward` still passes the gradient). That clamp alone would let ``v`` run on past the cap (Adam's
        momentum), where no gradient reaches it to bring it back."""
        self.variance.clamp_(max=math.log(self.max_inv_s) / self.scale * (1.0 - 1e-6))


def neus_alpha(sdf: Tensor, grad: Tensor, dirs: Tensor, dt: Tensor, inv_s: Tensor, cos_anneal: float) -> Tensor:
    """Section opacity from the SDF at the midpoint and its directional derivative."""
    true_cos = (dirs * grad).sum(-1)
    iter_cos = -(torch.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal) + torch.relu(-true_cos) * cos_anneal)
    next_sdf = sdf + iter_cos * dt * 0.5
    prev_sdf = sdf - iter_cos * dt * 0.5
    prev_cdf = torch.sigmoid(prev_sdf * inv_s)
    next_cdf = torch.sigmoid(next_sdf * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


def packed_weights(alpha: Tensor, ray_idx: Tensor, n_rays: int) -> tuple[Tensor, Tensor]:
    """Weights ``T_i alpha_i`` and transmittance ``T_i`` for packed samples sorted by ray.

    The exclusive cumulative sum of ``log(1 - alpha)`` runs in float64 over the whole pack; each ray's
    running sum starts from the value just before its first sample.
    """
    log1m = torch.log((1.0 - alpha).clamp_min(1e-10)).double()
    cs = torch.cumsum(log1m, 0)
    excl = cs - log1m
    counts = torch.bincount(ray_idx, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    start_val = excl[starts.clamp_max(max(alpha.shape[0] - 1, 0))] if alpha.shape[0] else excl.new_zeros(n_rays)
    trans = torch.exp(excl - start_val[ray_idx]).to(alpha.dtype)
    return trans * alpha, trans


def composite(values: Tensor, weights: Tensor, ray_idx: Tensor, n_rays: int) -> Tensor:
    """Per-ray sum of ``weights * values`` (values [S, C] or [S]), accumulated in at least float32.

    Under mixed precision the radiance heads return bf16 values; pixel sums are kept in float32.
    """
    w = weights if values.dim() == 1 else weights[:, None]
    src = w * values
    src = src.to(torch.promote_types(src.dtype, torch.float32))
    out = torch.zeros((n_rays, *values.shape[1:]), device=values.device, dtype=src.dtype)
    return out.index_add_(0, ray_idx, src)


def estimated_alpha(sdf: Tensor, t: Tensor, ray_idx: Tensor, step: float, inv_s: Tensor) -> Tensor:
    """Section opacities from SDF values alone: the directional derivative along the ray comes from the next sample
    of the same ray (NeuS' original discretisation); where there is none it is taken as 0 (opacity 0, which can
    only keep more samples)."""
    same = torch.zeros_like(sdf, dtype=torch.bool)
    slope = torch.zeros_like(sdf)
    if sdf.shape[0] > 1:
        gap = t[1:] - t[:-1]
        same[:-1] = (ray_idx[1:] == ray_idx[:-1]) & (gap < 1.5 * step)
        slope[:-1] = torch.where(same[:-1], (sdf[1:] - sdf[:-1]) / gap.clamp_min(1e-8), slope[:-1])
    iter_cos = slope.clamp(-1.0, 0.0)
    dt = torch.full_like(sdf, step)
    prev_cdf = torch.sigmoid((sdf - iter_cos * dt * 0.5) * inv_s)
    next_cdf = torch.sigmoid((sdf + iter_cos * dt * 0.5) * inv_s)
    return ((prev_cdf - next_cdf) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


@torch.no_grad()
def prune_occluded(sdf: Tensor, t: Tensor, ray_idx: Tensor, n_rays: int, step: float, inv_s: Tensor,
                   eps: float) -> Tensor:
    """Mask of samples whose transmittance, estimated from SDF values alone (:func:`estimated_alpha`), is still
    above ``eps``."""
    _, trans = packed_weights(estimated_alpha(sdf, t, ray_idx, step, inv_s), ray_idx, n_rays)
    return trans > eps


def opaque_after(step: float, inv_s: float, eps: float) -> int:
    """How many sections a ray must cross before its transmittance (:func:`estimated_alpha`) can fall to ``eps``.

    A section's SDF values differ by at most ``step`` (the slope is clamped to [-1, 0]), and
    ``1 - alpha = Phi_s(f_next) / Phi_s(f_prev) >= exp(-inv_s step)`` for logistic ``Phi_s``, so ``k`` sections
    leave at least ``exp(-k inv_s step)``. Early in cpu-quick training (``inv_s`` about 23, ``eps`` 1e-3) that is 44
    sections; once ``inv_s`` passes ``-ln(eps) / step`` (about 1000), a single section can hide what follows."""
    per_section = inv_s * step
    if per_section <= 0.0:
        return 2**62
    return math.floor(0.999 * -math.log(eps) / per_section)  # a margin for rounding


@torch.no_grad()
def prune_occluded_progressive(sdf_at: Callable[[Tensor], Tensor], t: Tensor, ray_idx: Tensor, n_rays: int,
                               step: float, inv_s: Tensor, eps: float, segment: int = 8,
                               need_sdf: bool = True) -> tuple[Tensor, Tensor]:
    """:func:`prune_occluded` with early ray termination: the SDF (``sdf_at(sample indices)``) is queried a segment
    of samples a ray at a time, front to back (``segment`` samples, then twice as many each time, so a long ray
    takes a few rounds), and a ray stops being queried once its transmittance is below ``eps``; samples behind that
    point cost nothing. Each segment also reads the next sample of its ray, so
    the opacities are those of the one-pass estimate. Returns the keep mask and the SDF (NaN where not queried).
    Without ``need_sdf``, rays too short to become opaque (:func:`opaque_after`) are kept whole and never queried
    (steps 20-40 of cpu-quick on bunny_plastic: 2-18% of the samples)."""
    n = t.shape[0]
    sdf = torch.full_like(t, float("nan"))
    keep = torch.zeros(n, dtype=torch.bool, device=t.device)
    if n == 0:
        return keep, sdf
    counts = torch.bincount(ray_idx, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(n, device=t.device) - starts[ray_idx]
    log_t = torch.zeros(n_rays, dtype=torch.float64, device=t.device)
    if not need_sdf:  # a ray of at most k + 1 samples has crossed at most k sections at its last sample
        short = counts <= opaque_after(step, float(inv_s), eps) + 1
        keep = short[ray_idx]
        log_t.masked_fill_(short, -math.inf)  # not alive: never queried
    k0, longest = 0, int(counts.max())
    while k0 < longest:
        alive = log_t > math.log(eps)
        window = (rank >= k0) & (rank <= k0 + segment) & alive[ray_idx]
        idx = window.nonzero()[:, 0]
        if idx.numel() == 0:
            break
        new = idx[torch.isnan(sdf[idx])]
        if new.numel():
            sdf[new] = sdf_at(new)
        alpha = estimated_alpha(sdf[idx], t[idx], ray_idx[idx], step, inv_s)
        own = rank[idx] < k0 + segment  # the look-ahead sample belongs to the next segment
        idx, alpha = idx[own], alpha[own]
        r = ray_idx[idx]
        _, trans = packed_weights(alpha, r, n_rays)
        keep[idx] = trans * torch.exp(log_t[r]).to(trans.dtype) > eps
        log_t.index_add_(0, r, torch.log((1.0 - alpha).clamp_min(1e-10)).double())
        k0, segment = k0 + segment, 2 * segment
    return keep, sdf


@torch.no_grad()
def prune_hidden(distance: Callable[[Tensor], Tensor], origins: Tensor, dirs: Tensor, s: Samples, step: float,
                 inv_s: Tensor, eps: float, one_pass: bool, need_sdf: bool) -> tuple[Tensor, Tensor | None]:
    """The keep mask of the marched samples ``s`` (:func:`prune_occluded`) from the SDF ``distance(points)``: in one
    pass over every sample (``one_pass``: on a GPU each progressive round reads the selection back), else front to
    back (:func:`prune_occluded_progressive`: a ray's samples behind its opaque point are never queried), which with
    ``need_sdf`` also returns the kept samples' SDF values."""
    if one_pass:
        sdf = distance(origins[s.ray_idx] + dirs[s.ray_idx] * s.t[:, None])
        return prune_occluded(sdf, s.t, s.ray_idx, s.n_rays, step, inv_s, eps), None

    def sdf_at(i: Tensor) -> Tensor:
        r = s.ray_idx[i]
        return distance(origins[r] + dirs[r] * s.t[i, None])

    keep, sdf = prune_occluded_progressive(sdf_at, s.t, s.ray_idx, s.n_rays, step, inv_s, eps, need_sdf=need_sdf)
    return keep, sdf[keep] if need_sdf else None
