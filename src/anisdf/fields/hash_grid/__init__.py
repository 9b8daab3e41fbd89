"""Multiresolution hash grid (Mueller et al. 2022), the encoding of both SDF branches (paper Sec. 3.2, Eq. 5).

Backends side by side, each importing only what lies below it:

* :mod:`.reference`: plain PyTorch, the definition every fast backend is tested against (imports none of them);
* :mod:`.ops`: the autograd Functions that drive a fast backend's three entry points;
* :mod:`.cpu_kernel`: the compiled C++ extension (``anisdf/kernels/hashgrid_cpu.cpp``), built under
  :mod:`.build_lock` (a bounded wait for a live build, no wait on a killed one);
* :mod:`.triton`: the CUDA kernels in Triton;
* :mod:`.dispatch`: picks one per device, and the learnable :class:`HashGrid` module.
"""

from anisdf.fields.hash_grid.cpu_kernel import kernel_info, kernel_module
from anisdf.fields.hash_grid.dispatch import (
    HashGrid,
    fast_backend,
    fast_hash_encode,
    jacobian_transpose_product,
    kernel_supports,
    load_fast_encoder,
    triton_info,
    triton_module,
)
from anisdf.fields.hash_grid.reference import EncodeFn, GridSpec, hash_encode_reference

__all__ = ["EncodeFn", "GridSpec", "HashGrid", "fast_backend", "fast_hash_encode", "hash_encode_reference",
           "jacobian_transpose_product", "kernel_info", "kernel_module", "kernel_supports", "load_fast_encoder",
           "triton_info", "triton_module"]
