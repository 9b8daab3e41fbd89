"""The SDF MLP with its closed-form input gradient: the compiled CPU kernel (forward and hand-written backward by
tiles of rows, kernels/sdf_mlp_cpu.cpp) against the autograd reference (fields/sdf_mlp.py)."""

from __future__ import annotations

import pytest
import torch

from anisdf.fields import sdf_mlp


def _mlp(n_hidden: int, d_in: int = 27, width: int = 64, n_out: int = 17, seed: int = 0
         ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    dims = [d_in] + [width] * n_hidden + [n_out]
    ws = [(torch.randn(dims[i + 1], dims[i], generator=g) * 0.3).requires_grad_(True) for i in range(len(dims) - 1)]
    bs = [(torch.randn(dims[i + 1], generator=g) * 0.05).requires_grad_(True) for i in range(len(dims) - 1)]
    return ws, bs


def _grads(fn, h: torch.Tensor, ws: list[torch.Tensor], bs: list[torch.Tensor], use: str, rows: torch.Tensor
           ) -> list[torch.Tensor]:
    """Outputs and the gradients of a loss on the outputs named in ``use`` (out, hidden (feature rows), grad)."""
    out, hidden, grad = fn(h, ws, bs)
    loss = h.new_zeros(())
    if "out" in use:
        loss = loss + (out * torch.linspace(-1, 2, out.shape[0])).sum()
    if "hidden" in use:  # the feature of some rows, as the renderer asks for them
        feat = torch.nn.functional.linear(hidden.index_select(0, rows), ws[-1][1:], bs[-1][1:])
        loss = loss + feat.sin().sum()
    if "grad" in use:  # eikonal, and the grid part of the gradient as forward_with_grad slices it
        loss = loss + (grad.norm(dim=-1) - 1).square().sum() + grad[:, 3:9].square().sum()
    return [out, hidden, grad, *torch.autograd.grad(loss, [h, *ws, *bs], allow_unused=True)]


@pytest.mark.parametrize("n_hidden", [1, 2, 3])
@pytest.mark.parametrize("use", ["out+hidden+grad", "grad", "out", "hidden+grad"])
def test_fused_path_matches_the_reference(kernel, n_hidden: int, use: str) -> None:
    ws, bs = _mlp(n_hidden)
    g = torch.Generator().manual_seed(1)
    h = (torch.randn(1500, 27, generator=g) * 0.4).requires_grad_(True)
    rows = torch.randperm(1500, generator=g)[:900]
    got = _grads(sdf_mlp.mlp_with_input_grad, h, ws, bs, use, rows)
    want = _grads(sdf_mlp.mlp_with_input_grad_reference, h, ws, bs, use, rows)
    for a, b in zip(got, want, strict=True):
        if b is None:
            assert a is None or not a.abs().any()
            continue
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * max(float(b.detach().abs().max()), 1e-6))


def test_tile_products_without_blas_match_the_reference(kernel) -> None:
    """Where torch exports no sgemm_ (or it fails the kernel's self-check) the tiles' products are at::mm_out."""
    ws, bs = _mlp(2)
    g = torch.Generator().manual_seed(4)
    h = (torch.randn(1300, 27, generator=g) * 0.4).requires_grad_(True)
    rows = torch.randperm(1300, generator=g)[:700]
    was = kernel.sdf_mlp_allow_blas(False)
    try:
        got = _grads(sdf_mlp.mlp_with_input_grad, h, ws, bs, "out+hidden+grad", rows)
    finally:
        kernel.sdf_mlp_allow_blas(was)
    want = _grads(sdf_mlp.mlp_with_input_grad_reference, h, ws, bs, "out+hidden+grad", rows)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * max(float(b.detach().abs().max()), 1e-6))


def test_fused_path_is_taken_and_handles_no_rows(kernel, monkeypatch) -> None:
    ws, bs = _mlp(2)
    calls = []
    real = sdf_mlp._FusedMLPWithInputGrad.apply
    monkeypatch.setattr(sdf_mlp._FusedMLPWithInputGrad, "apply", lambda *a: calls.append(1) or real(*a))
    h = torch.zeros(0, 27, requires_grad=True)
    out, hidden, grad = sdf_mlp.mlp_with_input_grad(h, ws, bs)
    assert calls and out.shape == (0,) and hidden.shape == (0, 64) and grad.shape == (0, 27)
    (out.sum() + grad.sum()).backward()
    assert all(w.grad is not None and not w.grad.abs().any() for w in ws[:-1])


def test_gradients_do_not_depend_on_the_thread_count(kernel) -> None:
    """The kernel sums every weight and bias gradient per tile of rows and adds the tiles in order, each tile's
    products on one thread: 1 and 2 threads give the same bits, also for a single tile (N below the tile size)."""
    ws, bs = _mlp(2)
    threads = torch.get_num_threads()
    for n_rows in (5000, 300):
        h = (torch.randn(n_rows, 27, generator=torch.Generator().manual_seed(2)) * 0.4).requires_grad_(True)
        rows = torch.arange(0, n_rows, 3)
        results = []
        try:
            for n in (1, 2):
                torch.set_num_threads(n)
                results.append(_grads(sdf_mlp.mlp_with_input_grad, h, ws, bs, "out+hidden+grad", rows))
        finally:
            torch.set_num_threads(threads)
        # the feature layer (ws[-1][1:]) is the caller's PyTorch product: its gradient's split is oneDNN's
        skip = {4 + len(ws) - 1}
        for i, (a, b) in enumerate(zip(*results, strict=True)):
            if i not in skip:
                assert torch.equal(a, b), f"output {i}, {n_rows} rows"


def test_kernel_rejects_mismatched_shapes(kernel) -> None:
    ws, bs = _mlp(2)
    ws, bs = [w.detach() for w in ws], [b.detach() for b in bs]
    with pytest.raises(RuntimeError, match="weight 0 must have 26 columns"):
        kernel.sdf_mlp_forward(torch.rand(10, 26), ws[:2], bs[:2], ws[2][0], bs[2][0], 100.0)
    with pytest.raises(RuntimeError, match="bias must have 64 elements"):
        kernel.sdf_mlp_forward(torch.rand(10, 27), ws[:2], [bs[0][:60], bs[1]], ws[2][0], bs[2][0], 100.0)
    out0, g0, *rest = kernel.sdf_mlp_forward(torch.rand(10, 27), ws[:2], bs[:2], ws[2][0], bs[2][0], 100.0)
    acts = [torch.rand(10, 27), *rest[:2]]
    with pytest.raises(RuntimeError, match=r"d_g0 must be \[10, 27\]"):
        kernel.sdf_mlp_backward(ws[:2], ws[2][0], acts, rest[2:4], rest[4:6], rest[6:], None, None,
                                torch.ones(10, 26), True, 100.0)
    with pytest.raises(RuntimeError, match="b must have 8 elements"):
        kernel.bias_softplus_(torch.rand(10, 8), torch.ones(9), 100.0)


def test_distance_without_gradient_matches_the_reference(kernel) -> None:
    ws, bs = _mlp(2)
    h = torch.randn(2000, 27, generator=torch.Generator().manual_seed(3)) * 0.4
    want = sdf_mlp.mlp_with_input_grad_reference(h, ws, bs, fast=False)[0]
    with torch.no_grad():
        got = sdf_mlp.mlp_distance(h, ws, bs)
        plain = sdf_mlp.mlp_distance(h, ws, bs, fast=False)
    torch.testing.assert_close(got, want.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(plain, want.detach(), rtol=1e-5, atol=1e-6)
    with_grad = sdf_mlp.mlp_distance(h, ws, bs)  # with gradient: PyTorch's operators, differentiable
    assert with_grad.requires_grad
    torch.testing.assert_close(with_grad.detach(), want.detach(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("step", [0, 10_000])  # some levels still off; every level on
def test_field_on_the_fast_path_matches_the_pure_pytorch_field(kernel, step: int) -> None:
    """The SDF field with the compiled encoding (its Jacobian), the fused MLP and the first weight cut to the active
    levels against the pure-PyTorch field (padded features, autograd) with the same parameters: SDF, normal and
    the parameters' gradients of a loss on both, and the distance query."""
    from anisdf.config import load_config
    from anisdf.fields.sdf_field import SDFField

    small = ["geometry.log2_hashmap_size=12"]
    torch.manual_seed(0)
    fast = SDFField(load_config("cpu-quick", small).geometry)
    with torch.no_grad():
        for p in fast.parameters():
            p.add_(torch.randn_like(p) * 0.05)  # past the geometric initialisation: every path carries weight
    ref = SDFField(load_config("cpu-quick", [*small, "geometry.encoding_backend=torch"]).geometry)
    ref.load_state_dict(fast.state_dict())
    x = torch.rand(3000, 3, generator=torch.Generator().manual_seed(4)) * 1.6 - 0.8
    results = []
    for field in (fast, ref):
        field.set_step(step)
        q = field.query(x, create_graph=True)
        loss = q.sdf.square().sum() + (q.grad.norm(dim=-1) - 1).square().sum() + q.feature().sin().sum()
        grads = torch.autograd.grad(loss, list(field.parameters()))
        with torch.no_grad():
            results.append([q.sdf, q.grad, field.distance(x), *grads])
    assert fast.branches[1].n_active < fast.branches[1].n_levels or step > 0
    for a, b in zip(*results, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * max(float(b.abs().max()), 1e-6))
