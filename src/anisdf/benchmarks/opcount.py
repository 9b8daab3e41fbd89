"""What one training step dispatches: operators that would launch a GPU kernel, and reads of device values.

Counted on any device, so a launch budget can be tracked without a GPU: on CUDA a step of this model is bound by
kernel launches and by host reads (each ``.item()``/``nonzero``/boolean-mask index waits for the GPU queue to
drain), not by arithmetic (benchmarks/RESULTS.md). Used by ``benchmarks/profile_step.py --count`` and the tests.
The hash grid's own kernels (C++ on CPU, Triton on CUDA) are not aten operators and are not counted: a few per
SDF query and branch.
"""

from __future__ import annotations

import collections
from typing import TYPE_CHECKING

import torch
from torch.utils._python_dispatch import TorchDispatchMode

if TYPE_CHECKING:
    from anisdf.training.trainer import Trainer

# dispatched but launch no kernel: allocations and metadata
_NO_KERNEL = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "_local_scalar_dense",
              "promote_types", "result_type", "is_nonzero", "sym_size", "sym_numel", "sym_stride"}
_HOST_READS = {"_local_scalar_dense", "nonzero", "unique", "_unique2", "masked_select"}


class OpCounter(TorchDispatchMode):
    """Counts dispatched aten operators and host reads by ``(phase, name)``; ``phase`` is set from outside.

    ``Tensor.tolist`` reads without dispatching an operator: ``count_step`` counts it by wrapping the method."""

    def __init__(self) -> None:
        super().__init__()
        self.phase = "forward"
        self.kernels: collections.Counter[tuple[str, str]] = collections.Counter()
        self.host_reads: collections.Counter[tuple[str, str]] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        if name in _HOST_READS:
            self.host_reads[(self.phase, name)] += 1
        elif name in ("index", "index_put", "index_put_") and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1] if i is not None):
            self.host_reads[(self.phase, f"{name} (bool mask)")] += 1  # a boolean mask becomes indices on the host
        if not func.is_view and name not in _NO_KERNEL:
            self.kernels[(self.phase, name)] += 1
        return func(*args, **kwargs)


def count_step(tr: Trainer) -> OpCounter:
    """Operators of one training step, by phase: the step's own code is run with hooks marking the phases."""
    counter = OpCounter()
    opt_step, backward, tolist = tr.opt.step, torch.Tensor.backward, torch.Tensor.tolist

    def step_marked(*a, **k):  # noqa: ANN002, ANN003, ANN202
        counter.phase = "optimizer"
        out = opt_step(*a, **k)
        counter.phase = "after optimizer"
        return out

    def backward_marked(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        counter.phase = "backward"
        backward(self, *a, **k)
        counter.phase = "after backward"

    def tolist_counted(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        counter.host_reads[(counter.phase, "tolist")] += 1  # reads the data directly: no operator is dispatched
        return tolist(self, *a, **k)

    tr.opt.step = step_marked
    torch.Tensor.backward, torch.Tensor.tolist = backward_marked, tolist_counted
    try:
        with counter:
            tr.train_step()
    finally:
        torch.Tensor.backward, torch.Tensor.tolist = backward, tolist
        del tr.opt.step
    return counter
