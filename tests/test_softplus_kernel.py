"""The compiled softplus-with-slope kernel against its PyTorch reference (fields/softplus.py): values, the backward,
and the SDF MLP with its closed-form normal built on either."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from anisdf.config import load_config
from anisdf.fields import asg, mlp, sdf_mlp
from anisdf.fields import softplus as sp
from anisdf.fields.sdf_field import BETA, SDFField, mlp_with_input_grad
from anisdf.models.anisdf import AniSDFModel


def _pre_activations() -> torch.Tensor:
    """Pre-activations over every regime of softplus_100: deep negative (exp underflows), around the kink, large
    positive (softplus = z), exact zeros and tiny values."""
    g = torch.Generator().manual_seed(0)
    parts = [torch.randn(4000, generator=g) * s for s in (1e-3, 1e-2, 0.05, 0.3, 3.0)]
    parts.append(torch.tensor([0.0, -0.0, 1e-9, -1e-9, 0.2, -0.2, 0.87, -0.87, 50.0, -50.0, 1e3, -1e3]))
    return torch.cat(parts).reshape(-1, 4)


def test_values_match_pytorch(kernel) -> None:
    z = _pre_activations()
    a, s = sp.softplus_slope(z, BETA)
    a_ref, s_ref = sp.softplus_slope_reference(z, BETA)
    # a few float32 ulps of the value (softplus_100 is at least 0 and at most |z| + 0.007)
    torch.testing.assert_close(a, a_ref, rtol=2e-6, atol=1e-9)
    torch.testing.assert_close(s, s_ref, rtol=2e-6, atol=3e-7)
    torch.testing.assert_close(sp.softplus(z, BETA), F.softplus(z, beta=BETA), rtol=2e-6, atol=1e-9)
    assert (a >= 0).all() and ((s >= 0) & (s <= 1)).all()


def test_no_output_is_denormal(kernel) -> None:
    """Deep in the negative tail softplus_100 and its slope would be denormal floats (exp(-87) / 100 is), and every
    product with a denormal costs the CPU a microcode assist: the kernel stops the tail at exp(-40) instead."""
    z = -torch.linspace(0.3, 20.0, 4096).reshape(-1, 64)
    a, s = sp.softplus_slope(z, BETA)
    tiny = torch.finfo(torch.float32).tiny
    assert (a >= tiny).all() and (s >= tiny).all()
    assert float(a.max()) < 1e-15 and float(s.max()) < 1e-13  # still the tail: below what float32 can add to 1


@pytest.mark.parametrize("which", ["both", "value", "slope"])
def test_backward_matches_autograd(kernel, which: str) -> None:
    z = _pre_activations().requires_grad_(True)
    g = torch.Generator().manual_seed(1)
    wa, ws = torch.randn(z.shape, generator=g), torch.randn(z.shape, generator=g)

    def loss(a: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        return (a * wa).sum() * (which != "slope") + (s * ws).sum() * (which != "value")

    (gz,) = torch.autograd.grad(loss(*sp.softplus_slope(z, BETA)), z)
    a_ref, s_ref = sp.softplus_slope_reference(z, BETA)
    (gz_ref,) = torch.autograd.grad(loss(a_ref, s_ref), z)
    torch.testing.assert_close(gz, gz_ref, rtol=1e-5, atol=1e-5 * float(gz_ref.abs().max()))


def test_sdf_mlp_with_kernel_matches_reference(kernel) -> None:
    """The closed-form MLP (outputs, normals, and the gradients of a loss on both w.r.t. every weight) is the same
    function on the kernel as on PyTorch's operators."""
    g = torch.Generator().manual_seed(2)
    dims = [27, 64, 64, 65]
    ws = [(torch.randn(dims[i + 1], dims[i], generator=g) * 0.15).requires_grad_(True) for i in range(3)]
    bs = [(torch.randn(dims[i + 1], generator=g) * 0.02).requires_grad_(True) for i in range(3)]
    h = torch.randn(3000, 27, generator=g) * 0.5

    def run(fast: bool) -> list[torch.Tensor]:
        out, hidden, grad = mlp_with_input_grad(h, ws, bs, fast)
        loss = out.square().mean() + hidden.sin().mean() + (grad.norm(dim=-1) - 1).square().mean()
        return [out, hidden, grad, *torch.autograd.grad(loss, [*ws, *bs])]

    for got, want in zip(run(True), run(False), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5 * float(want.detach().abs().max()))


def test_reference_backend_stays_on_pytorch(monkeypatch) -> None:
    """``geometry.encoding_backend=torch`` is the pure-PyTorch reference: its SDF and ASG heads never call the
    kernel."""
    def forbidden(z):
        raise AssertionError("a compiled kernel ran under encoding_backend=torch")

    for module in (sp, asg, sdf_mlp, mlp):
        monkeypatch.setattr(module, "kernel_for", forbidden)
    cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch"])
    field = SDFField(cfg.geometry)
    x = torch.rand(64, 3) * 1.6 - 0.8
    sdf, _, grad = field.with_gradient(x, create_graph=True)
    assert torch.isfinite(sdf).all() and torch.isfinite(grad).all()
    assert torch.isfinite(field.distance(x)).all()
    model = AniSDFModel(cfg)
    feat = torch.randn(64, cfg.geometry.feature_dim)
    n = F.normalize(grad.detach(), dim=-1)
    assert torch.isfinite(model.appearance(x, feat, n, -n)["rgb"]).all()
