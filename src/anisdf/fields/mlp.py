"""The colour heads' small ReLU MLPs (``Psi_v``, ``Psi_r``, ``Psi_w``, ``f_par``: Eqs. 9-11).

:func:`mlp` builds one as an ``nn.Sequential`` of ``Linear`` and ``ReLU`` (the reference: calling it). On CPU,
:func:`run_mlp` evaluates it as one autograd node with a hand-written backward: PyTorch's matrix products without
the bias, and each layer's bias and ReLU in one in-place pass of the compiled kernel (``kernels/relu_cpu.cpp``); the
backward masks each layer's gradient and sums its bias gradient in one pass, where autograd copies the bias into
every product's output, applies the ReLU, masks and sums in separate passes. tests/test_mlp_kernel.py compares the
two.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from anisdf.fields.hash_grid.cpu_kernel import kernel_for


def mlp(in_dim: int, hidden: int, n_hidden: int, out_dim: int) -> nn.Sequential:
    """``n_hidden`` layers of ``hidden`` units with ReLU, then a linear layer to ``out_dim``."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(n_hidden):
        layers += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def run_mlp(net: nn.Sequential, x: Tensor, fast: bool = True) -> Tensor:
    """``net(x)`` for an :func:`mlp`; by the fused CPU path where ``fast`` and the compiled kernel applies (float32
    CPU, outside ``torch.compile`` and autocast), else by the module itself."""
    mod = kernel_for(x) if fast and not torch.is_autocast_enabled(x.device.type) else None
    if mod is None:
        return net(x)
    params = [t for layer in net if isinstance(layer, nn.Linear) for t in (layer.weight, layer.bias)]
    return _FusedReluMLP.apply(x.contiguous(), mod, *params)


class _FusedReluMLP(torch.autograd.Function):
    """``h_{k+1} = relu(h_k W_k^T + b_k)`` for the hidden layers, ``out = h_K W_K^T + b_K``."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, mod: Any, *params: Tensor) -> Tensor:
        ws, bs = params[0::2], params[1::2]
        acts = [x]
        for w, b in zip(ws[:-1], bs[:-1], strict=True):
            acts.append(mod.bias_act_(torch.mm(acts[-1], w.t()), b, True))
        out = mod.bias_act_(torch.mm(acts[-1], ws[-1].t()), bs[-1], False)
        ctx.mod = mod
        ctx.save_for_backward(*ws, *acts)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, d_out: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors
        n = len(saved) // 2
        ws, acts = saved[:n], saved[n:]
        d = d_out.contiguous()
        grads: list[Tensor] = []
        d_x = None
        for k in range(n - 1, -1, -1):
            db = d.sum(0) if k == n - 1 else ctx.mod.relu_backward_(d, acts[k + 1])  # d masked in place
            grads[:0] = [torch.mm(d.t(), acts[k]), db]
            if k > 0 or ctx.needs_input_grad[0]:
                d_x = torch.mm(d, ws[k])
                d = d_x
        return (d_x if ctx.needs_input_grad[0] else None, None, *grads)
