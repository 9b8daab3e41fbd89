"""The compiled CPU backend: a C++/OpenMP kernel (``anisdf/kernels/hashgrid_cpu.cpp``).

Built with ``torch.utils.cpp_extension.load`` on first use, once per process, into torch's extension cache
(``~/.cache/torch_extensions/...``) or under ``$ANISDF_KERNEL_DIR``. Measured on 2 shared cores
(``benchmarks/bench_encoding.py``, 2^16-2^18 points, 10-16 levels, log2 T 17-19): forward 14-30x,
forward + backward 8-18x, an eikonal step 6-13x the reference. A build that fails logs one warning and
:func:`kernel_module` returns ``None`` from then on.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import time
from pathlib import Path
from types import ModuleType
from typing import Any

from anisdf.fields.hash_grid.ops import kernels_disabled, short_error

log = logging.getLogger(__name__)

SOURCE = Path(__file__).resolve().parents[2] / "kernels" / "hashgrid_cpu.cpp"
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
    # The source's hash in the name: checkouts with different kernel sources (branches, versions) sharing one
    # extension cache never load or rebuild each other's build (torch only versions a name within a process).
    digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(flags).encode()).hexdigest()[:10]
    name = f"{_EXT_NAME}_{tag}_{digest}"
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


def kernel_info() -> dict[str, Any]:
    """Build facts for reports: extension name, flags, build/load seconds and the failure reason, if any."""
    return {k: _state[k] for k in ("name", "flags", "build_s", "error")}
