"""Anisotropic spherical Gaussian (ASG) encoding of the reflected direction (paper Eqs. 8-9).

``ASG(w | [x, y, z], [lambda, mu], xi) = xi * max(w . z, 0) * exp(-lambda (w . x)^2 - mu (w . y)^2)``

The lobe frames are fixed: ``n_theta x n_phi`` axes ``z`` spread over the sphere, tangent ``x`` the axis at
``theta + pi/2`` and bitangent ``y = z x x``. Sharpness (lambda, mu) and the 2-channel amplitude xi are predicted
per point by a small network ``f_par`` (see :mod:`anisdf.fields.radiance_field`). Following the paper, the unit
reflected direction enters the dot products (the authors' release used (r + 1) / 2).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


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
