"""``torch.compile`` for the parts of a step that need no double backward, with the eager code kept beside it.

On a GPU a training step of this model is bound by kernel launches (benchmarks/RESULTS.md): the SDF MLPs, the
radiance heads and the NeuS opacity are chains of small element-wise operators that inductor fuses into a few
kernels. The SDF MLPs can be compiled because their input gradient (the normal) is written out in closed form
(``fields/sdf_field.mlp_with_input_grad``): compiled graphs support one backward, not the double backward of
``autograd.grad(create_graph=True)``. The hash grids stay outside, with their own kernels.
Shapes change every step (the number of samples), so graphs are compiled with dynamic shapes, once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)


class Compiled:
    """``fn`` compiled on first call. If a compiled call fails (no C++ compiler, no Triton, a recompile for new
    inputs that breaks) and the eager ``fn`` succeeds on the same inputs: one warning, and eager from then on.

    An error that the eager function raises as well is the caller's error and propagates unchanged.
    """

    def __init__(self, fn: Callable[..., Any], name: str) -> None:
        self.eager = fn
        self.name = name
        self.compiled: Callable[..., Any] | None = torch.compile(fn, dynamic=True)
        self.compiled_calls = 0

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            return self.eager(*args)
        try:
            out = self.compiled(*args)
        except Exception as err:  # noqa: BLE001  (whatever the compiler raises; the eager call below decides)
            out = self.eager(*args)  # raises here if the inputs, not the compiler, are at fault
            log.warning("torch.compile of %s failed (%s: %s); running it eagerly", self.name,
                        type(err).__name__, str(err).splitlines()[0] if str(err) else "")
            self.compiled = None
            return out
        self.compiled_calls += 1
        return out
