"""Quick checks on the real datasets in ../shared/data (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from anisdf.data import inspect_dataset, load_scene

DATA = Path(__file__).parents[1] / ".." / "shared" / "data"

EXPECTED = {
    # folder: (format, n_images, n_train, n_test, has_masks, has_normals)
    "fox": ("instant-ngp", 50, 43, 7, False, False),
    "dtu_scan65": ("neus", 49, 42, 7, True, False),
    "maryrose": ("llff", 69, 60, 9, True, False),
    "bunny_plastic": ("nerf-synthetic", 150, 100, 50, False, True),
}


def need(name: str) -> Path:
    path = DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is not available")
    return path


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_inspect_real_dataset(name: str) -> None:
    report = inspect_dataset(need(name))
    fmt, n, n_train, n_test, masks, normals = EXPECTED[name]
    got = (report["format"], report["n_images"], report["n_train"], report["n_test"], report["has_masks"],
           report["has_normals"])
    assert got == (fmt, n, n_train, n_test, masks, normals)
    assert report["warnings"] == []
    assert report["camera_distance"][0] > 1.0  # every camera outside the region of interest
    if name == "bunny_plastic":  # GT mesh: bounding radius 1 at the origin, padded ~10%
        assert report["roi_method"] == "visual-hull" and report["has_alpha"]
        assert np.linalg.norm(report["scene_center"]) < 0.05 and 1.0 < report["scene_radius"] < 1.25
    if name == "maryrose":  # the masks agree with the LLFF poses only if the axes are right
        assert report["roi_method"] == "visual-hull"
    if name == "fox":
        assert report["has_distortion"] and (report["width"], report["height"]) == (270, 480)


def test_bunny_mesh_projects_inside_alpha() -> None:
    trimesh = pytest.importorskip("trimesh")
    root = need("bunny_plastic")
    scene = load_scene(root, max_images=2)
    mesh = trimesh.load(root / "gt_mesh.ply", process=False)
    verts = torch.tensor(scene.to_normalised_frame(np.asarray(mesh.vertices)), dtype=torch.float32)
    for i in scene.splits["test"][::10]:
        uv = scene.cameras.project(verts, i).round().long().clamp(0, scene.width - 1)
        assert scene.alpha is not None
        inside = (scene.alpha[i][uv[:, 1], uv[:, 0]] > 0).float().mean()
        assert inside > 0.995, f"image {i}: only {inside:.3f} of the mesh lands on the alpha mask"
    assert set(scene.normals) == set(scene.splits["test"])
