"""The demo's bundled scene ships with the package and loads as a NeRF-synthetic scene with what eval needs."""

from __future__ import annotations

from anisdf.config import load_config
from anisdf.data.dataparsers import load_scene
from anisdf.eval.metrics import load_mesh
from anisdf.tasks.demo import DEMO_OVERRIDES, demo_scene


def test_the_bundled_bunny_loads_with_test_normals_and_a_reference_mesh():
    root = demo_scene()
    d = load_config("cpu-quick", DEMO_OVERRIDES).data
    scene = load_scene(root, downscale=d.downscale, min_size=d.min_size)  # as the demo trains it: not halved
    assert len(scene.splits["train"]) == 100 and len(scene.splits["test"]) == 5
    assert (scene.height, scene.width) == (128, 128) and scene.alpha is not None and scene.downscale == 1.0
    assert set(scene.normals) >= set(scene.splits["test"])
    assert len(load_mesh(root / "gt_mesh.ply").faces) > 1000
    assert (root / "SOURCES.md").is_file()
