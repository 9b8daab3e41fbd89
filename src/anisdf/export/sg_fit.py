"""Per-texel spherical Gaussian (SG) lobes fitted to a trained model's view-dependent colour.

The baked colour of a surface point seen along the unit view direction ``d`` is

    C(d) = D + sum_k a_k exp(lambda_k (mu_k . r - 1)),      r = d - 2 (d . n) n,

with ``D`` the diffuse colour (RGB), ``r`` the view direction reflected about the shading normal ``n``, and per lobe
an axis ``mu_k`` (unit), a sharpness ``lambda_k > 0`` and an RGB amplitude ``a_k >= 0`` (BakedSDF's per-vertex model,
here per texel). :func:`fit_lobes` fits ``D`` and the ``K`` lobes of a batch of texels, jointly, to colours sampled
over many reflected directions (weighted least squares: matching pursuit, backfitting, a few Adam steps, a last
linear solve). ``K = 0`` leaves the weighted mean colour: the best view-independent colour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

SHARPNESS_RANGE = (1.0, 1000.0)
"""Sharpness bounds: 1 is a lobe over a whole hemisphere; 1000 falls to 1/e at 2.6 degrees from its axis."""


@dataclass
class Lobes:
    """Fitted parameters of ``B`` texels: ``diffuse`` [B, 3], ``axis`` [B, K, 3] (unit), ``sharpness`` [B, K],
    ``amplitude`` [B, K, 3]."""

    diffuse: Tensor
    axis: Tensor
    sharpness: Tensor
    amplitude: Tensor

    @property
    def k(self) -> int:
        return int(self.axis.shape[1])


def sg_eval(r: Tensor, axis: Tensor, sharpness: Tensor, amplitude: Tensor) -> Tensor:
    """``sum_k a_k exp(lambda_k (mu_k . r - 1))`` of unit directions ``r`` [B, N, 3]: [B, N, 3]."""
    if axis.shape[1] == 0:
        return r.new_zeros(r.shape)
    cos = torch.einsum("bnc,bkc->bnk", r, axis)
    g = torch.exp(sharpness[:, None, :] * (cos - 1.0))
    return torch.einsum("bnk,bkc->bnc", g, amplitude)


def baked_color(r: Tensor, lobes: Lobes) -> Tensor:
    """The model's colour ``D + sum_k SG_k(r)`` for reflected directions ``r`` [B, N, 3]."""
    return lobes.diffuse[:, None, :] + sg_eval(r, lobes.axis, lobes.sharpness, lobes.amplitude)


def _luminance(c: Tensor) -> Tensor:
    return c @ c.new_tensor([0.2126, 0.7152, 0.0722])


def _solve_linear(r: Tensor, target: Tensor, w: Tensor, axis: Tensor, sharpness: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted least-squares diffuse colour [B, 3] and amplitudes [B, K, 3] for fixed axes and sharpness (a small
    ridge keeps lobes no sample sees at zero), clamped to [0, 1]."""
    g = torch.exp(sharpness[:, None, :] * (torch.einsum("bnc,bkc->bnk", r, axis) - 1.0))  # [B, N, K]
    design = torch.cat([torch.ones_like(g[..., :1]), g], -1)  # [B, N, K + 1]
    gram = torch.einsum("bni,bn,bnj->bij", design, w, design)
    gram = gram + 1e-6 * torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    rhs = torch.einsum("bni,bn,bnc->bic", design, w, target)
    x = torch.linalg.solve(gram, rhs).clamp(0.0, 1.0)
    return x[:, 0], x[:, 1:]


def _fit_one(r: Tensor, w: Tensor, residual: Tensor, mu: Tensor, cands: Tensor, shifts: int
             ) -> tuple[Tensor, Tensor, Tensor]:
    """One lobe fitted to ``residual`` [B, N, 3] from the start axis ``mu`` [B, 3]: ``shifts`` mean-shift steps move
    the axis to the centroid of the positive residual under the lobe, and the sharpness among ``cands`` with its
    least-squares amplitude (clamped to [0, 1]) that lowers the error most is kept. Axis, sharpness, amplitude."""
    rows = torch.arange(r.shape[0], device=r.device)
    lum = _luminance(residual).clamp_min(0.0) * w
    lam = cands[len(cands) // 2].expand(r.shape[0])
    for it in range(shifts + 1):
        cos = (r * mu[:, None, :]).sum(-1)
        g = torch.exp(cands[None, None, :] * (cos[..., None] - 1.0))  # [B, N, C]
        num = torch.einsum("bnc,bn,bnj->bcj", g, w, residual)  # [B, C, 3]
        den = torch.einsum("bnc,bn->bc", g * g, w)[..., None].clamp_min(1e-12)
        a = (num / den).clamp(0.0, 1.0)
        gain = (2 * a * num - a * a * den).sum(-1)  # the error reduction of each candidate
        best = gain.argmax(dim=1)
        lam = cands[best]
        if it == shifts:
            # the sharpness between the candidates: the vertex of the parabola through the best and its neighbours
            # (in log sharpness), then the amplitude for it
            c = best.clamp(1, len(cands) - 2)
            g0, g1, g2 = gain[rows, c - 1], gain[rows, c], gain[rows, c + 1]
            curv = g0 - 2 * g1 + g2
            off = torch.where(curv < -1e-20, 0.5 * (g0 - g2) / curv.clamp(max=-1e-20), torch.zeros_like(g1))
            step = torch.log(cands[1] / cands[0])
            lam = torch.exp(cands[c].log() + off.clamp(-1, 1) * step)
            lam = torch.where((best == c) & (curv < -1e-20), lam, cands[best])
            gl = torch.exp(lam[:, None] * (cos - 1.0))
            a = (torch.einsum("bn,bn,bnj->bj", gl, w, residual)
                 / torch.einsum("bn,bn->b", gl * gl, w)[:, None].clamp_min(1e-12)).clamp(0.0, 1.0)
            return mu, lam, a
        shifted = (lum * g[rows, :, best])[..., None].mul(r).sum(1)
        norm = shifted.norm(dim=-1, keepdim=True)
        mu = torch.where(norm > 1e-12, shifted / norm.clamp_min(1e-12), mu)
    raise AssertionError("unreachable")


def fit_lobes(r: Tensor, target: Tensor, k: int, weights: Tensor | None = None, rounds: int = 1, shifts: int = 3,
              iters: int = 60, lr: float = 0.02, sharpness_range: tuple[float, float] = SHARPNESS_RANGE) -> Lobes:
    """Fit ``D`` and ``k`` lobes per texel to colours ``target`` [B, N, 3] seen in reflected directions ``r``
    [B, N, 3] (unit), with optional sample ``weights`` [B, N] (default: equal); least squares, batched over texels.

    Lobes are added one by one (matching pursuit), each started on the sample that the colour's mean and the earlier
    lobes explain least; then ``rounds`` of backfitting refit each lobe to what the others leave. A lobe's fit moves
    its axis by ``shifts`` mean-shift steps (to the centroid of the positive residual under the lobe) and picks the
    sharpness, among 9 candidates from a hemisphere-wide lobe to one a sample spacing wide, with the least-squares
    amplitude that lowers the error most. After each round the diffuse colour and all amplitudes are solved jointly
    (least squares). Last, ``iters`` Adam steps (learning rate ``lr``) move all parameters together (:func:`_polish`).
    The diffuse colour and the amplitudes are held in [0, 1], the sharpness in ``sharpness_range``.
    """
    if r.shape != target.shape or r.dim() != 3 or r.shape[-1] != 3:
        raise ValueError(f"r and target must both be [B, N, 3], got {tuple(r.shape)} and {tuple(target.shape)}")
    if k < 0:
        raise ValueError(f"the number of lobes must be >= 0, got {k}")
    b, n, _ = r.shape
    w = torch.ones(b, n, device=r.device, dtype=r.dtype) if weights is None else weights.to(r)
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    mean = (w[..., None] * target).sum(1)
    if k == 0:
        empty = r.new_zeros(b, 0)
        return Lobes(mean.clamp(0, 1), r.new_zeros(b, 0, 3), empty, r.new_zeros(b, 0, 3))
    lo, hi = sharpness_range
    # N samples over the hemisphere lie ~sqrt(2 pi / N) apart, and exp(lambda (cos t - 1)) ~ exp(-lambda t^2 / 2):
    # a lobe narrower than ~lambda = 4 N / (2 pi) falls between the samples
    widest, narrowest = 2.0, 4.0 * n / (2.0 * math.pi)
    cands = torch.tensor([min(max(widest * (narrowest / widest) ** (i / 8), lo), hi) for i in range(9)],
                         device=r.device, dtype=r.dtype)
    rows = torch.arange(b, device=r.device)
    diffuse = mean
    axis = r.new_zeros(b, k, 3)
    lam = r.new_zeros(b, k)
    amp = r.new_zeros(b, k, 3)
    for j in range(k):  # matching pursuit
        residual = target - diffuse[:, None, :] - sg_eval(r, axis[:, :j], lam[:, :j], amp[:, :j])
        start = r[rows, _luminance(residual).argmax(dim=1)]
        axis[:, j], lam[:, j], amp[:, j] = _fit_one(r, w, residual, start, cands, shifts)
    diffuse, amp = _solve_linear(r, target, w, axis, lam)
    for _ in range(rounds):  # backfitting
        for j in range(k):
            others = [i for i in range(k) if i != j]
            residual = target - diffuse[:, None, :] - sg_eval(r, axis[:, others], lam[:, others], amp[:, others])
            axis[:, j], lam[:, j], amp[:, j] = _fit_one(r, w, residual, axis[:, j], cands, shifts)
        diffuse, amp = _solve_linear(r, target, w, axis, lam)
    if iters > 0:
        axis, lam, amp, diffuse = _polish(r, target, w, axis, lam, amp, diffuse, iters, lr, (lo, hi))
    return Lobes(diffuse, axis, lam, amp)


def _weighted_error(r: Tensor, target: Tensor, w: Tensor, diffuse: Tensor, axis: Tensor, lam: Tensor, amp: Tensor
                    ) -> Tensor:
    return (w[..., None] * (diffuse[:, None] + sg_eval(r, axis, lam, amp) - target) ** 2).sum((1, 2))


def _polish(r: Tensor, target: Tensor, w: Tensor, axis: Tensor, lam: Tensor, amp: Tensor, diffuse: Tensor,
            iters: int, lr: float, sharpness_range: tuple[float, float]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``iters`` Adam steps on all parameters together, then a least-squares solve of the diffuse colour and the
    amplitudes; each texel keeps whichever of the start and the result fits it better."""
    log_lo, log_hi = (math.log(v) for v in sharpness_range)
    p_axis = axis.clone().requires_grad_(True)
    p_log = lam.log().clone().requires_grad_(True)
    p_amp = amp.clone().requires_grad_(True)
    p_diffuse = diffuse.clone().requires_grad_(True)
    opt = torch.optim.Adam([p_axis, p_log, p_amp, p_diffuse], lr=lr)
    with torch.enable_grad():
        for _ in range(iters):
            opt.zero_grad(set_to_none=True)
            mu = p_axis / p_axis.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            # a sum over texels of per-texel errors: each texel's fit is its own, whatever the batch size
            _weighted_error(r, target, w, p_diffuse, mu, p_log.exp(), p_amp).sum().backward()
            opt.step()
            with torch.no_grad():
                p_amp.clamp_(0.0, 1.0)
                p_diffuse.clamp_(0.0, 1.0)
                p_log.clamp_(log_lo, log_hi)
    with torch.no_grad():
        mu = p_axis / p_axis.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        lam2 = p_log.exp()
        d2, a2 = _solve_linear(r, target, w, mu, lam2)
        before = _weighted_error(r, target, w, diffuse, axis, lam, amp)
        better = _weighted_error(r, target, w, d2, mu, lam2, a2) < before
        pick = lambda new, old: torch.where(better.view(-1, *([1] * (new.dim() - 1))), new, old)  # noqa: E731
        return pick(mu, axis), pick(lam2, lam), pick(a2, amp), pick(d2, diffuse)


def hemisphere_directions(n: int) -> Tensor:
    """``n`` cosine-weighted directions over the hemisphere around +z, [n, 3]: a Vogel spiral on the unit disc
    lifted to the hemisphere (Malley's method), so each stands for an equal share of projected solid angle."""
    if n < 1:
        raise ValueError(f"need at least one direction, got {n}")
    i = torch.arange(n, dtype=torch.float64)
    rad = torch.sqrt((i + 0.5) / n)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    x, y = rad * torch.cos(phi), rad * torch.sin(phi)
    z = torch.sqrt((1.0 - x * x - y * y).clamp_min(0.0))
    return torch.stack([x, y, z], -1).float()


def tangent_frames(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents ``t, b`` [B, 3] with ``(t, b, n)`` orthonormal and right-handed, for unit normals ``n``."""
    helper = torch.where(n[:, 2:3].abs() < 0.9, n.new_tensor([0.0, 0.0, 1.0]).expand_as(n),
                         n.new_tensor([1.0, 0.0, 0.0]).expand_as(n))
    t = torch.linalg.cross(helper, n)
    t = t / t.norm(dim=-1, keepdim=True)
    return t, torch.linalg.cross(n, t)


def sample_reflections(normals: Tensor, n_dirs: int, generator: torch.Generator | None = None) -> Tensor:
    """Reflected directions ``r`` [B, n_dirs, 3] about unit ``normals`` [B, 3]: the cosine-weighted hemisphere set of
    :func:`hemisphere_directions`, spun about each normal by a random angle (so neighbouring texels see different
    directions). The view direction of each is ``d = r - 2 (r . n) n``."""
    base = hemisphere_directions(n_dirs).to(normals)
    angle = torch.rand(normals.shape[0], generator=generator, device=generator.device if generator else None)
    angle = angle.to(normals) * 2 * math.pi
    c, s = angle.cos()[:, None], angle.sin()[:, None]
    x = c * base[None, :, 0] - s * base[None, :, 1]
    y = s * base[None, :, 0] + c * base[None, :, 1]
    t, b = tangent_frames(normals)
    return x[..., None] * t[:, None, :] + y[..., None] * b[:, None, :] + base[None, :, 2:3] * normals[:, None, :]


def reflect(v: Tensor, n: Tensor) -> Tensor:
    """``v - 2 (v . n) n`` (GLSL's ``reflect``), broadcasting ``n`` over ``v``."""
    return v - 2.0 * (v * n).sum(-1, keepdim=True) * n
