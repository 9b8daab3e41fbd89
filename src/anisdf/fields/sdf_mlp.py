"""The SDF MLP (softplus, beta = 100) with its input gradient in closed form: the normal of Eq. 5's branches.

``out_0 = w_L sp(... sp(W_1 h + b_1) ...) + b_L[0]`` and ``d out_0 / d h = (((w_L * s_K) W_K * s_{K-1}) ... * s_1) W_1``
with ``s_k = sigmoid(beta z_k)`` the slope of softplus at layer ``k``'s pre-activation. Training puts the eikonal
and curvature losses (Eqs. 14-15) on this gradient, so it must be differentiable w.r.t. the weights.

:func:`mlp_with_input_grad_reference` writes it with PyTorch operators and lets autograd differentiate it: one
ordinary backward, no double backward, a plain graph that ``torch.compile`` fuses (``train.compile``). On CPU,
:func:`mlp_with_input_grad` runs the same maths as one autograd node with a hand-written backward: the matrix
products stay with PyTorch, and the element-wise work around each layer (bias, softplus, slope, the gradient's
first factor; in the backward the slope's derivative, the gradient products and the bias sums) is one pass of the
compiled kernel (``kernels/softplus_cpu.cpp``) instead of the dozen passes and gradient accumulations autograd
makes. tests/test_sdf_mlp.py compares the two.
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
            h = mod.softplus_bias_slope(torch.mm(h, w.t()), b, BETA, None, False)[0]
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
    gradient ``gs_{K-1} = w s_{K-1}``, ``g_k = gs_k W_k`` (``g_0`` the output), ``gs_{k-1} = g_k s_{k-1}``."""

    @staticmethod
    def forward(ctx: Any, h0: Tensor, mod: Any, w: Tensor, b_out: Tensor, *hidden: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        ws, bs = hidden[0::2], hidden[1::2]
        n_layers = len(ws)
        acts, slopes = [h0], []
        gs = None
        for k in range(n_layers):
            z = torch.mm(acts[-1], ws[k].t())
            a, s, gs = mod.softplus_bias_slope(z, bs[k], BETA, w if k == n_layers - 1 else None)
            acts.append(a)
            slopes.append(s)
        out0 = torch.addmv(b_out.expand(h0.shape[0]), acts[-1], w)
        gss, gins = [gs], []  # gs_k, from the top; gins: g_k for k >= 1, the factor entering gs_{k-1}
        for k in range(n_layers - 1, 0, -1):
            g = torch.mm(gss[0], ws[k])
            gins.insert(0, g)
            gss.insert(0, g * slopes[k - 1])
        g0 = torch.mm(gss[0], ws[0])
        ctx.mod, ctx.n_layers = mod, n_layers
        ctx.save_for_backward(w, *ws, *acts, *slopes, *gss, *gins)
        ctx.set_materialize_grads(False)  # an output nothing depends on has no gradient: None, not zeros
        return out0, acts[-1], g0

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, d_out0: Tensor | None, d_top: Tensor | None, d_g0: Tensor | None
                 ) -> tuple[Tensor | None, ...]:
        n, mod = ctx.n_layers, ctx.mod
        saved = ctx.saved_tensors
        w, ws = saved[0], saved[1 : 1 + n]
        acts = saved[1 + n : 2 + 2 * n]
        slopes = saved[2 + 2 * n : 2 + 3 * n]
        gss = saved[2 + 3 * n : 2 + 4 * n]
        gins = saved[2 + 4 * n :]
        d_ws: list[Tensor | None] = [None] * n
        d_gss: list[Tensor | None] = [None] * n
        if d_g0 is not None:  # the gradient's chain, bottom up: g_k = gs_k W_k, gs_k = g_{k+1} s_k
            d_g = d_g0.contiguous()
            for k in range(n):
                d_gss[k] = torch.mm(d_g, ws[k].t())
                d_ws[k] = torch.mm(gss[k].t(), d_g)
                if k < n - 1:
                    d_g = d_gss[k] * slopes[k]
        d_a = d_top
        d_w = torch.mv(acts[-1].t(), d_out0) if d_out0 is not None else None
        d_b_out = d_out0.sum() if d_out0 is not None else None
        d_bs: list[Tensor] = []
        d_h0 = None
        for k in range(n - 1, -1, -1):  # each layer top down: dz_k from the activation's and the slope's gradients
            top = k == n - 1
            dz, db, dw_chain = mod.softplus_layer_backward(
                slopes[k], BETA, d_a, d_out0 if top else None, w if top else None, d_gss[k],
                None if top else gins[k])
            if dw_chain is not None:
                d_w = dw_chain if d_w is None else d_w + dw_chain
            d_bs.insert(0, db)
            d_ws[k] = torch.mm(dz.t(), acts[k]) if d_ws[k] is None else torch.addmm(d_ws[k], dz.t(), acts[k])
            if k > 0 or ctx.needs_input_grad[0]:
                d_a = torch.mm(dz, ws[k])
        if ctx.needs_input_grad[0]:
            d_h0 = d_a
        hidden_grads = [t for pair in zip(d_ws, d_bs, strict=True) for t in pair]
        return (d_h0, None, d_w, d_b_out, *hidden_grads)
