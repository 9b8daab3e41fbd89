"""Tests for anisdf.export: mesh extraction and export, pictures, videos, orbit cameras."""

from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import trimesh

from anisdf.errors import AnisdfError
from anisdf.eval.metrics import chamfer_distance, load_mesh
from anisdf.export.mesh import color_vertices, extract_mesh, remove_floaters, save_mesh, to_world
from anisdf.utils import video as video_mod
from anisdf.utils.images import (
    depth_to_image,
    hstack_labeled,
    normal_to_image,
    save_image,
    scalar_to_image,
    to_uint8,
)
from anisdf.utils.video import orbit_poses, write_video


def sphere_sdf(center: tuple[float, float, float] = (0.0, 0.0, 0.0), r: float = 0.5):
    c = torch.tensor(center)
    return lambda p: (p - c).norm(dim=-1) - r


@pytest.fixture(scope="module")
def sphere_mesh() -> trimesh.Trimesh:
    return extract_mesh(sphere_sdf(), radius=1.0, resolution=64, progress=False)


def _no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------- extraction


def test_sphere_mesh_accurate_and_outward(sphere_mesh: trimesh.Trimesh) -> None:
    m = sphere_mesh
    assert m.is_watertight
    expected_volume = 4.0 / 3.0 * math.pi * 0.5**3
    assert m.volume > 0
    assert abs(m.volume - expected_volume) / expected_volume < 0.03
    # every face normal points away from the centre
    assert np.all(np.einsum("ij,ij->i", m.face_normals, m.triangles_center) > 0)
    radii = np.linalg.norm(m.vertices, axis=1)
    assert np.abs(radii - 0.5).max() < 0.01
    ico = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    assert chamfer_distance(m, ico, n_points=50_000)["chamfer"] < 0.01


def test_extraction_axes_and_offcentre_box() -> None:
    # an axis-aligned ellipsoid away from the origin: checks x/y/z ordering and the world mapping
    centre = np.array([0.3, -0.2, 0.1])
    axes = np.array([0.5, 0.3, 0.15])
    c, a = torch.tensor(centre, dtype=torch.float32), torch.tensor(axes, dtype=torch.float32)

    def ellipsoid(p: torch.Tensor) -> torch.Tensor:  # an approximate SDF with the right zero set
        return ((((p - c) / a) ** 2).sum(-1).sqrt() - 1.0) * a.min()

    m = extract_mesh(ellipsoid, resolution=96, chunk=5000, progress=False)
    lo, hi = m.bounds
    np.testing.assert_allclose((lo + hi) / 2, centre, atol=0.01)
    np.testing.assert_allclose((hi - lo) / 2, axes, atol=0.01)
    assert m.volume == pytest.approx(4 / 3 * math.pi * axes.prod(), rel=0.03)


def test_two_pass_refines_the_surface() -> None:
    single = extract_mesh(sphere_sdf(r=0.3), resolution=96, two_pass=False, progress=False)
    double = extract_mesh(sphere_sdf(r=0.3), resolution=96, two_pass=True, progress=False)
    # pass 1 at 64, pass 2 spends the 96 samples on the object's box only: finer triangles, smaller error
    assert len(double.faces) > 3 * len(single.faces)
    err_single = np.abs(np.linalg.norm(single.vertices, axis=1) - 0.3).max()
    err_double = np.abs(np.linalg.norm(double.vertices, axis=1) - 0.3).max()
    assert err_double < err_single
    assert double.volume > 0


def test_sparse_second_pass_matches_the_dense_reference() -> None:
    # a torus (a hole, thin parts) away from the origin, as an approximate SDF scaled by 0.7
    c = torch.tensor([0.1, -0.2, 0.05])

    def torus(p: torch.Tensor) -> torch.Tensor:
        q = p - c
        ring = torch.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2) - 0.45
        return 0.7 * (torch.sqrt(ring**2 + q[:, 2] ** 2) - 0.12)

    seen: list[int] = []

    def counted(p: torch.Tensor) -> torch.Tensor:
        seen.append(p.shape[0])
        return torus(p)

    dense = extract_mesh(counted, resolution=256, two_pass=True, sparse=False, progress=False)
    n_dense, seen[:] = sum(seen), []
    sparse = extract_mesh(counted, resolution=256, two_pass=True, sparse=True, chunk=3000, progress=False)
    np.testing.assert_array_equal(sparse.vertices, dense.vertices)
    np.testing.assert_array_equal(sparse.faces, dense.faces)
    assert max(seen) <= 3000
    assert sum(seen) < 0.7 * n_dense, (sum(seen), n_dense)  # 0.66 here; ~0.36 at 512 (pass 1 at 128)


@pytest.mark.parametrize("chunk", [700, 32 * 32 * 3 + 5])  # pieces of one x-slice; several x-slices
def test_chunking_does_not_change_the_result(chunk: int) -> None:
    f = sphere_sdf(center=(0.1, 0.0, -0.1), r=0.4)
    seen: list[int] = []

    def counted(p: torch.Tensor) -> torch.Tensor:
        seen.append(p.shape[0])
        return f(p)

    ref = extract_mesh(f, resolution=32, two_pass=False, progress=False)
    got = extract_mesh(counted, resolution=32, two_pass=False, chunk=chunk, progress=False)
    assert max(seen) <= chunk and sum(seen) == 32**3
    np.testing.assert_array_equal(got.vertices, ref.vertices)
    np.testing.assert_array_equal(got.faces, ref.faces)


def test_sdf_output_shape_n1_accepted() -> None:
    f = sphere_sdf()
    m = extract_mesh(lambda p: f(p)[:, None], resolution=32, two_pass=False, progress=False)
    assert m.is_watertight and m.volume > 0


@pytest.mark.parametrize("value", [1.0, -1.0])
def test_no_surface_raises(value: float) -> None:
    with pytest.raises(AnisdfError, match="no surface"):
        extract_mesh(lambda p: torch.full((p.shape[0],), value), resolution=16, progress=False)


def test_nonfinite_sdf_raises() -> None:
    f = sphere_sdf()

    def bad(p: torch.Tensor) -> torch.Tensor:
        out = f(p)
        out[0] = float("nan")
        return out

    with pytest.raises(AnisdfError, match="not finite"):
        extract_mesh(bad, resolution=16, progress=False)


def test_remove_floaters_keeps_main_component() -> None:
    big, tiny = sphere_sdf(r=0.5), sphere_sdf(center=(0.55, 0.55, 0.3), r=0.06)
    m = extract_mesh(lambda p: torch.minimum(big(p), tiny(p)), resolution=96, two_pass=False, progress=False)
    assert m.body_count == 2
    cleaned = remove_floaters(m, min_fraction=0.05)
    assert cleaned.body_count == 1
    assert np.linalg.norm(cleaned.vertices, axis=1).max() < 0.52  # the far sphere is gone
    assert cleaned.is_watertight
    assert remove_floaters(m, min_fraction=0.0).body_count == 2  # threshold respected


def test_only_the_marched_sphere_is_meshed_unless_the_box_is_asked_for() -> None:
    # a blob in a corner of the box, outside the unit sphere that training marches rays through
    big, corner = sphere_sdf(r=0.5), sphere_sdf(center=(0.85, 0.85, 0.85), r=0.1)
    both = lambda p: torch.minimum(big(p), corner(p))  # noqa: E731
    m = extract_mesh(both, resolution=64, progress=False)
    assert m.body_count == 1 and np.linalg.norm(m.vertices, axis=1).max() < 0.52
    assert extract_mesh(both, resolution=64, progress=False, region="box").body_count == 2
    # a surface cut by the sphere is closed by a cap on it: a half space gives a watertight half ball
    half = extract_mesh(lambda p: p[:, 2], resolution=64, two_pass=False, progress=False)
    assert half.is_watertight
    assert half.volume == pytest.approx(2 / 3 * math.pi, rel=0.03)
    with pytest.raises(AnisdfError, match="no surface found in the sphere"):  # negative inside, positive corners
        extract_mesh(lambda p: p.norm(dim=-1) - 1.2, resolution=32, progress=False)


# ---------------------------------------------------------------- colours, transform, saving


def test_color_vertices(sphere_mesh: trimesh.Trimesh) -> None:
    colored = color_vertices(sphere_mesh, lambda p: p + 0.5, chunk=1000)
    vc = colored.visual.vertex_colors
    assert vc.dtype == np.uint8 and vc.shape == (len(sphere_mesh.vertices), 4)
    expected = np.round(np.clip(sphere_mesh.vertices + 0.5, 0, 1) * 255)
    assert np.abs(vc[:, :3].astype(int) - expected).max() <= 1
    assert np.all(vc[:, 3] == 255)
    unchanged = color_vertices(sphere_mesh, None)
    assert unchanged is not sphere_mesh and unchanged.visual.kind != "vertex"


def test_to_world(sphere_mesh: trimesh.Trimesh) -> None:
    T = np.eye(4)
    T[:3, :3] *= 2.0
    T[:3, 3] = [1.0, 2.0, 3.0]
    w = to_world(sphere_mesh, T)
    assert w.volume == pytest.approx(8 * sphere_mesh.volume, rel=1e-9)
    np.testing.assert_allclose(w.vertices.mean(0), [1, 2, 3], atol=1e-6)
    assert np.allclose(sphere_mesh.vertices.mean(0), 0, atol=1e-6)  # input left alone
    mirror = to_world(sphere_mesh, np.diag([-1.0, 1.0, 1.0, 1.0]))
    assert mirror.volume > 0  # winding flipped with the reflection
    with pytest.raises(ValueError):
        to_world(sphere_mesh, np.eye(3))


@pytest.mark.parametrize("fmt", ["ply", "obj", "glb"])
def test_save_mesh_roundtrip_with_colours(tmp_path: Path, sphere_mesh: trimesh.Trimesh, fmt: str) -> None:
    colored = color_vertices(sphere_mesh, lambda p: p + 0.5)
    path = save_mesh(colored, tmp_path / f"sub/mesh.{fmt}")
    assert path.is_file()
    back = load_mesh(path)
    assert len(back.vertices) == len(colored.vertices)
    assert len(back.faces) == len(colored.faces)
    np.testing.assert_allclose(back.vertices, colored.vertices, atol=1e-5)
    assert back.visual.kind == "vertex"
    np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], colored.visual.vertex_colors[:, :3])
    assert back.volume == pytest.approx(colored.volume, rel=1e-5)  # winding survives
    assert _no_temp_files(path.parent)


def test_save_mesh_is_atomic(tmp_path: Path, sphere_mesh: trimesh.Trimesh, monkeypatch) -> None:
    path = tmp_path / "mesh.ply"
    save_mesh(sphere_mesh, path)
    before = path.read_bytes()

    def crash(*args, **kwargs):
        raise RuntimeError("disk on fire")

    broken = sphere_mesh.copy()
    monkeypatch.setattr(broken, "export", crash)
    with pytest.raises(RuntimeError):
        save_mesh(broken, path)
    assert path.read_bytes() == before
    assert _no_temp_files(tmp_path)
    with pytest.raises(AnisdfError, match="unsupported"):
        save_mesh(sphere_mesh, tmp_path / "mesh.xyz")


# ---------------------------------------------------------------- pictures


def test_to_uint8_and_normal_image() -> None:
    assert to_uint8(np.array([-0.5, 0.0, 0.5, 1.0, 2.0, np.nan])).tolist() == [0, 0, 128, 255, 255, 0]
    n = np.zeros((2, 2, 3), dtype=np.float32)
    n[0, 0] = [1, -1, 0]
    n[0, 1] = [0, 0, 1]
    img = normal_to_image(torch.tensor(n))
    assert img.dtype == np.uint8 and img.shape == (2, 2, 3)
    assert img[0, 0].tolist() == [255, 0, 128]
    assert img[0, 1].tolist() == [128, 128, 255]
    masked = normal_to_image(n, mask=np.array([[True, False], [True, True]]))
    assert masked[0, 1].tolist() == [255, 255, 255]


def test_depth_and_scalar_images() -> None:
    depth = np.array([[1.0, 2.0, 3.0], [4.0, np.inf, 9.0]])
    mask = np.array([[True, True, True], [True, True, False]])
    img = depth_to_image(depth, mask=mask)
    assert img.shape == (2, 3, 3) and img.dtype == np.uint8
    lum = img.astype(float).sum(-1)
    assert lum[0, 0] > lum[0, 1] > lum[0, 2] > lum[1, 0]  # near is bright, monotone
    assert img[1, 1].tolist() == [255, 255, 255] and img[1, 2].tolist() == [255, 255, 255]
    g = scalar_to_image(np.array([[0.0, 0.5, 1.0]]), cmap="gray")
    assert g[0, :, 0].tolist() == [0, 128, 255] and np.all(g[..., 0] == g[..., 2])
    v = scalar_to_image(np.linspace(0, 1, 5)[None])
    assert v[0, 0].tolist() == [68, 1, 84]  # viridis end points
    assert v[0, -1].tolist() == [253, 231, 37]


def test_save_image_and_hstack(tmp_path: Path) -> None:
    a = np.zeros((20, 30, 3), dtype=np.float32)
    b = np.full((10, 15), 200, dtype=np.uint8)
    c = np.zeros((20, 10, 4), dtype=np.uint8)  # fully transparent -> white
    panel = hstack_labeled([a, b, c], ["rgb", "gray", "alpha"], gap=4, label_height=16, min_width=0)
    assert panel.shape == (36, 30 + 15 + 10 + 8, 3) and panel.dtype == np.uint8
    strip = panel[:16, :30]
    assert (strip < 128).any() and (strip == 255).mean() > 0.5  # a label is drawn on white
    assert np.all(panel[16:36, :30] == 0)
    assert np.all(panel[16:26, 34:49] == 200) and np.all(panel[26:36, 34:49] == 255)
    assert np.all(panel[16:, 53:] == 255)
    path = save_image(tmp_path / "out" / "panel.png", panel)
    np.testing.assert_array_equal(iio.imread(path), panel)
    assert _no_temp_files(path.parent)
    # small panels are enlarged by a whole factor (nearest pixel) until the widest reaches min_width
    big = hstack_labeled([a, b, c], ["rgb", "gray", "alpha"], gap=4, label_height=16, min_width=60)
    assert big.shape == (16 + 40, 60 + 30 + 20 + 8, 3)
    assert np.all(big[16:36, 64:94] == 200)
    with pytest.raises(ValueError):
        hstack_labeled([a, b], ["only one"])


# ---------------------------------------------------------------- video and cameras


def _frames(n: int = 6, h: int = 33, w: int = 45) -> list[np.ndarray]:
    return [np.full((h, w, 3), 40 * i, dtype=np.uint8) for i in range(n)]


def test_write_video_mp4(tmp_path: Path) -> None:
    path = write_video(_frames(), tmp_path / "orbit.mp4", fps=12)
    assert path == tmp_path / "orbit.mp4"
    frames = iio.imread(path)
    assert frames.shape[0] == 6 and frames.shape[1:3] == (34, 46)  # padded to even size
    assert abs(float(frames[3, 5:25, 5:35].mean()) - 120) < 6  # content survives the codec
    assert _no_temp_files(tmp_path)
    with pytest.raises(AnisdfError):
        write_video([], tmp_path / "empty.mp4")


def test_write_video_falls_back_to_gif(tmp_path: Path, monkeypatch) -> None:
    def fail(*args, **kwargs):
        raise OSError("no ffmpeg here")

    monkeypatch.setattr(video_mod, "_write_mp4", fail)
    with pytest.warns(UserWarning, match="MP4 writing failed"):
        path = write_video(_frames(4), tmp_path / "orbit.mp4")
    assert path == tmp_path / "orbit.gif" and not (tmp_path / "orbit.mp4").exists()
    gif = iio.imread(path)
    assert gif.shape[:3] == (4, 33, 45)
    assert _no_temp_files(tmp_path)


@pytest.mark.parametrize(
    ("up", "look_at"),
    [("z", (0.0, 0.0, 0.0)), ((0.0, 1.0, 0.0), (0.5, -0.2, 1.0)), ((1.0, 1.0, 0.0), (0, 0, 0))],
)
def test_orbit_poses_opencv(up, look_at) -> None:
    n, radius, elev = 8, 3.0, 30.0
    poses = orbit_poses(n, radius, elev, up=up, look_at=look_at).double().numpy()
    assert poses.shape == (n, 3, 4)
    u = np.array([0.0, 0.0, 1.0]) if up == "z" else np.asarray(up, dtype=float) / np.linalg.norm(up)
    target = np.asarray(look_at, dtype=float)
    for P in poses:
        R, t = P[:, :3], P[:, 3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-6)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
        to_target = target - t
        assert np.linalg.norm(to_target) == pytest.approx(radius, rel=1e-6)
        np.testing.assert_allclose(R[:, 2], to_target / radius, atol=1e-6)  # z looks at the target
        assert np.dot(R[:, 1], u) < 0  # y points down
        assert abs(np.dot(R[:, 0], u)) < 1e-6  # x is level (no roll)
        elevation = math.degrees(math.asin(np.dot(t - target, u) / radius))
        assert elevation == pytest.approx(elev, abs=1e-4)
    # the cameras go once around: distinct, evenly spaced positions
    steps = np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-5)
    with pytest.raises(ValueError):
        orbit_poses(4, 1.0, 90.0)


def _hollow_ball(hole: bool):
    """A ball of radius 0.6 with a pocket of radius 0.3 inside; ``hole`` drills a shaft from the pocket to +z."""
    def f(p: torch.Tensor) -> torch.Tensor:
        r = p.norm(dim=-1)
        d = torch.maximum(r - 0.6, 0.3 - r)
        if hole:
            shaft = torch.maximum(p[:, :2].norm(dim=-1) - 0.15, -p[:, 2])
            d = torch.maximum(d, -shaft)
        return d
    return f


def test_enclosed_pockets_are_filled_open_ones_kept() -> None:
    closed = extract_mesh(_hollow_ball(False), resolution=64, two_pass=False, progress=False)
    r = np.linalg.norm(closed.vertices, axis=1)
    assert r.min() > 0.58 and closed.body_count == 1  # the inner shell is gone
    inner = extract_mesh(_hollow_ball(False), resolution=64, two_pass=False, progress=False, keep_inner=True)
    assert inner.body_count == 2 and np.linalg.norm(inner.vertices, axis=1).min() < 0.32
    drilled = extract_mesh(_hollow_ball(True), resolution=64, two_pass=False, progress=False)
    assert np.linalg.norm(drilled.vertices, axis=1).min() < 0.32  # reachable through the shaft: kept
    # two-pass sparse extraction (the default) fills the same pocket
    two_pass = extract_mesh(_hollow_ball(False), resolution=96, progress=False)
    assert np.linalg.norm(two_pass.vertices, axis=1).min() > 0.58
