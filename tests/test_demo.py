"""The demo's bundled scene ships with the package and loads as a NeRF-synthetic scene with what eval needs."""

from __future__ import annotations

from anisdf.data.dataparsers import load_scene
from anisdf.eval.metrics import load_mesh
from anisdf.tasks.demo import DEMO_OVERRIDES, demo_scene


def test_the_bundled_bunny_loads_with_test_normals_and_a_reference_mesh():
    root = demo_scene()
    scene = load_scene(root, downscale=1)
    assert len(scene.splits["train"]) == 100 and len(scene.splits["test"]) == 5
    assert (scene.height, scene.width) == (128, 128) and scene.alpha is not None  # RGBA, the size cpu-quick trains
    assert set(scene.normals) >= set(scene.splits["test"])
    assert len(load_mesh(root / "gt_mesh.ply").faces) > 1000
    assert (root / "SOURCES.md").is_file() and "data.downscale=1" in DEMO_OVERRIDES
