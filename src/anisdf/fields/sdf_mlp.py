"""The SDF MLP (softplus, beta = 100) with its input gradient in closed form: the normal of Eq. 5's branches.

``out_0 = w_L sp(... sp(W_1 h + b_1) ...) + b_L[0]`` and ``d out_0 / d h = (((w_L * s_K) W_K * s_{K-1}) ... * s_1) W_1``
with ``s_k = sigmoid(beta z_k)`` the slope of softplus at layer ``k``'s pre-activation. Training puts the eikonal
and curvature losses (Eqs. 14-15) on this gradient, so it must be differentiable w.r.t. the weights.

:func:`mlp_with_input_grad_reference` writes it with PyTorch operators and lets autograd differentiate it: one
ordinary backward, no double backward, a plain graph that ``torch.compile`` fuses (``train.compile``). On CPU,
:func:`mlp_with_input_grad` runs the same maths as one autograd node whose forward and hand-written backward are
the compiled kernel's (``kernels/sdf_mlp_cpu.cpp``): each tile of rows goes through every layer's product and
element-wise work (bias, softplus, slope, the gradient's factors; in the backward the slope's derivative, the
gradient products and the bias sums) while it is in cache, instead of autograd's dozen whole-matrix passes.
tests/test_sdf_mlp.py compares the two.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.fields.hash_grid.cpu_kernel import kernel_for
from anisdf.fields.softplus import softplus, softplus_slope

BETA = 100.0  # Softplus sharpness of the SDF MLPs (NeuS, the release)


def mlp_with_input_grad_reference(h: Tensor, weights: list[Tensor], biases: list[Tensor], fast: bool = True
                                  ) -> tuple[Tensor, Tensor, Tensor]:
    """The first output ``out_0`` [N] of a softplus MLP, its last hidden activation ``a`` [N, H] and
    ``d out_0 / d h`` [N, D], with PyTorch's operators (each softplus with its slope from one pass of the compiled
    kernel where ``fast``: :func:`anisdf.fields.softplus.softplus_slope`). The other outputs (the geometry feature)
    are ``F.linear(a, W_L[1:], b_L[1:])``, computed by the caller for the rows that need them."""
    slopes = []
    for w, b in zip(weights[:-1], biases[:-1], strict=True):
        h, s = softplus_slope(F.linear(h, w, b), BETA, fast)
        slopes.append(s)
    w_sdf = weights[-1][0]
    out0 = torch.addmv(biases[-1][0].expand(h.shape[0]), h, w_sdf)  # a 0-d bias: a 0-d result for 0 rows
    g = w_sdf.expand(h.shape[0], -1)
    for w, s in zip(reversed(weights[:-1]), reversed(slopes), strict=True):
        g = (g * s) @ w
    return out0, h, g


def mlp_distance(h: Tensor, weights: list[Tensor], biases: list[Tensor], fast: bool = True) -> Tensor:
    """``out_0`` [N] alone (queries that need neither feature nor normal: pruning, grids, meshes). Without gradient
    on CPU each hidden layer is a product without bias and one in-place kernel pass (bias and softplus)."""
    mod = kernel_for(h) if fast and not torch.is_grad_enabled() else None
    for w, b in zip(weights[:-1], biases[:-1], strict=True):
        if mod is None:
            h = softplus(F.linear(h, w, b), BETA, fast)
        else:
            h = mod.bias_softplus_(torch.mm(h, w.t()), b, BETA)
    return torch.addmv(biases[-1][0].expand(h.shape[0]), h, weights[-1][0])


def mlp_with_input_grad(h: Tensor, weights: list[Tensor], biases: list[Tensor], fast: bool = True
                        ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`mlp_with_input_grad_reference`'s outputs, by the fused CPU path where ``fast`` and the compiled
    kernel applies (float32 CPU, outside ``torch.compile``), else by the reference."""
    mod = kernel_for(h) if fast else None
    if mod is None or len(weights) < 2:
        return mlp_with_input_grad_reference(h, weights, biases, fast)
    hidden = [t for wb in zip(weights[:-1], biases[:-1], strict=True) for t in wb]
    return _FusedMLPWithInputGrad.apply(h, mod, weights[-1][0], biases[-1][0], *hidden)


class _FusedMLPWithInputGrad(torch.autograd.Function):
    """Layers ``k = 0..K-1``: ``z_k = h_k W_k^T + b_k``, ``h_{k+1} = sp(z_k)``, ``s_k = sigmoid(beta z_k)``; the
    gradient ``gs_{K-1} = w s_{K-1}``, ``g_k = gs_k W_k`` (``g_0`` the output), ``gs_{k-1} = g_k s_{k-1}``.
    Forward and backward are the compiled kernel's (``kernels/sdf_mlp_cpu.cpp``), a tile of rows at a time."""

    @staticmethod
    def forward(ctx: Any, h0: Tensor, mod: Any, w: Tensor, b_out: Tensor, *hidden: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        ws, bs = list(hidden[0::2]), list(hidden[1::2])
        h0 = h0.contiguous()
        n = len(ws)
        out0, g0, *rest = mod.sdf_mlp_forward(h0, ws, bs, w, b_out, BETA)
        acts = rest[:n]  # a_1..a_K; slopes, gs and the gradient's inner factors follow
        ctx.mod, ctx.n_layers = mod, n
        ctx.save_for_backward(w, h0, *ws, *rest)
        ctx.set_materialize_grads(False)  # an output nothing depends on has no gradient: None, not zeros
        return out0, acts[-1], g0

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, d_out0: Tensor | None, d_top: Tensor | None, d_g0: Tensor | None
                 ) -> tuple[Tensor | None, ...]:
        n = ctx.n_layers
        w, h0, *saved = ctx.saved_tensors
        ws, acts, slopes = saved[:n], [h0, *saved[n : 2 * n]], saved[2 * n : 3 * n]
        gss, gins = saved[3 * n : 4 * n], saved[4 * n :]
        d_h0, d_w, d_b_out, *grads = ctx.mod.sdf_mlp_backward(
            ws, w, acts, slopes, gss, gins, d_out0, d_top, d_g0, ctx.needs_input_grad[0], BETA)
        hidden_grads = [t for pair in zip(grads[:n], grads[n:], strict=True) for t in pair]
        return (d_h0, None, d_w, d_b_out, *hidden_grads)
