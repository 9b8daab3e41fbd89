"""What the fast backends share: the autograd Functions that drive their three entry points, and the env switch.

Both backends (:mod:`.cpu_kernel`, the compiled C++ extension, and :mod:`.triton`) expose ``encode_forward``,
``encode_backward`` and ``encode_double_backward`` with one signature; :func:`apply_kernels` turns such a module
into the encoding ``(x, table, spec) -> [N, L * F]`` of :func:`.reference.hash_encode_reference`.

Autograd: the forward is a :class:`torch.autograd.Function` whose backward (gradients to the table and to
``x``) is itself a Function with an exact backward, so the eikonal loss on analytic normals
(``n = d sdf / d x`` with ``create_graph=True``) trains the table correctly. Unlike torch-ngp, the second
derivative of the trilinear weights with respect to ``x`` is included, so ``x.grad`` also matches the
reference. Third derivatives are not supported (the double backward is ``once_differentiable``).

:func:`encode_with_jacobian` (the CPU kernel only) returns the encoding with its Jacobian w.r.t. ``x``, so the
analytic normal is a contraction ``J^T g`` and training's backward scatters into the table once (both outputs'
gradients in one pass) instead of running the backward and the double backward.
"""

from __future__ import annotations

import functools
import os
from types import ModuleType
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from anisdf.fields.hash_grid.reference import GridSpec


def kernels_disabled() -> bool:
    """``ANISDF_NO_KERNEL=1`` turns every fast backend off (the reference is used)."""
    return os.environ.get("ANISDF_NO_KERNEL", "") not in ("", "0")


def short_error(err: BaseException) -> str:
    """First non-empty line of an exception (compiler logs are long), at most 300 characters."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    msg = lines[0] if lines else type(err).__name__
    return msg[:300]


@functools.lru_cache(maxsize=64)
def level_table(spec: GridSpec, device: torch.device | None = None) -> Tensor:
    """Per-level ``(resolution, hashed, offset)`` rows, the kernels' view of a :class:`GridSpec`."""
    rows = [(r, int(h), o) for r, h, o in zip(spec.resolutions, spec.hashed, spec.offsets[:-1], strict=True)]
    return torch.tensor(rows, dtype=torch.int64, device=device)


def _engine_will_run(t: Tensor) -> bool:
    """Whether the running backward pass wants a gradient for ``t``.

    ``autograd.grad(sdf, x, create_graph=True)`` (analytic normals) does not, and skipping the table
    scatter there saved 16% of an eikonal step (2^17 points, 16 levels). Uses a private torch hook;
    unsure means yes.
    """
    try:
        node = torch.autograd.graph.get_gradient_edge(t).node
        return bool(torch._C._will_engine_execute_node(node))
    except (AttributeError, RuntimeError, TypeError):
        return True


class _EncodeBackward(torch.autograd.Function):
    """``(g, x, table) -> (grad_table, grad_x)`` of the encoding, with an exact backward of its own."""

    @staticmethod
    def forward(ctx: Any, g: Tensor, x: Tensor, table: Tensor, levels: Tensor, log2: int,  # type: ignore[override]
                need_table: bool, need_x: bool, ops: ModuleType) -> tuple[Tensor | None, Tensor | None]:
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(g, x, table)
        ctx.levels, ctx.log2, ctx.ops = levels, log2, ops
        gt, gx = ops.encode_backward(g, x, table, levels, log2, need_table, need_x)
        return gt, gx

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, ggt: Tensor | None, ggx: Tensor | None) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        g, x, table = ctx.saved_tensors
        need_g, need_x, need_table = ctx.needs_input_grad[:3]
        need_table = need_table and ggx is not None
        if not (need_g or need_x or need_table) or (ggt is None and ggx is None):
            return (None,) * 8
        og, ot, ox = ctx.ops.encode_double_backward(g, x, table, ggx, ggt, ctx.levels, ctx.log2,
                                                    need_g, need_table, need_x)
        return og, ox, ot, None, None, None, None, None


class _Encode(torch.autograd.Function):
    """``(x [N, 3], table [T, F]) -> [N, L * F]``, :func:`hash_encode_reference` by the kernels ``ops``."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, table: Tensor, levels: Tensor, log2: int,  # type: ignore[override]
                ops: ModuleType) -> Tensor:
        ctx.save_for_backward(x, table)
        ctx.levels, ctx.log2, ctx.ops = levels, log2, ops
        return ops.encode_forward(x, table, levels, log2)

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, table = ctx.saved_tensors
        need_x, need_table = ctx.needs_input_grad[:2]
        if need_table and not _engine_will_run(table):
            need_table = False
        if not (need_x or need_table):
            return None, None, None, None, None
        gt, gx = _EncodeBackward.apply(g, x, table, ctx.levels, ctx.log2, need_table, need_x, ctx.ops)
        return gx, gt, None, None, None


def apply_kernels(x: Tensor, table: Tensor, spec: GridSpec, ops: Any, n_levels: int | None = None) -> Tensor:
    """Encode ``x`` [N, 3] with the backend module ``ops`` (differentiable twice, see the module docstring); the
    first ``n_levels`` levels only when given (the kernels take the level rows they are handed)."""
    return _Encode.apply(x.contiguous(), table, _levels(spec, x.device, n_levels), spec.log2_hashmap_size, ops)


def _levels(spec: GridSpec, device: torch.device, n_levels: int | None) -> Tensor:
    """The kernels' level rows (:func:`level_table`), the first ``n_levels`` only when given."""
    levels = level_table(spec, device)
    return levels[:n_levels] if n_levels is not None and n_levels < spec.n_levels else levels


class _EncodeJacobian(torch.autograd.Function):
    """``(x, table) -> (out [N, L * F], jac [N, L * F, 3])``: the encoding and its Jacobian ``d out / d x`` in one
    sweep, differentiable (once) w.r.t. the table only, both outputs' gradients scattered in one pass."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, table: Tensor, levels: Tensor, log2: int,  # type: ignore[override]
                ops: ModuleType) -> tuple[Tensor, Tensor]:
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(x, table)
        ctx.levels, ctx.log2, ctx.ops = levels, log2, ops
        return tuple(ops.encode_forward_jacobian(x, table, levels, log2))

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, g: Tensor | None, gj: Tensor | None) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, table = ctx.saved_tensors
        if not ctx.needs_input_grad[1] or (g is None and gj is None):
            return (None,) * 5
        gt = ctx.ops.encode_jacobian_backward(g, gj, x, table, ctx.levels, ctx.log2)
        return None, gt, None, None, None


def encode_with_jacobian(x: Tensor, table: Tensor, spec: GridSpec, ops: Any, n_levels: int | None = None
                         ) -> tuple[Tensor, Tensor]:
    """The encoding of ``x`` [N, 3] and its Jacobian w.r.t. ``x`` [N, L * F, 3] by the backend ``ops`` (which must
    have ``encode_forward_jacobian``: the CPU kernel); gradients reach the table, not ``x``."""
    return _EncodeJacobian.apply(x.detach().contiguous(), table, _levels(spec, x.device, n_levels),
                                 spec.log2_hashmap_size, ops)


class _JacobianTransposeProduct(torch.autograd.Function):
    """``(jac [N, K, 3], g [N, K]) -> jac^T g [N, 3]``; the backward forms ``d jac = g d^T`` with one broadcast
    product (autograd's batched outer products took 2.7x as long for K = 24)."""

    @staticmethod
    def forward(ctx: Any, jac: Tensor, g: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(jac, g)
        return torch.bmm(g.unsqueeze(1), jac).squeeze(1)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, d: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        jac, g = ctx.saved_tensors
        d_jac = g.unsqueeze(2) * d.unsqueeze(1) if ctx.needs_input_grad[0] else None
        d_g = torch.bmm(jac, d.unsqueeze(2)).squeeze(2) if ctx.needs_input_grad[1] else None
        return d_jac, d_g


class _JacobianTransposeProductKernel(torch.autograd.Function):
    """:class:`_JacobianTransposeProduct` by the compiled CPU kernel (``kernels/jacobian_product_cpu.cpp``)."""

    @staticmethod
    def forward(ctx: Any, jac: Tensor, g: Tensor, mod: Any) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(jac, g)
        ctx.mod = mod
        return mod.jacobian_product_forward(jac, g)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, d: Tensor) -> tuple[Tensor | None, Tensor | None, None]:  # type: ignore[override]
        jac, g = ctx.saved_tensors
        d_jac, d_g = ctx.mod.jacobian_product_backward(d, jac, g, ctx.needs_input_grad[0], ctx.needs_input_grad[1])
        return d_jac, d_g, None


def jacobian_transpose_product(jac: Tensor, g: Tensor, mod: ModuleType | None = None) -> Tensor:
    """``sum_k g[n, k] jac[n, k, :]``: the gradient w.r.t. the point of ``<enc, g>`` (:func:`encode_with_jacobian`).
    By the compiled CPU kernel ``mod`` when given (float32 CPU tensors; :func:`.dispatch.jacobian_transpose_product`
    picks it), else by batched matrix products (:class:`_JacobianTransposeProduct`, the reference)."""
    if mod is None:
        return _JacobianTransposeProduct.apply(jac, g)
    return _JacobianTransposeProductKernel.apply(jac, g, mod)


def kernel_inputs(x: Tensor, table: Tensor, spec: GridSpec) -> bool:
    """Whether the kernels handle these inputs at all (dtype, device, features per level, table size)."""
    return (x.device == table.device and x.dtype == torch.float32 and table.dtype == torch.float32
            and spec.features_per_level in (1, 2, 4, 8) and 1 <= spec.log2_hashmap_size <= 31)
