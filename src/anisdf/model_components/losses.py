"""The five training losses of AniSDF (paper Sec. 3.4, Eqs. 13-17; their weighted sum is Eq. 18), the mask term and
anisdf's interior prior."""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

ANGLE_CLAMP = 1e-6
"""The angle form's margin from +-1 for the dot product (the release's)."""


def rgb_loss(pred: Tensor, gt: Tensor, kind: str = "mse+l1") -> Tensor:
    """Eq. 13 (``mse``); the release adds an L1 term for object scenes and uses L1 alone on DTU."""
    loss = pred.new_zeros(())
    if "mse" in kind:
        loss = loss + F.mse_loss(pred, gt)
    if "l1" in kind:
        loss = loss + F.l1_loss(pred, gt)
    return loss


def eikonal_loss(grad: Tensor) -> Tensor:
    """Eq. 14: ``E[(||grad f(x)|| - 1)^2]``."""
    return ((grad.norm(dim=-1) - 1.0) ** 2).mean()


def curvature_loss(normal: Tensor, normal_eps: Tensor, form: Literal["squared", "angle"] = "squared") -> Tensor:
    """Eq. 15 between unit normals at ``x`` and at a tangent step from it, averaged: ``squared``, the paper's
    ``(n . n_eps - 1)^2``; ``angle``, the release's (PermutoSDF's) ``acos(n . n_eps) / pi``, in [0, 1], with the dot
    product clamped to ``[-1 + 1e-6, 1 - 1e-6]`` (acos's slope is infinite at +-1)."""
    if form == "angle":
        dot = (normal * normal_eps).sum(-1).clamp(-1.0 + ANGLE_CLAMP, 1.0 - ANGLE_CLAMP)
        return (torch.acos(dot) / math.pi).mean()
    return (((normal * normal_eps).sum(-1) - 1.0) ** 2).mean()


def orientation_loss(weights: Tensor, normal: Tensor, dirs: Tensor, ray_idx: Tensor, n_rays: int) -> Tensor:
    """Eq. 16 (Ref-NeRF): ``sum_i w_i max(0, n . d)^2`` per ray, averaged over rays."""
    per_sample = weights * torch.relu((normal * dirs).sum(-1)) ** 2
    per_ray = torch.zeros(n_rays, device=weights.device, dtype=weights.dtype).index_add_(0, ray_idx, per_sample)
    return per_ray.mean()


def alpha_entropy_loss(opacity: Tensor, eps: float = 1e-4) -> Tensor:
    """Eq. 17: ``BCE(alpha, alpha)``, the binary entropy of accumulated opacity, pushing it to 0 or 1."""
    a = opacity.clamp(eps, 1.0 - eps)
    return -(a * torch.log(a) + (1.0 - a) * torch.log(1.0 - a)).mean()


def mask_loss(opacity: Tensor, mask: Tensor, eps: float = 1e-3) -> Tensor:
    """BCE between accumulated opacity and an object mask (NeuS 'w/ mask' setting, DTU)."""
    return F.binary_cross_entropy(opacity.clamp(eps, 1.0 - eps), mask)


def interior_loss(sdf: Tensor, bound: Tensor) -> Tensor:
    """The interior prior (not in the paper; model_components/interior.py): ``E[max(0, sdf(x) - bound(x))]``."""
    return torch.relu(sdf - bound).mean()


def tangent_perturbation(x: Tensor, normal: Tensor, eps: float, generator: torch.Generator | None) -> Tensor:
    """Points ``x + eps * t`` with ``t`` a random unit tangent to the (detached) normal."""
    dev = generator.device if generator is not None else x.device
    r = torch.randn(x.shape, generator=generator, device=dev).to(x.device, x.dtype)
    n = normal.detach()
    t = F.normalize(torch.linalg.cross(n, r), dim=-1)
    return x + eps * t
