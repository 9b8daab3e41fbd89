"""The compiled CPU backend: a C++/OpenMP kernel (``anisdf/kernels/hashgrid_cpu.cpp``, and in the same extension
``softplus_cpu.cpp``, the SDF MLPs' softplus with its slope: :mod:`anisdf.fields.softplus`, ``sdf_mlp_cpu.cpp``,
the SDF MLP with its closed-form gradient, forward and backward: :mod:`anisdf.fields.sdf_mlp`, ``asg_cpu.cpp``,
the colour heads' ASG encoding: :mod:`anisdf.fields.asg`, ``relu_cpu.cpp``, the colour heads' ReLU layers:
:mod:`anisdf.fields.mlp`, ``march_cpu.cpp``, ray marching: :mod:`anisdf.model_components.ray_marching`, and
``jacobian_product_cpu.cpp``, the normal's grid part ``J^T g``: :func:`.ops.jacobian_transpose_product`).

Built with ``torch.utils.cpp_extension.load`` on first use, once per process, under ``$ANISDF_KERNEL_DIR``, else
torch's extension cache (``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``), which every checkout
and environment on the machine shares: the build's name carries a hash of the source, the flags, the torch
version and the Python ABI, so no two of them load or rebuild each other's build. A build runs under
:func:`.build_lock.build_lock`: a build by another live process is waited for (bounded), a killed build's lock is
cleared instead of waited on for ever. Measured on 2 shared cores (``benchmarks/encoding_speed.py``, 2^16-2^18
points, 10-16 levels, log2 T 17-19): forward 14-30x, forward + backward 8-18x, an eikonal step 6-13x the
reference. A build that fails (or waits too long) logs one warning and :func:`kernel_module` returns ``None``
from then on.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

from anisdf.fields.hash_grid.build_lock import build_lock, wait_seconds
from anisdf.fields.hash_grid.ops import kernels_disabled, short_error

log = logging.getLogger(__name__)

_KERNELS = Path(__file__).resolve().parents[2] / "kernels"
SOURCES = (_KERNELS / "hashgrid_cpu.cpp", _KERNELS / "softplus_cpu.cpp", _KERNELS / "sdf_mlp_cpu.cpp",
           _KERNELS / "asg_cpu.cpp", _KERNELS / "jacobian_product_cpu.cpp", _KERNELS / "relu_cpu.cpp",
           _KERNELS / "march_cpu.cpp")
"""The extension's sources; the first holds the Python bindings of all of them."""
HEADERS = (_KERNELS / "fast_math.h", _KERNELS / "softplus_rows.h")
"""Headers the sources include: part of what the build's name hashes."""
_EXT_NAME = "anisdf_hashgrid_cpu"
AVX512 = frozenset({"avx512f", "avx512vl", "avx512dq", "avx512bw"})
"""The AVX-512 subsets the ``avx512`` build is compiled for (with AVX2 and FMA)."""

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

    No ``-march=native``: the cache may be shared by machines of another CPU model. AVX2/FMA, and AVX-512 on top,
    are used only where this CPU has them, and the tag keeps such builds apart from the generic x86-64 one (512-bit
    vectors made the softplus passes of the SDF MLP about 1.25x faster on the 2-core Xeon: benchmarks/RESULTS.md).
    ``-ffp-contract=off`` keeps the rounding identical with and without FMA; ``-fno-trapping-math`` lets
    GCC vectorise ``floor`` (nothing here reads floating-point exception flags).
    """
    flags = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-trapping-math"]
    cpu = _cpu_flags()
    if not {"avx2", "fma"} <= cpu:
        return flags, "generic"
    flags += ["-mavx2", "-mfma"]
    if AVX512 <= cpu:
        return [*flags, *(f"-m{f}" for f in sorted(AVX512))], "avx512"
    return flags, "avx2"


def source_bytes() -> bytes:
    """All sources and headers, in order: what the build's name hashes."""
    return b"\0".join(p.read_bytes() for p in (*SOURCES, *HEADERS))


def torch_identity() -> str:
    """The installed torch: version and source commit."""
    return f"{torch.__version__} {getattr(torch.version, 'git_version', '')}".strip()


def python_abi() -> str:
    """The interpreter's extension ABI, e.g. ``cpython-311-x86_64`` (``sys.abiflags`` where there are any)."""
    return f"{sys.implementation.cache_tag}{getattr(sys, 'abiflags', '')}-{platform.machine()}"


def extension_name(source: bytes, flags: Sequence[str], tag: str, torch_version: str | None = None,
                   abi: str | None = None) -> str:
    """The build's name in the shared extension cache: a hash of everything the compiled module depends on.

    Checkouts with other kernel sources (branches, versions), other torch builds or other Pythons sharing one
    cache never load or rebuild each other's build (torch itself only versions a name within a process).
    """
    key = b"\0".join([source, " ".join(flags).encode(), (torch_version or torch_identity()).encode(),
                       (abi or python_abi()).encode()])
    return f"{_EXT_NAME}_{tag}_{hashlib.sha256(key).hexdigest()[:12]}"


def build_directory(name: str) -> Path:
    """``$ANISDF_KERNEL_DIR/<name>``, else ``<torch's extension cache>/<name>``."""
    root = os.environ.get("ANISDF_KERNEL_DIR") or os.environ.get("TORCH_EXTENSIONS_DIR")
    if not root:
        from torch.utils.cpp_extension import get_default_build_root

        root = get_default_build_root()
    return Path(root).expanduser() / name


def _load(name: str, flags: list[str], build_dir: Path) -> ModuleType:
    from torch.utils import cpp_extension

    return cpp_extension.load(name=name, sources=[str(p) for p in SOURCES], extra_cflags=flags,
                              extra_ldflags=["-fopenmp"], build_directory=str(build_dir), verbose=False)


def _build() -> ModuleType:
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise RuntimeError(f"no C++ compiler ({cxx}) on PATH")
    missing = [str(p) for p in (*SOURCES, *HEADERS) if not p.is_file()]
    if missing:
        raise RuntimeError(f"kernel source {missing[0]} is missing")
    flags, tag = _compile_flags()
    name = extension_name(source_bytes(), flags, tag)
    build_dir = build_directory(name)
    wait_s = wait_seconds()
    log.info("hash grid: loading the compiled CPU kernel (the first build takes about a minute)")
    t0 = time.perf_counter()
    with build_lock(build_dir, wait_s):
        module = _load(name, flags, build_dir)
    _state.update(build_s=time.perf_counter() - t0, name=name, flags=flags)
    return module


def kernel_module() -> ModuleType | None:
    """The compiled CPU extension (built on the first call in this process), or ``None`` if unavailable."""
    if kernels_disabled():
        return None
    if _state["module"] is None and _state["error"] is None:
        try:
            _state["module"] = _build()
        except Exception as err:  # any build failure (compiler, ninja, headers, linker): use the reference
            _state["error"] = short_error(err)
            log.warning("hash grid: compiled CPU kernel unavailable (%s); falling back to the PyTorch "
                        "reference encoding", _state["error"])
    return _state["module"]


def kernel_for(t: torch.Tensor) -> ModuleType | None:
    """The compiled extension for a float32 CPU tensor ``t`` outside ``torch.compile`` (which fuses the references
    itself), else ``None``."""
    if t.device.type != "cpu" or t.dtype != torch.float32 or torch.compiler.is_compiling():
        return None
    return kernel_module()


def kernel_info() -> dict[str, Any]:
    """Build facts for reports: extension name, flags, build/load seconds and the failure reason, if any."""
    return {k: _state[k] for k in ("name", "flags", "build_s", "error")}
