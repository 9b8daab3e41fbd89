"""The fast hash-grid kernels (compiled C++ on CPU, Triton for CUDA) compute the reference encoding, its
gradients and the eikonal double backward; without a kernel everything falls back to the reference.

Without a GPU the Triton kernels run in Triton's interpreter (``TRITON_INTERPRET=1``) on CPU tensors: the same
kernel source and arithmetic as on CUDA, so these tests check its math in CI; on a CUDA machine they run compiled.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from collections.abc import Callable, Iterator

import pytest
import torch

from anisdf.errors import AnisdfError
from anisdf.fields.hash_grid import cpu_kernel, ops
from anisdf.fields.hash_grid import dispatch as hef
from anisdf.fields.hash_grid.dispatch import HashGrid
from anisdf.fields.hash_grid.reference import GridSpec, hash_encode_reference

# Levels 0-1 dense ((R+1)^3 <= 4096), levels 2-5 hashed.
SMALL = GridSpec(n_levels=6, features_per_level=2, log2_hashmap_size=12, base_resolution=8, per_level_scale=1.5)




@pytest.fixture(scope="module")
def triton_ops() -> object:
    """The Triton kernels, compiled for the GPU if there is one, else interpreted on the CPU (see conftest.py)."""
    pytest.importorskip("triton")
    device = "cuda" if torch.cuda.is_available() else "cpu"
    assert device == "cuda" or os.environ.get("TRITON_INTERPRET") == "1"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("ANISDF_NO_KERNEL", raising=False)
        mod = hef.triton_module(device)
    assert mod is not None, f"Triton kernels unusable: {hef.triton_info(device)['error']}"
    return mod


def _triton_encode(kernel_ops: object) -> Callable:
    device = "cuda" if torch.cuda.is_available() else "cpu"

    def encode(x: torch.Tensor, table: torch.Tensor, spec: GridSpec, n_levels: int | None = None) -> torch.Tensor:
        return ops.apply_kernels(x.to(device), table.to(device), spec, kernel_ops, n_levels).cpu()
    # Compiled for a GPU, Triton contracts multiply-adds into FMAs and the table gradient's atomics add in any
    # order, so sums of thousands of terms (point gradients scale with the resolution, 2048 at the finest
    # level) differ from the CPU reference by a few float32 ulps more than the interpreter does. On an H100
    # the largest difference seen was 2.4e-5 of the largest value; wrong indices or weights give errors of order 1.
    encode.slack = 5.0 if device == "cuda" else 1.0  # type: ignore[attr-defined]
    return encode


@pytest.fixture(params=["cpu", "triton"])
def fast(request) -> Callable:
    """An encode function ``(x, table, spec)`` on CPU tensors, by each fast backend."""
    if request.param == "cpu":
        request.getfixturevalue("kernel")
        return hef.fast_hash_encode
    return _triton_encode(request.getfixturevalue("triton_ops"))


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Run the reference on one thread: its many small ops spend most of their time in OpenMP barriers when
    other processes share the two cores (measured 0.08 s single-threaded against 1.5 s)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _points(n: int, spec: GridSpec, gen: torch.Generator, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
    """Random points plus points on cell faces, edges and vertices of several levels, and at 0 and 1."""
    x = lo + (hi - lo) * torch.rand(n, 3, generator=gen)
    special = []
    for r in spec.resolutions[:3]:
        k = torch.randint(0, r + 1, (20, 3), generator=gen).float()
        on_vertex = k / r
        on_face = on_vertex.clone()
        on_face[:, 1:] = torch.rand(20, 2, generator=gen)
        special += [on_vertex, on_face]
    corners = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [1.0, 0.0, 0.25]])
    return torch.cat([x, *special, corners])


def _assert_close(actual: torch.Tensor, expected: torch.Tensor, rel: float = 2e-5, what: str = "") -> None:
    scale = max(1.0, float(expected.abs().max()))
    err = float((actual - expected).abs().max())
    assert err <= rel * scale, f"{what}: max |diff| {err:.3g} > {rel:.1e} * {scale:.3g}"


def _encode_and_grads(encode, x: torch.Tensor, table: torch.Tensor, spec: GridSpec, w: torch.Tensor):
    xx = x.clone().requires_grad_(True)
    tt = table.clone().requires_grad_(True)
    out = encode(xx, tt, spec)
    (out * w).sum().backward()
    return out.detach(), tt.grad, xx.grad


@pytest.mark.parametrize(("spec", "n", "lo", "hi"), [
    (SMALL, 3000, 0.0, 1.0),     # multi-threaded path
    (SMALL, 50, 0.0, 1.0),       # below the threading threshold
    (SMALL, 1000, -0.25, 1.25),  # outside the unit cube: clamped cells, extrapolated weights
    (GridSpec(), 2000, 0.0, 1.0),
    (GridSpec(n_levels=10), 1500, 0.0, 1.0),
    *[(GridSpec(n_levels=4, features_per_level=f, log2_hashmap_size=10, base_resolution=6), 400, 0.0, 1.0)
      for f in (1, 4, 8)],  # the other table widths both kernels handle
])
def test_values_and_gradients_match_reference(fast, spec: GridSpec, n: int, lo: float, hi: float) -> None:
    gen = torch.Generator().manual_seed(n + spec.n_levels)
    x = _points(n, spec, gen, lo, hi)
    table = torch.randn(spec.n_params, spec.features_per_level, generator=gen)
    w = torch.randn(x.shape[0], spec.output_dim, generator=gen)
    assert any(spec.hashed) and not all(spec.hashed)
    with _one_thread():
        ref = _encode_and_grads(hash_encode_reference, x, table, spec, w)
    got = _encode_and_grads(fast, x, table, spec, w)
    for name, a, b in zip(("values", "grad table", "grad x"), got, ref, strict=True):
        assert a.shape == b.shape, name
        _assert_close(a, b, 2e-5 * getattr(fast, "slack", 1.0), name)


def _eikonal_grads(encode, x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> list[torch.Tensor]:
    torch.manual_seed(3)
    mlp = torch.nn.Sequential(torch.nn.Linear(spec.output_dim, 32), torch.nn.Softplus(beta=20),
                              torch.nn.Linear(32, 1))
    xx = x.clone().requires_grad_(True)
    tt = table.clone().requires_grad_(True)
    sdf = mlp(encode(xx, tt, spec))
    (normal,) = torch.autograd.grad(sdf.sum(), xx, create_graph=True)
    loss = ((normal.norm(dim=-1) - 1.0) ** 2).mean() + 0.1 * sdf.abs().mean()
    loss.backward()
    return [normal.detach(), tt.grad, xx.grad, mlp[0].weight.grad]


@pytest.mark.parametrize("spec", [SMALL, GridSpec()])
def test_eikonal_double_backward_matches_reference(fast, spec: GridSpec) -> None:
    gen = torch.Generator().manual_seed(7)
    x = _points(2000, spec, gen)
    table = 0.5 * torch.randn(spec.n_params, spec.features_per_level, generator=gen)
    with _one_thread():
        ref = _eikonal_grads(hash_encode_reference, x, table, spec)
    got = _eikonal_grads(fast, x, table, spec)
    # The table gradient includes the part through d enc / dx; x.grad includes the second derivative of the
    # trilinear weights (which torch-ngp omits), so it matches too.
    for name, a, b in zip(("normal", "grad table", "grad x", "grad mlp"), got, ref, strict=True):
        assert float(b.abs().max()) > 0, name
        _assert_close(a, b, 5e-5 * getattr(fast, "slack", 1.0), name)


def test_first_levels_only_match_reference(fast) -> None:
    """Levels not yet switched on are not looked up (``n_levels``): the first levels' values, the normals and the
    eikonal gradients match the reference's, and the table rows of the other levels get no gradient."""
    spec, n = GridSpec(), 3
    gen = torch.Generator().manual_seed(11)
    x = _points(1500, spec, gen)
    table = 0.5 * torch.randn(spec.n_params, spec.features_per_level, generator=gen)
    ref_fn = functools.partial(_first_levels, hash_encode_reference, n=n)
    with _one_thread():
        ref = _eikonal_grads(ref_fn, x, table, spec)
    got = _eikonal_grads(functools.partial(_first_levels, fast, n=n), x, table, spec)
    for name, a, b in zip(("normal", "grad table", "grad x", "grad mlp"), got, ref, strict=True):
        assert float(b.abs().max()) > 0, name
        _assert_close(a, b, 5e-5 * getattr(fast, "slack", 1.0), name)
    assert torch.all(got[1][spec.offsets[n]:] == 0)
    with _one_thread():
        full = hash_encode_reference(x, table, spec)
    torch.testing.assert_close(fast(x, table, spec, n), full[:, : n * spec.features_per_level], atol=2e-5, rtol=0)


def _first_levels(encode, x: torch.Tensor, table: torch.Tensor, spec: GridSpec, n: int) -> torch.Tensor:
    """The first ``n`` levels' features, zero-padded to the full width (as the SDF branches read them)."""
    out = encode(x, table, spec, n)
    return torch.nn.functional.pad(out, (0, spec.output_dim - out.shape[1]))


def _through_table_gradient(encode, x, table, spec, w, u, with_x: bool) -> list[torch.Tensor]:
    xx = x.clone().requires_grad_(True)
    tt = table.clone().requires_grad_(True)
    ww = w.clone().requires_grad_(True)
    s = (encode(xx, tt, spec) * ww).sum()
    gx, gt = torch.autograd.grad(s, [xx, tt], create_graph=True)
    loss = (gt * u).sum() + ((gx**2).sum() if with_x else 0.0)
    loss.backward()
    return [xx.grad, ww.grad] + ([tt.grad] if with_x else [])


@pytest.mark.parametrize("with_x", [False, True])
def test_differentiating_the_table_gradient_matches_reference(fast, with_x: bool) -> None:
    gen = torch.Generator().manual_seed(5)
    x = _points(1500, SMALL, gen)
    table = torch.randn(SMALL.n_params, 2, generator=gen)
    w = torch.randn(x.shape[0], SMALL.output_dim, generator=gen)
    u = torch.randn(SMALL.n_params, 2, generator=gen)
    with _one_thread():
        ref = _through_table_gradient(hash_encode_reference, x, table, SMALL, w, u, with_x)
    got = _through_table_gradient(fast, x, table, SMALL, w, u, with_x)
    for name, a, b in zip(("grad x", "grad w", "grad table"), got, ref, strict=False):
        assert float(b.abs().max()) > 0, name
        _assert_close(a, b, 5e-5 * getattr(fast, "slack", 1.0), name)


def _encoding_and_jacobian_grads(with_jacobian: bool, x, table, spec, w, u, q, n_levels, parts):
    """A loss on the encoding (weights ``w``) and on ``J^T u`` (weights ``q``; the normal's route), by the kernel's
    Jacobian or by the reference and autograd's double backward: the values and the table gradient."""
    k = n_levels * spec.features_per_level
    if with_jacobian:
        grid = HashGrid(spec, backend="fast")
        with torch.no_grad():
            grid.table.copy_(table)
        tt = grid.table
        out, jac = grid.encode_with_jacobian(x, n_levels)
        gx = torch.bmm(u[:, None, :k], jac).squeeze(1)
    else:
        tt = table.clone().requires_grad_(True)
        xx = x.clone().requires_grad_(True)
        out = hash_encode_reference(xx, tt, spec, n_levels)
        (gx,) = torch.autograd.grad(out, xx, u[:, :k], create_graph=True)
    loss = (out * w[:, :k]).sum() if "enc" in parts else 0.0
    loss = loss + ((gx * q).sum() if "jac" in parts else 0.0)
    loss.backward()
    return [out.detach(), gx.detach(), tt.grad]


@pytest.mark.parametrize(("spec", "n", "n_levels", "parts"), [
    (SMALL, 3000, 6, ("enc", "jac")),  # threads, every level
    (SMALL, 60, 4, ("enc", "jac")),    # one thread, the first levels only
    (SMALL, 800, 6, ("jac",)),         # only the Jacobian's gradient (the encoding's None)
    (SMALL, 800, 6, ("enc",)),
    *[(GridSpec(n_levels=4, features_per_level=f, log2_hashmap_size=10, base_resolution=6), 400, 4, ("enc", "jac"))
      for f in (1, 4, 8)],
])
def test_encoding_with_its_jacobian_matches_autograd(kernel, spec, n, n_levels, parts) -> None:
    """``encode_with_jacobian``: the features, ``J^T u`` and the table gradient of a loss on both equal the
    reference's and autograd's double backward (the training route of the analytic normal)."""
    gen = torch.Generator().manual_seed(n + spec.features_per_level)
    x = _points(n, spec, gen)
    table = 0.5 * torch.randn(spec.n_params, spec.features_per_level, generator=gen)
    w, u = (torch.randn(x.shape[0], spec.output_dim, generator=gen) for _ in range(2))
    q = torch.randn(x.shape[0], 3, generator=gen)
    with _one_thread():
        ref = _encoding_and_jacobian_grads(False, x, table, spec, w, u, q, n_levels, parts)
    got = _encoding_and_jacobian_grads(True, x, table, spec, w, u, q, n_levels, parts)
    for name, a, b in zip(("values", "J^T u", "grad table"), got, ref, strict=True):
        assert float(b.abs().max()) > 0, name
        _assert_close(a, b, 5e-5, name)
    assert torch.all(got[2][spec.offsets[n_levels]:] == 0)


def test_encoding_with_its_jacobian_of_no_points_is_empty_not_an_error(kernel) -> None:
    """A step can have no sample to query (a short-budget run losing its surface between two grid updates): the
    encoding, ``J^T u`` and their backward on 0 points are empty and a zero table gradient (the Jacobian's incoming
    gradient was reshaped to [0, -1], which PyTorch refuses)."""
    grid = HashGrid(SMALL, backend="fast")
    out, jac = grid.encode_with_jacobian(torch.zeros(0, 3), 6)
    assert out.shape == (0, SMALL.output_dim) and jac.shape == (0, SMALL.output_dim, 3)
    gx = ops.jacobian_transpose_product(jac, torch.ones(0, SMALL.output_dim))
    (out.sum() + gx.sum()).backward()
    assert grid.table.grad is not None and not grid.table.grad.any()


def test_jacobian_transpose_product_gradients_match_finite_differences() -> None:
    gen = torch.Generator().manual_seed(2)
    jac = torch.randn(7, 5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    g = torch.randn(7, 5, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(ops.jacobian_transpose_product, (jac, g))
    torch.testing.assert_close(ops.jacobian_transpose_product(jac, g), torch.einsum("nkd,nk->nd", jac, g))


def test_jacobian_transpose_product_kernel_matches_reference(kernel) -> None:
    """The compiled ``J^T g`` (float32 CPU) against the batched-product reference: the value and both gradients,
    with ``g`` a column slice of a wider matrix (the MLP input gradient's grid columns, as the SDF branch passes it),
    and on 0 rows."""
    gen = torch.Generator().manual_seed(3)
    jac = torch.randn(3000, 24, 3, generator=gen, requires_grad=True)
    wide = torch.randn(3000, 27, generator=gen, requires_grad=True)
    d = torch.randn(3000, 3, generator=gen)

    def run(fast: bool) -> list[torch.Tensor]:
        out = hef.jacobian_transpose_product(jac, wide[:, 3:], fast=fast)
        return [out, *torch.autograd.grad((out * d).sum(), [jac, wide])]

    for got, want in zip(run(True), run(False), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    empty = hef.jacobian_transpose_product(torch.zeros(0, 24, 3), torch.zeros(0, 24))
    assert empty.shape == (0, 3)


def test_jacobian_route_applies_only_where_it_is_exact(kernel) -> None:
    """The reference backend, and points that need their own gradient, take the autograd route (None)."""
    x = torch.rand(100, 3)
    assert HashGrid(SMALL, backend="torch").encode_with_jacobian(x) is None
    assert HashGrid(SMALL).encode_with_jacobian(x.requires_grad_(True)) is None
    assert HashGrid(SMALL).encode_with_jacobian(x.detach()) is not None


@pytest.mark.parametrize("backend", ["cpu", "triton"])
def test_table_gradient_is_skipped_when_only_normals_are_asked(request, backend: str) -> None:
    real = request.getfixturevalue("kernel" if backend == "cpu" else "triton_ops")
    device = "cuda" if backend == "triton" and torch.cuda.is_available() else "cpu"
    calls: list[tuple[bool, bool]] = []

    class Spy:
        def __getattr__(self, name: str):
            fn = getattr(real, name)
            if name != "encode_backward":
                return fn

            def wrapped(*args, **kwargs):
                calls.append((args[5], args[6]))
                return fn(*args, **kwargs)
            return wrapped

    x = torch.rand(500, 3, device=device, requires_grad=True)
    table = torch.nn.Parameter(torch.randn(SMALL.n_params, 2, device=device))
    enc = ops.apply_kernels(x, table, SMALL, Spy())
    (n,) = torch.autograd.grad(enc.pow(2).sum(), x, create_graph=True)
    assert calls == [(False, True)]  # (need_table, need_x)
    n.pow(2).sum().backward()
    assert table.grad is not None and float(table.grad.abs().sum()) > 0
    assert calls[-1] == (True, True)


def test_atomic_and_single_thread_paths_agree(kernel) -> None:
    gen = torch.Generator().manual_seed(11)
    x = _points(4000, SMALL, gen)
    table = torch.randn(SMALL.n_params, 2, generator=gen)
    g = torch.randn(x.shape[0], SMALL.output_dim, generator=gen)
    levels = ops.level_table(SMALL)
    by_levels = kernel.encode_backward(g, x, table, levels, SMALL.log2_hashmap_size, True, True, 0)
    atomic = kernel.encode_backward(g, x, table, levels, SMALL.log2_hashmap_size, True, True, 2)
    with _one_thread():
        single = kernel.encode_backward(g, x, table, levels, SMALL.log2_hashmap_size, True, True, 0)
    for other in (atomic, single):
        for a, b in zip(other, by_levels, strict=True):
            _assert_close(a, b)


def test_unsupported_inputs_use_the_reference(kernel) -> None:
    spec3 = GridSpec(n_levels=3, features_per_level=3, log2_hashmap_size=10, base_resolution=4)
    x = torch.rand(64, 3)
    t3 = torch.randn(spec3.n_params, 3)
    assert not hef.kernel_supports(x, t3, spec3)
    assert torch.equal(hef.fast_hash_encode(x, t3, spec3), hash_encode_reference(x, t3, spec3))
    x64 = x.double().requires_grad_(True)
    t = torch.randn(SMALL.n_params, 2)
    out = hef.fast_hash_encode(x64, t, SMALL)
    assert torch.equal(out, hash_encode_reference(x64, t, SMALL))
    out.sum().backward()
    assert x64.grad is not None and x64.grad.dtype == torch.float64
    with pytest.raises(ValueError, match="table has shape"):
        hef.fast_hash_encode(x, t[:-1], SMALL)


def test_hash_grid_module_uses_the_kernel(kernel, monkeypatch) -> None:
    torch.manual_seed(0)
    grid = HashGrid(SMALL, backend="fast", init_scale=0.1)
    used: list[object] = []
    real_apply = ops.apply_kernels

    def spy(x, table, spec, kernel_ops, n_levels=None):
        used.append(kernel_ops)
        return real_apply(x, table, spec, kernel_ops, n_levels)

    monkeypatch.setattr(hef, "apply_kernels", spy)
    x = torch.rand(300, 3) * 1.2 - 0.1
    expected = hash_encode_reference(x.clamp(0.0, 1.0), grid.table, SMALL)
    _assert_close(grid(x).detach(), expected.detach())
    assert used == [kernel]
    with pytest.raises(ValueError, match="backend must be"):
        HashGrid(SMALL, backend="tcnn")


def test_no_kernel_env_falls_back(monkeypatch) -> None:
    monkeypatch.setenv("ANISDF_NO_KERNEL", "1")
    assert hef.load_fast_encoder() is None
    with pytest.raises(AnisdfError, match="ANISDF_NO_KERNEL"):
        hef.load_fast_encoder(required=True)
    assert hef.fast_backend("cpu") is None and hef.triton_module("cpu") is None
    grid = HashGrid(SMALL, backend="auto", init_scale=0.1)
    x = torch.rand(100, 3)
    assert torch.equal(grid(x), hash_encode_reference(x, grid.table, SMALL))
    with pytest.raises(AnisdfError, match="ANISDF_NO_KERNEL"):
        HashGrid(SMALL, backend="fast")(x)


def test_build_failure_warns_once_and_falls_back(monkeypatch, caplog) -> None:
    monkeypatch.delenv("ANISDF_NO_KERNEL", raising=False)
    monkeypatch.setattr(cpu_kernel, "_state", {"module": None, "error": None, "build_s": None, "name": None,
                                        "flags": None})

    def broken_build():
        raise RuntimeError("Error building extension 'anisdf_hashgrid_cpu_avx2'\nlong compiler output")

    monkeypatch.setattr(cpu_kernel, "_build", broken_build)
    with caplog.at_level(logging.WARNING, logger=cpu_kernel.__name__):
        assert hef.load_fast_encoder() is None
        assert hef.load_fast_encoder() is None
        with pytest.raises(AnisdfError, match="could not be built"):
            hef.load_fast_encoder(required=True)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "falling back to the PyTorch reference" in warnings[0].getMessage()
    assert "\n" not in warnings[0].getMessage()
    # The returned encoder path still works: fast_hash_encode sees no kernel and uses the reference.
    x = torch.rand(40, 3)
    t = torch.randn(SMALL.n_params, 2)
    assert torch.equal(hef.fast_hash_encode(x, t, SMALL), hash_encode_reference(x, t, SMALL))


def test_triton_failure_warns_once_and_falls_back(monkeypatch, caplog) -> None:
    """A GPU whose Triton kernels cannot compile (or give a wrong answer) trains on the reference, saying so once."""
    monkeypatch.delenv("ANISDF_NO_KERNEL", raising=False)
    monkeypatch.setattr(hef, "_triton_state", {})

    def broken_check(mod, device):
        raise RuntimeError("self-check failed: values differ from the reference by 0.5 (relative)\nmore")

    monkeypatch.setattr(hef, "self_check", broken_check)
    with caplog.at_level(logging.WARNING, logger=hef.__name__):
        assert hef.triton_module("cpu") is None
        assert hef.triton_module("cpu") is None
        with pytest.raises(AnisdfError, match="no fast hash-grid kernel for cuda:3"):
            hef.load_fast_encoder(required=True, device="cuda:3")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2  # one per device, never again for the same one
    assert all("falling back to the PyTorch reference" in m and "\n" not in m for m in warnings)
    assert "self-check failed" in warnings[0]


def test_triton_self_check_catches_a_wrong_kernel(triton_ops) -> None:
    """The check that guards every new GPU rejects kernels that are off, here by a wrong table gradient."""

    class Wrong:
        def __getattr__(self, name: str):
            return getattr(triton_ops, name)

        def encode_backward(self, *args, **kwargs):
            gt, gx = triton_ops.encode_backward(*args, **kwargs)
            return [None if gt is None else gt * 1.01, gx]

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    # The first use may come from a render (no_grad) or a mixed-precision training step (autocast).
    with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16):
        hef.self_check(triton_ops, device)
    with torch.inference_mode():
        hef.self_check(triton_ops, device)
    with pytest.raises(RuntimeError, match="table gradient differ"):
        hef.self_check(Wrong(), device)


def test_encoding_benchmark_reports_both_backends(kernel) -> None:
    from anisdf.benchmarks.encoding import bench_encoding, format_table

    res = bench_encoding(n_points=2048, repeats=1, settings={"small": SMALL}, threads=1)
    row = res["settings"][0]
    assert res["kernel_available"] and res["device"] == "cpu"
    assert row["max_abs_diff_fwd"] < 1e-5
    assert set(row["speedup"]) == {"fwd", "fwd+bwd", "eikonal"} and all(v > 0 for v in row["speedup"].values())
    table = format_table(res)
    assert "speedup" in table and "random-read floor" in table


def test_kernel_entry_points_share_one_input_check(kernel) -> None:
    """Every entry point rejects bad inputs through the one prepare() helper, with a message naming the input."""
    x = torch.rand(10, 3)
    table = torch.randn(SMALL.n_params, 2)
    levels = ops.level_table(SMALL)
    log2 = SMALL.log2_hashmap_size
    g = torch.randn(10, SMALL.output_dim)
    calls = {
        "forward": lambda xx, tt, gg: kernel.encode_forward(xx, tt, levels, log2),
        "backward": lambda xx, tt, gg: kernel.encode_backward(gg, xx, tt, levels, log2, True, True),
        "double backward": lambda xx, tt, gg: kernel.encode_double_backward(gg, xx, tt, torch.ones(10, 3), None,
                                                                            levels, log2, True, True, True),
    }
    for name, call in calls.items():
        assert call(x, table, g)[0] is not None, name
        with pytest.raises(RuntimeError, match="hashgrid_cpu: float32 points and table only"):
            call(x.double(), table, g)
        with pytest.raises(RuntimeError, match=r"hashgrid_cpu: x must be \[N, 3\]"):
            call(x[:, :2], table, g)
        with pytest.raises(RuntimeError, match="hashgrid_cpu: table has too few rows"):
            call(x, table[:-1], g)
        if name != "forward":
            with pytest.raises(RuntimeError, match=r"hashgrid_cpu: incoming gradient g must be \[10, 12\]"):
                call(x, table, g[:, :-1])
