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

# Under pytest-xdist (`make test` runs one worker a core) each worker keeps to one thread: the toy scenes' tensors
# are too small for two threads to pay, and two workers with two threads each would fight for the cores.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def kernel() -> object:
    """The compiled CPU extension (hash grid, softplus, ASG, ``J^T g``); the test skips, saying why, without it."""
    from anisdf.fields.hash_grid import cpu_kernel

    mod = cpu_kernel.kernel_module()
    if mod is None:
        reason = cpu_kernel.kernel_info()["error"] or "disabled by ANISDF_NO_KERNEL"
        pytest.skip(f"compiled CPU kernel unavailable: {reason}")
    return mod


@pytest.fixture(scope="session")
def toy_scene(tmp_path_factory) -> Path:
    """A tiny analytic scene rendered by the project's own sphere tracer (NeRF-synthetic format)."""
    return make_synthetic_scene(tmp_path_factory.mktemp("toy"), n_train=16, n_test=2, size=32, mesh_resolution=48)


# Runs shared by the test files that use them (session scope: each is trained once a session, not once a file).
# test_materials expects the fit at its 15 steps when it starts (it then continues it): other files only read them.
EXPORT_ARGS = ["--faces", "4k", "--texture", "128", "--specular-texture", "64", "--directions", "32",
               "--resolution", "64", "--no-progress"]


@pytest.fixture(scope="session")
def exported(toy_scene, tmp_path_factory) -> tuple[Path, Path]:
    """A tiny trained run of the toy scene and its ``anisdf export`` with two lobes: (run, asset folder)."""
    from test_training import TINY

    from anisdf.cli import main

    root = tmp_path_factory.mktemp("export")
    run = root / "run"
    assert main(["train", str(toy_scene), "--out", str(run), "--preset", "cpu-quick", "--max-steps", "60",
                 "--no-progress", *TINY]) == 0
    assert main(["export", str(run), "--out", str(root / "k2"), "--lobes", "2", *EXPORT_ARGS]) == 0
    return run, root / "k2"


@pytest.fixture(scope="session")
def fitted_run(toy_scene, tmp_path_factory) -> Path:
    """A tiny trained run of the toy scene with a material fit (``anisdf materials``, 15 steps)."""
    from test_materials import TINY_FIT
    from test_training import TINY

    from anisdf.cli import main

    run = tmp_path_factory.mktemp("materials") / "run"
    assert main(["train", str(toy_scene), "--out", str(run), "--preset", "cpu-quick", "--max-steps", "60",
                 "--no-progress", *TINY]) == 0
    assert main(["materials", str(run), *TINY_FIT]) == 0
    return run
