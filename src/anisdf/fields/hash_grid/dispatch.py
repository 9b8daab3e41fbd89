"""Pick a hash-grid backend: the fast kernel of the tensors' device where it works, else the reference.

* CPU: :mod:`.cpu_kernel` (compiled C++/OpenMP).
* CUDA: :mod:`.triton`, compiled by Triton on first use and checked once per device against the reference on a
  few points before it is trusted.

``ANISDF_NO_KERNEL=1`` disables both. A backend that cannot be built logs one warning and the reference is used
(or :class:`AnisdfError` is raised where the fast path is ``required``). Inputs neither kernel handles (dtypes
other than float32, features per level other than 1/2/4/8, other devices) are passed to the reference, so
:func:`fast_hash_encode` is always safe to call. :class:`HashGrid` is the learnable module built on this.
"""

from __future__ import annotations

import functools
import logging
import time
from types import ModuleType
from typing import Any

import torch
from torch import Tensor, nn

from anisdf.errors import AnisdfError
from anisdf.fields.hash_grid import cpu_kernel, ops
from anisdf.fields.hash_grid.ops import (
    apply_kernels,
    encode_with_jacobian,
    kernel_inputs,
    kernels_disabled,
    short_error,
)
from anisdf.fields.hash_grid.reference import EncodeFn, GridSpec, hash_encode_reference

log = logging.getLogger(__name__)

# Triton kernels per device (str(device)): {"module", "error", "build_s"}, filled by the first call.
_triton_state: dict[str, dict[str, Any]] = {}


def triton_module(device: torch.device | str) -> ModuleType | None:
    """The Triton kernels for ``device``, checked once against the reference; ``None`` (one warning) if unusable.

    On a CPU device this only works under ``TRITON_INTERPRET=1`` (how the tests run the kernels without a GPU).
    """
    if kernels_disabled():
        return None
    key = _device_key(device)
    if key not in _triton_state:
        state: dict[str, Any] = {"module": None, "error": None, "build_s": None}
        try:
            from anisdf.fields.hash_grid import triton as mod

            log.info("hash grid: compiling the Triton kernels for %s and checking them against the reference", key)
            t0 = time.perf_counter()
            self_check(mod, torch.device(device))
            state.update(module=mod, build_s=time.perf_counter() - t0)
            log.info("hash grid: Triton kernels on %s compiled and checked in %.1f s", key, state["build_s"])
        except Exception as err:  # no triton, no compiler for this GPU, a wrong result: use the reference
            state["error"] = short_error(err)
            log.warning("hash grid: Triton kernels unavailable on %s (%s); falling back to the PyTorch "
                        "reference encoding", key, state["error"])
        _triton_state[key] = state
    return _triton_state[key]["module"]


def _device_key(device: torch.device | str) -> str:
    """``cuda`` and ``cuda:<current>`` are one device."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return str(device)


def triton_info(device: torch.device | str) -> dict[str, Any]:
    """Like :func:`.cpu_kernel.kernel_info`, for the Triton kernels on ``device`` (after :func:`triton_module`)."""
    state = _triton_state.get(_device_key(device), {"module": None, "error": "not loaded", "build_s": None})
    try:
        import triton

        name = f"triton {triton.__version__}"
    except ImportError:
        name = None
    mod = state["module"]
    return {"name": name, "flags": None if mod is None else [f"BLOCK={mod.BLOCK}"], "build_s": state["build_s"],
            "error": state["error"]}


def self_check(mod: Any, device: torch.device) -> None:
    """Raise unless ``mod`` gives the reference's values, gradients and eikonal double backward on ``device``.

    A small grid with dense and hashed levels, 300 points: it compiles every kernel variant that training uses.
    The first call may come from inside ``no_grad``, ``inference_mode`` or bf16 autocast (a training step, a
    render); the check sets its own float32, gradient-enabled context.
    """
    with torch.inference_mode(False), torch.enable_grad(), torch.autocast(device.type, enabled=False):
        _compare_with_reference(mod, device)


def _compare_with_reference(mod: Any, device: torch.device) -> None:
    spec = GridSpec(n_levels=4, features_per_level=2, log2_hashmap_size=10, base_resolution=6, per_level_scale=1.6)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(300, 3, generator=gen).to(device)
    table = torch.randn(spec.n_params, 2, generator=gen).to(device)
    w = torch.randn(300, spec.output_dim, generator=gen).to(device)
    results = []
    for encode in (hash_encode_reference, functools.partial(apply_kernels, ops=mod)):
        xx, tt = x.clone().requires_grad_(True), table.clone().requires_grad_(True)
        out = encode(xx, tt, spec)
        gx, gt = torch.autograd.grad((out * w).sum(), [xx, tt], create_graph=True)
        second = torch.autograd.grad(gx.pow(2).sum(), [xx, tt])
        results.append([t.detach() for t in (out, gx, gt, *second)])
    names = ("values", "point gradient", "table gradient", "eikonal point gradient", "eikonal table gradient")
    for name, a, b in zip(names, *results, strict=True):
        err = float((a - b).abs().max()) / max(1.0, float(b.abs().max()))
        if not err <= 1e-4:
            raise RuntimeError(f"self-check failed: {name} differ from the reference by {err:.2g} (relative)")


def fast_backend(device: torch.device | str) -> ModuleType | None:
    """The fast kernels for tensors on ``device``: compiled C++ on CPU, Triton on CUDA; ``None`` if unavailable."""
    device = torch.device(device)
    if device.type == "cpu":
        return cpu_kernel.kernel_module()
    if device.type == "cuda":
        return triton_module(device)
    return None


def kernel_supports(x: Tensor, table: Tensor, spec: GridSpec) -> bool:
    """Whether a fast kernel handles these inputs (else :func:`fast_hash_encode` uses the reference)."""
    return kernel_inputs(x, table, spec) and fast_backend(x.device) is not None


def fast_hash_encode(x: Tensor, table: Tensor, spec: GridSpec, n_levels: int | None = None,
                     required: bool = False) -> Tensor:
    """Encode ``x`` in ``[0, 1]^3`` ``[N, 3]`` to ``[N, L * F]`` (``n_levels``: the first levels only); same contract
    as :func:`hash_encode_reference`.

    ``required=True`` (``geometry.encoding_backend=fast``) raises :class:`AnisdfError` where no fast kernel
    exists for the device, instead of using the reference.
    """
    if x.dim() != 2 or x.shape[-1] != 3:
        raise ValueError(f"hash encoding expects points [N, 3], got {tuple(x.shape)}")
    if tuple(table.shape) != (spec.n_params, spec.features_per_level):
        raise ValueError(f"hash table has shape {tuple(table.shape)}, the spec needs "
                         f"({spec.n_params}, {spec.features_per_level})")
    ops = fast_backend(x.device) if kernel_inputs(x, table, spec) else None
    if ops is None:
        if required:
            _require(x.device)
        return hash_encode_reference(x, table, spec, n_levels)
    return apply_kernels(x, table, spec, ops, n_levels)


def jacobian_transpose_product(jac: Tensor, g: Tensor, fast: bool = True) -> Tensor:
    """``J^T g`` of :meth:`HashGrid.encode_with_jacobian`'s Jacobian (:func:`.ops.jacobian_transpose_product`): by
    the compiled CPU kernel when ``fast`` and it applies (float32 CPU tensors), else by the PyTorch reference."""
    mod = cpu_kernel.kernel_for(jac) if fast and g.dtype == torch.float32 else None
    return ops.jacobian_transpose_product(jac, g, mod)


def _require(device: torch.device) -> None:
    if kernels_disabled():
        raise AnisdfError("geometry.encoding_backend=fast, but ANISDF_NO_KERNEL is set")
    if fast_backend(device) is None:
        reason = cpu_kernel.kernel_info()["error"] if device.type == "cpu" else triton_info(device)["error"]
        what = "the compiled hash-grid kernel could not be built" if device.type == "cpu" else \
            f"no fast hash-grid kernel for {device}"
        raise AnisdfError(f"geometry.encoding_backend=fast: {what} ({reason})")


def load_fast_encoder(required: bool = False, device: torch.device | str = "cpu") -> EncodeFn | None:
    """The fast encoder ``fn(x, table, spec)`` if ``device`` has a fast kernel, else ``None`` (one warning logged).

    ``required=True`` raises :class:`AnisdfError` instead of returning ``None``.
    """
    device = torch.device(device)
    if fast_backend(device) is None:
        if required:
            _require(device)
        return None
    return fast_hash_encode


class HashGrid(nn.Module):
    """A learnable hash grid.

    ``backend``: ``torch`` (the reference), ``fast`` (the device's fast kernel, an error where there is none) or
    ``auto`` (the fast kernel where there is one: compiled C++ on CPU, Triton on CUDA; else the reference).
    """

    def __init__(self, spec: GridSpec, backend: str = "auto", init_scale: float = 1e-4) -> None:
        super().__init__()
        if backend not in ("auto", "fast", "torch"):
            raise ValueError(f"hash grid backend must be auto, fast or torch, not {backend!r}")
        self.spec = spec
        self.table = nn.Parameter(torch.empty(spec.n_params, spec.features_per_level).uniform_(-init_scale, init_scale))
        self.backend = backend
        self._encode: EncodeFn = hash_encode_reference
        if backend != "torch":
            self._encode = functools.partial(fast_hash_encode, required=backend == "fast")

    @property
    def output_dim(self) -> int:
        return self.spec.output_dim

    def forward(self, x: Tensor, n_levels: int | None = None) -> Tensor:
        """Features ``[N, L * F]`` of ``x`` in ``[0, 1]^3``; ``n_levels``: of the first levels only."""
        return self._encode(x.clamp(0.0, 1.0), self.table, self.spec, n_levels)

    def encode_with_jacobian(self, x: Tensor, n_levels: int | None = None) -> tuple[Tensor, Tensor] | None:
        """Features ``[N, n * F]`` of the first ``n = n_levels`` levels and their Jacobian ``[N, n * F, 3]`` w.r.t.
        the clamped point, in one pass of the compiled CPU kernel; ``None`` where it does not apply (the
        ``torch`` backend, another device, a point that needs its own gradient): then use :meth:`forward` and
        autograd. The Jacobian is differentiable w.r.t. the table, so a loss on ``jac^T g`` trains it."""
        if self.backend == "torch" or x.requires_grad or x.device.type != "cpu":
            return None
        if not kernel_inputs(x, self.table, self.spec):
            return None
        ops = cpu_kernel.kernel_module()  # built from this source (its name hashes it): it has the Jacobian pass
        if ops is None:
            return None
        return encode_with_jacobian(x.clamp(0.0, 1.0), self.table, self.spec, ops, n_levels)
