"""Fast hash-grid encodings: the same function as :func:`hash_encode_reference`, much faster.

* CPU: a C++/OpenMP kernel (``anisdf/kernels/hashgrid_cpu.cpp``), built with ``torch.utils.cpp_extension.load``
  on first use, once per process, into torch's extension cache (``~/.cache/torch_extensions/...``) or under
  ``$ANISDF_KERNEL_DIR``. Measured on 2 shared cores (``benchmarks/bench_encoding.py``, 2^16-2^18 points,
  10-16 levels, log2 T 17-19): forward 14-30x, forward + backward 8-18x, an eikonal step 6-13x the reference.
* CUDA: Triton kernels (:mod:`anisdf.fields.hash_encoding_triton`), compiled by Triton on first use and checked
  once per device against the reference on a few points before they are trusted.

``ANISDF_NO_KERNEL=1`` disables both. A backend that cannot be built logs one warning and the reference is used
(or :class:`AnisdfError` is raised where the fast path is ``required``).

Autograd: the forward is a :class:`torch.autograd.Function` whose backward (gradients to the table and to
``x``) is itself a Function with an exact backward, so the eikonal loss on analytic normals
(``n = d sdf / d x`` with ``create_graph=True``) trains the table correctly. Unlike torch-ngp, the second
derivative of the trilinear weights with respect to ``x`` is included, so ``x.grad`` also matches the
reference. Third derivatives are not supported (the double backward is ``once_differentiable``). Both backends
expose the same three functions (``encode_forward``, ``encode_backward``, ``encode_double_backward``); inputs
neither handles (dtypes other than float32, features per level other than 1/2/4/8, other devices) are passed to
the reference, so :func:`fast_hash_encode` is always safe to call.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from anisdf.errors import AnisdfError
from anisdf.fields.hash_encoding import EncodeFn, GridSpec, hash_encode_reference

log = logging.getLogger(__name__)

SOURCE = Path(__file__).resolve().parent.parent / "kernels" / "hashgrid_cpu.cpp"
_EXT_NAME = "anisdf_hashgrid_cpu"

# One build attempt per process: the module, or the reason it is unavailable.
_state: dict[str, Any] = {"module": None, "error": None, "build_s": None, "name": None, "flags": None}


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def _compile_flags() -> tuple[list[str], str]:
    """Compiler flags and a tag for the build name.

    No ``-march=native``: the cache may be shared by machines of another CPU model. AVX2/FMA are used only
    where this CPU has them, and the tag keeps such builds apart from the generic x86-64 one.
    ``-ffp-contract=off`` keeps the rounding identical with and without FMA; ``-fno-trapping-math`` lets
    GCC vectorise ``floor`` (nothing here reads floating-point exception flags).
    """
    flags = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-trapping-math"]
    if {"avx2", "fma"} <= _cpu_flags():
        return [*flags, "-mavx2", "-mfma"], "avx2"
    return flags, "generic"


def _build() -> ModuleType:
    from torch.utils import cpp_extension

    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise RuntimeError(f"no C++ compiler ({cxx}) on PATH")
    if not SOURCE.is_file():
        raise RuntimeError(f"kernel source {SOURCE} is missing")
    flags, tag = _compile_flags()
    name = f"{_EXT_NAME}_{tag}"
    build_dir = None
    root = os.environ.get("ANISDF_KERNEL_DIR")
    if root:
        build_dir = Path(root).expanduser() / name
        build_dir.mkdir(parents=True, exist_ok=True)
    log.info("hash grid: loading the compiled CPU kernel (the first build takes about a minute)")
    t0 = time.perf_counter()
    module = cpp_extension.load(
        name=name,
        sources=[str(SOURCE)],
        extra_cflags=flags,
        extra_ldflags=["-fopenmp"],
        build_directory=None if build_dir is None else str(build_dir),
        verbose=False,
    )
    _state.update(build_s=time.perf_counter() - t0, name=name, flags=flags)
    return module


def _short(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    msg = lines[0] if lines else type(err).__name__
    return msg[:300]


def _disabled() -> bool:
    return os.environ.get("ANISDF_NO_KERNEL", "") not in ("", "0")


def kernel_module() -> ModuleType | None:
    """The compiled CPU extension (built on the first call in this process), or ``None`` if unavailable."""
    if _disabled():
        return None
    if _state["module"] is None and _state["error"] is None:
        try:
            _state["module"] = _build()
        except Exception as err:  # any build failure (compiler, ninja, headers, linker): use the reference
            _state["error"] = _short(err)
            log.warning("hash grid: compiled CPU kernel unavailable (%s); falling back to the PyTorch "
                        "reference encoding", _state["error"])
    return _state["module"]


def kernel_info() -> dict[str, Any]:
    """Build facts for reports: extension name, flags, build/load seconds and the failure reason, if any."""
    return {k: _state[k] for k in ("name", "flags", "build_s", "error")}


# Triton kernels per device (str(device)): {"module", "error", "build_s"}, filled by the first call.
_triton_state: dict[str, dict[str, Any]] = {}


def triton_module(device: torch.device | str) -> ModuleType | None:
    """The Triton kernels for ``device``, checked once against the reference; ``None`` (one warning) if unusable.

    On a CPU device this only works under ``TRITON_INTERPRET=1`` (how the tests run the kernels without a GPU).
    """
    if _disabled():
        return None
    key = _device_key(device)
    if key not in _triton_state:
        state: dict[str, Any] = {"module": None, "error": None, "build_s": None}
        try:
            from anisdf.fields import hash_encoding_triton as mod

            log.info("hash grid: compiling the Triton kernels for %s and checking them against the reference", key)
            t0 = time.perf_counter()
            _self_check(mod, torch.device(device))
            state.update(module=mod, build_s=time.perf_counter() - t0)
            log.info("hash grid: Triton kernels on %s compiled and checked in %.1f s", key, state["build_s"])
        except Exception as err:  # no triton, no compiler for this GPU, a wrong result: use the reference
            state["error"] = _short(err)
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
    """Like :func:`kernel_info`, for the Triton kernels on ``device`` (after :func:`triton_module`)."""
    state = _triton_state.get(_device_key(device), {"module": None, "error": "not loaded", "build_s": None})
    try:
        import triton

        name = f"triton {triton.__version__}"
    except ImportError:
        name = None
    mod = state["module"]
    return {"name": name, "flags": None if mod is None else [f"BLOCK={mod.BLOCK}"], "build_s": state["build_s"],
            "error": state["error"]}


def _self_check(mod: ModuleType, device: torch.device) -> None:
    """Raise unless ``mod`` gives the reference's values, gradients and eikonal double backward on ``device``.

    A small grid with dense and hashed levels, 300 points: it compiles every kernel variant that training uses.
    The first call may come from inside ``no_grad``, ``inference_mode`` or bf16 autocast (a training step, a
    render); the check sets its own float32, gradient-enabled context.
    """
    with torch.inference_mode(False), torch.enable_grad(), torch.autocast(device.type, enabled=False):
        _compare_with_reference(mod, device)


def _compare_with_reference(mod: ModuleType, device: torch.device) -> None:
    spec = GridSpec(n_levels=4, features_per_level=2, log2_hashmap_size=10, base_resolution=6, per_level_scale=1.6)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(300, 3, generator=gen).to(device)
    table = torch.randn(spec.n_params, 2, generator=gen).to(device)
    w = torch.randn(300, spec.output_dim, generator=gen).to(device)
    results = []
    for encode in (hash_encode_reference, functools.partial(_apply, ops=mod)):
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
        return kernel_module()
    if device.type == "cuda":
        return triton_module(device)
    return None


@functools.lru_cache(maxsize=64)
def _levels(spec: GridSpec, device: torch.device | None = None) -> Tensor:
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


def _apply(x: Tensor, table: Tensor, spec: GridSpec, ops: ModuleType) -> Tensor:
    return _Encode.apply(x.contiguous(), table, _levels(spec, x.device), spec.log2_hashmap_size, ops)


def _kernel_inputs(x: Tensor, table: Tensor, spec: GridSpec) -> bool:
    """Whether the kernels handle these inputs at all (dtype, device, features per level, table size)."""
    return (x.device == table.device and x.dtype == torch.float32 and table.dtype == torch.float32
            and spec.features_per_level in (1, 2, 4, 8) and 1 <= spec.log2_hashmap_size <= 31)


def kernel_supports(x: Tensor, table: Tensor, spec: GridSpec) -> bool:
    """Whether a fast kernel handles these inputs (else :func:`fast_hash_encode` uses the reference)."""
    return _kernel_inputs(x, table, spec) and fast_backend(x.device) is not None


def fast_hash_encode(x: Tensor, table: Tensor, spec: GridSpec, required: bool = False) -> Tensor:
    """Encode ``x`` in ``[0, 1]^3`` ``[N, 3]`` to ``[N, L * F]``; same contract as :func:`hash_encode_reference`.

    ``required=True`` (``geometry.encoding_backend=fast``) raises :class:`AnisdfError` where no fast kernel
    exists for the device, instead of using the reference.
    """
    if x.dim() != 2 or x.shape[-1] != 3:
        raise ValueError(f"hash encoding expects points [N, 3], got {tuple(x.shape)}")
    if tuple(table.shape) != (spec.n_params, spec.features_per_level):
        raise ValueError(f"hash table has shape {tuple(table.shape)}, the spec needs "
                         f"({spec.n_params}, {spec.features_per_level})")
    ops = fast_backend(x.device) if _kernel_inputs(x, table, spec) else None
    if ops is None:
        if required:
            _require(x.device)
        return hash_encode_reference(x, table, spec)
    return _apply(x, table, spec, ops)


def _require(device: torch.device) -> None:
    if _disabled():
        raise AnisdfError("geometry.encoding_backend=fast, but ANISDF_NO_KERNEL is set")
    if fast_backend(device) is None:
        reason = _state["error"] if device.type == "cpu" else triton_info(device)["error"]
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
