"""The colour heads' ReLU MLPs: the fused CPU path (kernels/relu_cpu.cpp, hand-written backward) against the
``nn.Sequential`` itself (fields/mlp.py)."""

from __future__ import annotations

import pytest
import torch

from anisdf.fields.mlp import mlp, run_mlp


@pytest.mark.parametrize("n_hidden", [0, 1, 2])
def test_fused_mlp_matches_the_module(kernel, n_hidden: int) -> None:
    torch.manual_seed(0)
    net = mlp(70, 64, n_hidden, 5)
    x = torch.randn(3000, 70).requires_grad_(True)
    up = torch.randn(3000, 5)

    def run(fn) -> list[torch.Tensor]:
        y = fn(x)
        return [y, *torch.autograd.grad((y * up).sum(), [x, *net.parameters()])]

    got = run(lambda v: run_mlp(net, v))
    want = run(net)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.detach().abs().max()))


def test_fused_mlp_leaves_its_input_and_incoming_gradient_alone(kernel) -> None:
    torch.manual_seed(1)
    net = mlp(8, 16, 2, 3)
    x = torch.randn(50, 8)
    x0 = x.clone()
    y = run_mlp(net, x)
    d = torch.randn_like(y)
    d0 = d.clone()
    y.backward(d)
    assert torch.equal(x, x0) and torch.equal(d, d0)
    assert all(p.grad is not None for p in net.parameters())


def test_fused_mlp_is_used_and_rows_can_be_empty(kernel) -> None:
    net = mlp(8, 16, 1, 3)
    x = torch.zeros(0, 8, requires_grad=True)
    y = run_mlp(net, x)
    assert y.shape == (0, 3) and y.grad_fn is not None and "Fused" in type(y.grad_fn).__name__
    y.sum().backward()
    assert not net[0].weight.grad.abs().any()


def test_kernel_rejects_a_bias_of_the_wrong_size(kernel) -> None:
    with pytest.raises(RuntimeError, match="b must be a float32 CPU vector of 4 elements"):
        kernel.bias_act_(torch.zeros(3, 4), torch.zeros(5), True)
