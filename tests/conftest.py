from __future__ import annotations

from pathlib import Path

import pytest

from anisdf.data.synthetic import make_synthetic_scene


@pytest.fixture(scope="session")
def toy_scene(tmp_path_factory) -> Path:
    """A tiny analytic scene rendered by the project's own sphere tracer (NeRF-synthetic format)."""
    return make_synthetic_scene(tmp_path_factory.mktemp("toy"), n_train=16, n_test=2, size=32, mesh_resolution=48)
