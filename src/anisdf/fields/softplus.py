"""The SDF MLPs' activation: softplus (sharpness ``beta``, NeuS) and its slope ``sigmoid(beta z)`` in one pass.

The closed-form normal (:func:`anisdf.fields.sdf_field.mlp_with_input_grad`) needs both at every hidden layer.
:func:`softplus_slope_reference` computes them with PyTorch's operators; on CPU the compiled kernel
(``kernels/softplus_cpu.cpp``, in the hash grid's extension) computes both in one branch-free pass, with the
backward ``dz = da s + ds beta s (1 - s)`` in another. It is used for float32 CPU tensors when the extension is
available and ``geometry.encoding_backend`` is not ``torch`` (the pure-PyTorch reference path), and never inside
``torch.compile`` (which fuses the reference itself). tests/test_softplus_kernel.py compares the two.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.fields.hash_grid.cpu_kernel import kernel_for


def softplus_slope_reference(z: Tensor, beta: float) -> tuple[Tensor, Tensor]:
    """``(softplus(z, beta), sigmoid(beta z))`` with PyTorch's operators."""
    return F.softplus(z, beta=beta), torch.sigmoid(beta * z)


class _SoftplusSlope(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, z: Tensor, beta: float, mod: Any) -> tuple[Tensor, Tensor]:
        a, s = mod.softplus_slope(z, beta, True)
        ctx.save_for_backward(s)
        ctx.beta, ctx.mod = beta, mod
        return a, s

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, da: Tensor | None, ds: Tensor | None) -> tuple[Tensor, None, None]:
        (s,) = ctx.saved_tensors
        return ctx.mod.softplus_slope_backward(s, da, ds, ctx.beta), None, None


def softplus_slope(z: Tensor, beta: float, fast: bool = True) -> tuple[Tensor, Tensor]:
    """``(softplus(z, beta), sigmoid(beta z))``, differentiable (once) in ``z``; the compiled kernel when ``fast``
    and it applies, else :func:`softplus_slope_reference`."""
    mod = kernel_for(z) if fast else None
    if mod is None:
        return softplus_slope_reference(z, beta)
    return _SoftplusSlope.apply(z, beta, mod)


def softplus(z: Tensor, beta: float, fast: bool = True) -> Tensor:
    """``softplus(z, beta)``: the compiled kernel when ``fast`` and it applies (without gradient it skips the slope:
    queries of a fixed field, such as pruning, occupancy grids, images and meshes), else PyTorch's."""
    mod = kernel_for(z) if fast else None
    if mod is None:
        return F.softplus(z, beta=beta)
    if torch.is_grad_enabled() and z.requires_grad:
        return _SoftplusSlope.apply(z, beta, mod)[0]
    return mod.softplus_slope(z, beta, False)[0]
