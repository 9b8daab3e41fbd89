from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from anisdf.data.synthetic import make_synthetic_scene

# Without a GPU the Triton kernels (the CUDA hash grid) run in Triton's CPU interpreter, so that the tests check
# them against the reference. Triton reads this once, when it is imported, and torch imports it early (its
# optimizers load torch._dynamo), so it is set here, before any test runs.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")


@pytest.fixture(scope="session")
def toy_scene(tmp_path_factory) -> Path:
    """A tiny analytic scene rendered by the project's own sphere tracer (NeRF-synthetic format)."""
    return make_synthetic_scene(tmp_path_factory.mktemp("toy"), n_train=16, n_test=2, size=32, mesh_resolution=48)
