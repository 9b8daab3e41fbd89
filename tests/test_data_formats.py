"""Every dataset format: parse tiny scenes with known cameras and check the round trip.

``write_test_scene`` writes each format as that format's own tools do; the hand-written cases below pin
the axis conventions independently of it (a mirrored bug in writer and parser would cancel out).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scenes import write_test_scene

from anisdf.data import detect_format, load_scene
from anisdf.errors import DataError

DIST = (0.08, -0.03, 0.004, -0.003)
CASES = [
    ("nerf-synthetic", {}),
    ("neus", {}),
    ("instant-ngp", {}),
    ("instant-ngp", {"distortion": DIST}),
    ("llff", {}),
    ("llff", {"masks": True}),
    ("colmap", {"binary": True}),
    ("colmap", {"binary": False}),
    ("colmap", {"binary": True, "distortion": DIST}),
    ("colmap", {"binary": False, "distortion": DIST, "masks": True}),
]


def _id(case: tuple[str, dict]) -> str:
    return case[0] + "".join(f"-{k}" for k in case[1])


@pytest.mark.parametrize("case", CASES, ids=[_id(c) for c in CASES])
def test_round_trip(tmp_path: Path, case: tuple[str, dict]) -> None:
    fmt, kw = case
    truth = write_test_scene(tmp_path / "scene", fmt, **kw)
    assert detect_format(tmp_path / "scene") == fmt
    scene = load_scene(tmp_path / "scene")
    n = len(truth.image_paths)
    assert scene.format == fmt and scene.n_images == n
    assert scene.images.shape == (n, 12, 16, 3) and scene.images.dtype == torch.uint8
    assert sorted(scene.splits["train"] + scene.splits["test"]) == list(range(n))
    assert set(scene.splits["train"]).isdisjoint(scene.splits["test"]) and scene.splits["test"]
    assert (scene.cameras.distortion is not None) == ("distortion" in kw)
    # Same images, in the order of the cameras.
    order = [truth.image_paths.index(p) for p in scene.image_paths]

    rng = np.random.default_rng(0)
    pts = truth.sphere_center + rng.normal(size=(64, 3)) * 0.35
    pts_norm = torch.tensor(scene.to_normalised_frame(pts), dtype=torch.float32)
    for i, j in enumerate(order):
        ref = truth.project(pts, j)
        uv = scene.cameras.project(pts_norm, i)
        assert np.abs(uv.numpy() - ref).max() < 1e-3, f"camera {i}: projection differs from the truth"
        o, d = scene.cameras.rays(torch.full((64,), i), torch.tensor(ref[:, 0]), torch.tensor(ref[:, 1]))
        v = pts_norm - o
        miss = (v - (v * d).sum(-1, keepdim=True) * d).norm(dim=-1)
        assert miss.max() < 1e-4, f"camera {i}: ray misses its point by {miss.max():.2e}"

    # Normalisation: a similarity without rotation, mapping back to the dataset frame.
    tw = scene.to_world
    assert np.allclose(tw[:3, :3], tw[0, 0] * np.eye(3)) and np.allclose(tw[3], [0, 0, 0, 1])
    centers = scene.cameras.c2w[:, :, 3].double().numpy()
    assert np.allclose(scene.to_dataset_frame(centers), truth.c2w[order, :3, 3], atol=1e-5)
    assert np.allclose(scene.cameras.c2w[:, :, :3].numpy(), truth.c2w[order, :3, :3], atol=1e-5)
    # The object lies inside the unit sphere, the cameras outside it.
    obj = scene.to_normalised_frame(truth.sphere_center)
    r_obj = truth.sphere_radius / scene.scale
    assert np.linalg.norm(obj) + r_obj < 1.0, (scene.roi_method, obj, r_obj)
    assert r_obj > 0.25, "the object should fill a fair part of the unit sphere"
    assert (np.linalg.norm(centers, axis=1) > 1.0).all()
    assert scene.scene_radius == pytest.approx(scene.scale)


def test_region_of_interest_methods(tmp_path: Path) -> None:
    methods = {}
    for fmt, kw in [("nerf-synthetic", {}), ("neus", {}), ("llff", {"masks": True}), ("colmap", {})]:
        write_test_scene(tmp_path / fmt, fmt, **kw)
        scene = load_scene(tmp_path / fmt)
        methods[fmt] = scene.roi_method
        if fmt == "neus":  # the scale_mat is used as it is
            assert np.allclose(scene.to_world, np.load(tmp_path / fmt / "cameras_sphere.npz")["scale_mat_0"])
    assert methods == {"nerf-synthetic": "visual-hull", "neus": "scale_mat", "llff": "visual-hull",
                       "colmap": "camera-axes"}


def test_rgba_masks_and_normals(tmp_path: Path) -> None:
    truth = write_test_scene(tmp_path / "b", "nerf-synthetic")
    scene = load_scene(tmp_path / "b")
    assert scene.background == "rgba" and scene.alpha is not None and scene.masks is None
    assert sorted(scene.normals) == sorted(scene.splits["test"])
    for idx, nmap in scene.normals.items():
        assert nmap.shape == (12, 16, 4) and nmap.dtype == torch.float32
        covered = nmap[..., 3] > 0.99
        assert covered.any() and torch.allclose(nmap[covered][:, :3].norm(dim=-1), torch.ones(1), atol=2e-2)
        # At the pixel where the sphere's centre projects, the normal faces the camera.
        j = truth.image_paths.index(scene.image_paths[idx])
        u, v = truth.project(truth.sphere_center[None], j)[0]
        n = nmap[int(v), int(u), :3].double().numpy()
        view = truth.c2w[j, :3, 3] - truth.sphere_center
        assert n @ (view / np.linalg.norm(view)) > 0.9
    # Alpha covers the object where the camera sees it.
    u, v = truth.project(truth.sphere_center[None], 0)[0]
    assert scene.alpha[0, int(v), int(u)] == 255 and scene.alpha[0, 0, 0] == 0

    write_test_scene(tmp_path / "l", "llff", masks=True)
    llff = load_scene(tmp_path / "l")
    assert llff.background == "opaque" and llff.alpha is None and llff.masks is not None
    assert set(np.unique(llff.masks.numpy())) == {0, 255}


@pytest.mark.parametrize("suffix", ["_normal.png", "_normal_0001.png"])
def test_reference_normal_maps_under_both_public_names(tmp_path: Path, suffix: str) -> None:
    """Shiny Blender's r_i_normal.png and NeRF-synthetic's r_i_normal_0001.png: world-space (n + 1) / 2."""
    from scenes import _render

    truth = write_test_scene(tmp_path / "b", "nerf-synthetic", width=24, height=20, normal_suffix=suffix)
    assert sorted(p.name for p in (tmp_path / "b" / "test").iterdir() if "normal" in p.name) == sorted(
        p.stem + suffix for p in truth.image_paths if p.parent.name == "test")
    scene = load_scene(tmp_path / "b")
    assert sorted(scene.normals) == sorted(scene.splits["test"])
    for idx, nmap in scene.normals.items():
        j = truth.image_paths.index(scene.image_paths[idx])
        _, cov, ref = _render(truth, j)  # the sphere's true world normals
        full = cov > 0.99
        got = nmap[..., :3].double().numpy()[full]
        cos = np.clip((got * ref[full]).sum(-1), -1, 1)
        assert full.sum() > 20 and np.degrees(np.arccos(cos)).max() < 1.5  # 8-bit quantisation only


def test_one_split_reloaded_in_a_given_normalisation(tmp_path: Path) -> None:
    """What eval does: the test views alone, at another resolution, in the frame training found."""
    write_test_scene(tmp_path / "s", "colmap", n_images=17)
    train = load_scene(tmp_path / "s", downscale=2)
    test = load_scene(tmp_path / "s", split="test", to_world=train.to_world)
    ids = train.splits["test"]
    assert test.splits["test"] == [0, 1, 2] and not test.splits["train"] and len(ids) == 3
    assert [p.name for p in test.image_paths] == [train.image_paths[i].name for i in ids]
    np.testing.assert_array_equal(test.to_world, train.to_world)
    assert torch.allclose(test.cameras.c2w, train.cameras.c2w[ids])
    assert torch.allclose(test.cameras.fx, 2 * train.cameras.fx[ids]) and (test.width, test.height) == (16, 12)
    with pytest.raises(DataError, match="split 'val' is empty"):
        load_scene(tmp_path / "s", split="val", to_world=train.to_world)
    with pytest.raises(ValueError):
        load_scene(tmp_path / "s", split="test")


def test_downscale_scales_intrinsics_with_pixel_centres(tmp_path: Path) -> None:
    truth = write_test_scene(tmp_path / "s", "instant-ngp", distortion=DIST, masks=True)
    full = load_scene(tmp_path / "s")
    half = load_scene(tmp_path / "s", downscale=2)
    assert (half.width, half.height) == (8, 6) and half.images.shape == (6, 6, 8, 3)
    assert half.masks is not None and half.masks.shape == (6, 6, 8)
    assert torch.allclose(half.cameras.fx, full.cameras.fx / 2) and torch.allclose(half.cameras.cx, full.cameras.cx / 2)
    pts = truth.sphere_center + np.random.default_rng(1).normal(size=(20, 3)) * 0.3
    for i in range(6):
        ref = truth.project(pts, i) / 2  # pixel corner (0, 0) is fixed, so coordinates simply halve
        uv = half.cameras.project(torch.tensor(half.to_normalised_frame(pts), dtype=torch.float32), i)
        assert np.abs(uv.numpy() - ref).max() < 1e-3
    # Area downscaling: a 2x2 block average of the full image.
    block = full.images[2].float().reshape(6, 2, 8, 2, 3).mean(dim=(1, 3))
    assert (block - half.images[2].float()).abs().max() <= 1.0


def test_min_size_lowers_the_downscale_of_small_images(tmp_path: Path) -> None:
    """data.min_size: a 16 x 12 capture halved would be 8 px wide; with min_size 12 it loads 12 x 9, its intrinsics
    scaled to match, and the scene says the factor it applied. Larger images, and no min_size, halve as asked."""
    write_test_scene(tmp_path / "s", "instant-ngp", distortion=DIST)
    full = load_scene(tmp_path / "s")
    capped = load_scene(tmp_path / "s", downscale=2, min_size=12)
    assert (capped.width, capped.height) == (12, 9) and capped.images.shape[1:3] == (9, 12)
    assert capped.downscale == pytest.approx(16 / 12)
    assert torch.allclose(capped.cameras.fx, full.cameras.fx * 12 / 16)
    for min_size, want in [(0, (8, 6)), (8, (8, 6)), (64, (16, 12))]:
        s = load_scene(tmp_path / "s", downscale=2, min_size=min_size)
        assert (s.width, s.height) == want and s.downscale == pytest.approx(16 / want[0])
    assert load_scene(tmp_path / "s", downscale=1, min_size=64).width == 16  # never enlarged


def test_max_images_thins_the_train_split(tmp_path: Path) -> None:
    write_test_scene(tmp_path / "s", "colmap", n_images=12)
    full = load_scene(tmp_path / "s")
    few = load_scene(tmp_path / "s", max_images=3)
    assert len(few.splits["train"]) == 3 and len(few.splits["test"]) == len(full.splits["test"])
    assert few.n_images == 3 + len(full.splits["test"])
    kept = {few.image_paths[i] for i in few.splits["train"]}
    assert kept <= {full.image_paths[i] for i in full.splits["train"]}
    assert {few.image_paths[i] for i in few.splits["test"]} == {full.image_paths[i] for i in full.splits["test"]}


# --- hand-written files pinning each format's axis convention ------------------------------------------

def _blank(path: Path, size: tuple[int, int] = (16, 12)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (90, 90, 90)).save(path)


def _check_axes(scene_dir: Path, y_up: bool) -> None:
    """The camera at world (0, 0, +-4) looks at the origin: world +x appears to the right and world +y
    up (OpenGL-style files) or down (OpenCV-style files)."""
    scene = load_scene(scene_dir)
    pts = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    uv = scene.cameras.project(torch.tensor(scene.to_normalised_frame(pts), dtype=torch.float32), 0).numpy()
    assert np.allclose(uv[0], [scene.cameras.cx[0], scene.cameras.cy[0]], atol=1e-3)
    assert uv[1, 0] > uv[0, 0] + 1 and abs(uv[1, 1] - uv[0, 1]) < 1e-3
    assert abs(uv[2, 0] - uv[0, 0]) < 1e-3 and ((uv[2, 1] < uv[0, 1] - 1) if y_up else (uv[2, 1] > uv[0, 1] + 1))


GL_POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]  # at +4 z, looking down -z, y up


def test_axes_blender(tmp_path: Path) -> None:
    _blank(tmp_path / "train" / "r_0.png")
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0", "transform_matrix": GL_POSE}]}))
    _check_axes(tmp_path, y_up=True)
    assert load_scene(tmp_path).cameras.cx[0] == pytest.approx(8.0)


def test_axes_instant_ngp(tmp_path: Path) -> None:
    _blank(tmp_path / "images" / "a.jpg")
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 6.0, "w": 16, "h": 12,
         "frames": [{"file_path": "images/a.jpg", "transform_matrix": GL_POSE}]}))
    _check_axes(tmp_path, y_up=True)


def test_axes_llff(tmp_path: Path) -> None:
    _blank(tmp_path / "images" / "a.png")
    down, right, back, center, hwf = [0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 4], [12, 16, 20]
    pose = np.array([down, right, back, center, hwf], dtype=np.float64).T  # 3x5, columns as LLFF stores them
    np.save(tmp_path / "poses_bounds.npy", np.concatenate([pose.reshape(-1), [2.0, 6.0]])[None])
    _check_axes(tmp_path, y_up=True)


def test_axes_colmap_txt(tmp_path: Path) -> None:
    _blank(tmp_path / "images" / "a.png")
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 PINHOLE 16 12 20 20 8 6\n")
    # world-to-camera identity rotation, t = (0, 0, 4): the camera sits at (0, 0, -4) looking along +z
    (sparse / "images.txt").write_text("# comment\n1 1 0 0 0 0 0 4 1 a.png\n\n")
    _check_axes(tmp_path, y_up=False)


def test_axes_colmap_bin_radial(tmp_path: Path) -> None:
    _blank(tmp_path / "images" / "a.png")
    sparse = tmp_path / "sparse"  # models directly in sparse/ are found too
    sparse.mkdir(parents=True)
    (sparse / "cameras.bin").write_bytes(struct.pack("<QiiQQ5d", 1, 7, 3, 16, 12, 20.0, 8.0, 6.0, 0.1, 0.02))
    blob = struct.pack("<Qidddddddi", 1, 1, 1, 0, 0, 0, 0, 0, 4, 7) + b"a.png\x00" + struct.pack("<Q", 0)
    (sparse / "images.bin").write_bytes(blob)
    _check_axes(tmp_path, y_up=False)
    scene = load_scene(tmp_path)
    assert torch.allclose(scene.cameras.distortion[0], torch.tensor([0.1, 0.02, 0.0, 0.0]))


def test_axes_neus_and_pixel_centre_shift(tmp_path: Path) -> None:
    _blank(tmp_path / "image" / "000.png")
    k = np.array([[20.0, 0, 7.5, 0], [0, 20.0, 5.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # IDR: centres at integers
    w2c = np.eye(4)
    w2c[2, 3] = 4.0
    np.savez(tmp_path / "cameras_sphere.npz", world_mat_0=k @ w2c, scale_mat_0=np.diag([2.0, 2.0, 2.0, 1.0]))
    _check_axes(tmp_path, y_up=False)
    scene = load_scene(tmp_path)
    assert (float(scene.cameras.cx[0]), float(scene.cameras.cy[0])) == pytest.approx((8.0, 6.0))
    assert scene.scene_radius == pytest.approx(2.0)


def test_llff_hwf_scaled_to_image_size(tmp_path: Path) -> None:
    _blank(tmp_path / "images" / "a.png", size=(16, 12))
    pose = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 4], [24, 32, 40]], dtype=np.float64).T
    np.save(tmp_path / "poses_bounds.npy", np.concatenate([pose.reshape(-1), [2.0, 6.0]])[None])
    scene = load_scene(tmp_path)
    assert float(scene.cameras.fx[0]) == pytest.approx(20.0) and float(scene.cameras.cx[0]) == pytest.approx(8.0)
