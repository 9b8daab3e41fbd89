"""Anisotropic spherical Gaussian (ASG) encoding of the reflected direction (paper Eqs. 8-9).

``ASG(w | [x, y, z], [lambda, mu], xi) = xi * max(w . z, 0) * exp(-lambda (w . x)^2 - mu (w . y)^2)``

The lobe frames are fixed: ``n_theta x n_phi`` axes ``z`` spread over the sphere, tangent ``x`` the axis at
``theta + pi/2`` and bitangent ``y = z x x``. Sharpness (lambda, mu) and the 2-channel amplitude xi are predicted
per point by a small network ``f_par`` (see :mod:`anisdf.fields.radiance_field`). Following the paper, the unit
reflected direction enters the dot products (the authors' release used (r + 1) / 2).

:func:`asg_features` takes ``f_par``'s raw output: the sharpnesses' softplus and the encoding in one step, on CPU by
the compiled kernel (``kernels/asg_cpu.cpp``, forward and backward) when it applies, else by
:func:`asg_features_reference` in PyTorch; tests/test_asg_kernel.py compares the two.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.fields.hash_grid.cpu_kernel import kernel_for


def asg_frames(n_theta: int = 8, n_phi: int = 16) -> Tensor:
    """Fixed orthonormal lobe frames ``[N, 3, 3]`` with rows (x, y, z), ``N = n_theta * n_phi``."""
    theta = (torch.arange(n_theta, dtype=torch.float64) + 0.5) * math.pi / n_theta
    phi = torch.arange(n_phi, dtype=torch.float64) * 2 * math.pi / n_phi
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    th, ph = th.reshape(-1), ph.reshape(-1)

    def sph(t: Tensor, p: Tensor) -> Tensor:
        return torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], dim=-1)

    z = sph(th, ph)
    x = sph(th + math.pi / 2, ph)
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z], dim=1).float()


def asg_encode(w: Tensor, frames: Tensor, lam: Tensor, mu: Tensor, xi: Tensor) -> Tensor:
    """ASG features of unit directions ``w`` [B, 3].

    ``frames`` [N, 3, 3]; ``lam``, ``mu`` [B, N] (positive); ``xi`` [B, N, C]. Returns [B, N * C].
    """
    dots = torch.einsum("bk,nrk->bnr", w, frames)  # [B, N, 3]: w.x, w.y, w.z
    smooth = dots[..., 2].clamp_min(0.0)
    lobe = smooth * torch.exp(-lam * dots[..., 0] ** 2 - mu * dots[..., 1] ** 2)
    return (xi * lobe[..., None]).flatten(1)


def asg_features_reference(par: Tensor, w: Tensor, frames: Tensor) -> Tensor:
    """ASG features [B, N * 2] of unit directions ``w`` [B, 3] from raw lobe parameters ``par`` [B, N, 4]:
    ``lambda = softplus(par[..., 0])``, ``mu = softplus(par[..., 1])``, ``xi = par[..., 2:]`` (PyTorch's operators)."""
    lam_mu = F.softplus(par[..., :2])
    return asg_encode(w, frames, lam_mu[..., 0], lam_mu[..., 1], par[..., 2:])


class _ASGFeatures(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, par: Tensor, w: Tensor, frames: Tensor, mod: Any) -> Tensor:
        ctx.save_for_backward(par, w, frames)
        ctx.mod = mod
        return mod.asg_forward(par, w, frames)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, Tensor | None, None, None]:
        par, w, frames = ctx.saved_tensors
        grad_par, grad_w = ctx.mod.asg_backward(grad, par, w, frames, ctx.needs_input_grad[1])
        return grad_par, grad_w, None, None


def asg_features(par: Tensor, w: Tensor, frames: Tensor, fast: bool = True) -> Tensor:
    """:func:`asg_features_reference`, by the compiled kernel when ``fast`` and it applies (float32 CPU tensors,
    not inside ``torch.compile``); differentiable once in ``par`` and ``w``."""
    mod = kernel_for(par) if fast else None
    if mod is None or w.dtype != torch.float32:
        return asg_features_reference(par, w, frames)
    return _ASGFeatures.apply(par, w, frames, mod)
