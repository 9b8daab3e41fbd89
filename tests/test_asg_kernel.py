"""The compiled ASG encoding (kernels/asg_cpu.cpp) against its PyTorch reference (fields/asg.py): the features, the
gradients of the lobe parameters and of the direction, and the colour heads built on either."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from anisdf.config import load_config
from anisdf.fields.asg import asg_features, asg_features_reference, asg_frames
from anisdf.fields.radiance_field import RadianceField


def _inputs(n: int = 3000, lobes: tuple[int, int] = (4, 8)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw lobe parameters over every regime of the softplus (deep negative, around 0, past PyTorch's linear
    threshold of 20), directions all round the sphere (behind a lobe as well: w . z < 0) and next to the lobe axes.
    Not on them: an axis is at right angles to other lobes' axes, where max(w . z, 0) has its kink and the two
    codes' roundings of w . z = 0 pick different sides of it."""
    g = torch.Generator().manual_seed(0)
    frames = asg_frames(*lobes)
    n_lobes = frames.shape[0]
    par = torch.randn(n, n_lobes, 4, generator=g) * torch.tensor([4.0, 4.0, 1.0, 1.0])
    par[:50, :, :2] = torch.tensor([-30.0, 25.0])
    par[50:60, :, :2] = 0.0
    w = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
    w[:n_lobes] = F.normalize(frames[:, 2] + 0.01 * frames[:, 0] + 0.02 * frames[:, 1], dim=-1)
    return par, w, frames


def test_features_and_gradients_match_reference(kernel) -> None:
    par, w, frames = _inputs()
    par.requires_grad_(True)
    w.requires_grad_(True)
    got, want = asg_features(par, w, frames), asg_features_reference(par, w, frames)
    assert got.shape == want.shape == (par.shape[0], frames.shape[0] * 2)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    c = torch.randn(got.shape, generator=torch.Generator().manual_seed(1))
    g_got = torch.autograd.grad((got * c).sum(), [par, w])
    g_want = torch.autograd.grad((want * c).sum(), [par, w])
    for a, b in zip(g_got, g_want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


def test_direction_without_gradient(kernel) -> None:
    """A direction that needs no gradient (images of a fixed model's colour under training of the heads alone)
    gets none, and the parameters' gradient is unchanged."""
    par, w, frames = _inputs(500)
    par.requires_grad_(True)
    (g_par,) = torch.autograd.grad(asg_features(par, w, frames).square().sum(), [par])
    (g_ref,) = torch.autograd.grad(asg_features_reference(par, w, frames).square().sum(), [par])
    torch.testing.assert_close(g_par, g_ref, rtol=1e-4, atol=1e-5 * float(g_ref.abs().max()))


def test_bad_shapes_are_refused(kernel) -> None:
    par, w, frames = _inputs(40)
    with pytest.raises(RuntimeError, match=r"par must be \[B, L, 4\]"):
        kernel.asg_forward(par[..., :3].contiguous(), w, frames)
    with pytest.raises(RuntimeError, match=r"w must be \[B, 3\]"):
        kernel.asg_forward(par, w[:5], frames)


def test_colour_heads_with_kernel_match_reference(kernel) -> None:
    """The reflection branch by the kernel: the same colours, and the same gradients of every head parameter and
    of the normal (the route by which colour trains the geometry), as with PyTorch's operators."""
    cfg = load_config("cpu-quick")
    torch.manual_seed(0)
    fast = RadianceField(cfg.appearance, cfg.geometry.feature_dim, fast=True)
    ref = RadianceField(cfg.appearance, cfg.geometry.feature_dim, fast=False)
    ref.load_state_dict(fast.state_dict())
    g = torch.Generator().manual_seed(3)
    x, feat = torch.rand(2000, 3, generator=g) - 0.5, torch.randn(2000, cfg.geometry.feature_dim, generator=g)
    n, d = (F.normalize(torch.randn(2000, 3, generator=g), dim=-1) for _ in range(2))

    def run(field: RadianceField) -> list[torch.Tensor]:
        normal = n.clone().requires_grad_(True)
        rgb = field(x, feat, normal, d)["rgb"]
        return [rgb, *torch.autograd.grad(rgb.square().sum(), [normal, *field.parameters()])]

    for got, want in zip(run(fast), run(ref), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5 * float(want.detach().abs().max()))
