"""DTU Chamfer protocol (anisdf.eval.dtu) on tiny scenes written in the official DTU evaluation layout."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from anisdf.cli import main
from anisdf.errors import AnisdfError, DataError
from anisdf.eval.dtu import downsample, dtu_chamfer, sample_mesh

SCAN = 65
CENTER = np.array([-28.0, -28.0, 640.0])  # roughly where DTU scan 65 lies in DTU world coordinates (mm)
RADIUS = 4.0


def _sphere(radius: float = RADIUS, center: np.ndarray = CENTER, subdivisions: int = 4) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(center)
    return m


def _write_dtu(root: Path, obs_half: float = 40.0, res: float = 1.0, bb_half: float = 40.0) -> Path:
    """ObsMask (set within ``obs_half`` mm of the centre), Plane (z = centre - 3, keeps z above) and STL points
    (20k random points on the exact sphere) for scan 65."""
    (root / "ObsMask").mkdir(parents=True)
    (root / "Points" / "stl").mkdir(parents=True)
    p = np.random.default_rng(1).normal(size=(20_000, 3))
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * RADIUS + CENTER
    trimesh.PointCloud(p).export(root / "Points" / "stl" / f"stl{SCAN:03}_total.ply")
    n = int(round(2 * bb_half / res)) + 1
    axis = np.arange(n) * res - bb_half  # voxel centres relative to CENTER
    inside = np.abs(axis) <= obs_half
    obs = (inside[:, None, None] & inside[None, :, None] & inside[None, None, :]).astype(np.uint8)
    bb = np.stack([CENTER - bb_half, CENTER + bb_half])
    scipy.io.savemat(root / "ObsMask" / f"ObsMask{SCAN}_10.mat", {"ObsMask": obs, "BB": bb, "Res": np.array([[res]])})
    scipy.io.savemat(root / "ObsMask" / f"Plane{SCAN}.mat", {"P": np.array([[0.0], [0.0], [1.0], [-(CENTER[2] - 3)]])})
    return root


def _export(mesh: trimesh.Trimesh, path: Path) -> Path:
    mesh.export(path)
    return path


@pytest.fixture
def dtu_root(tmp_path: Path) -> Path:
    return _write_dtu(tmp_path / "dtu")


def test_sampling_and_thinning() -> None:
    tri = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]])
    pts = sample_mesh(tri, np.array([[0, 1, 2]]), 0.2)
    assert len(pts) == 3 + 45  # vertices + grid points (i + 0.5) / 10 with s1 + s2 < 1
    thin = downsample(pts, 0.25, seed=0)
    d, _ = cKDTree(thin).query(thin, k=2)
    assert d[:, 1].min() > 0.25  # no two kept points within the radius
    d_all, _ = cKDTree(thin).query(pts)
    assert d_all.max() <= 0.25  # every removed point has a kept one within the radius
    np.testing.assert_array_equal(thin, downsample(pts, 0.25, seed=0))  # deterministic with the seed
    np.testing.assert_array_equal(sample_mesh(tri, np.array([[0, 1, 2]] * 3), 0.2, chunk=10),
                                  np.concatenate([tri] + [pts[3:]] * 3))  # chunks of the grid give the same points


@pytest.mark.parametrize("radius", [0.02, 0.06, 0.15])
def test_thinning_matches_the_sequential_loop(radius: float) -> None:
    """The vectorised rounds give exactly the points of the official loop over the shuffled order."""
    x = np.random.default_rng(3).uniform(size=(4000, 3))
    order = x.copy()
    np.random.default_rng(5).shuffle(order, axis=0)
    keep = np.ones(len(order), dtype=bool)
    for cur, nb in enumerate(cKDTree(order).query_ball_point(order, radius)):
        if keep[cur]:
            keep[nb] = False
            keep[cur] = True
    np.testing.assert_array_equal(downsample(x, radius, seed=5), order[keep])


def test_self_is_near_zero_and_plane_culls_stl(tmp_path: Path, dtu_root: Path) -> None:
    mesh = _export(_sphere(), tmp_path / "m.ply")
    r = dtu_chamfer(mesh, dtu_root, SCAN, density=0.1)
    assert r["accuracy"] < 0.1 and r["completeness"] < 0.1
    assert r["chamfer"] == pytest.approx((r["accuracy"] + r["completeness"]) / 2)
    # plane z > centre - 3 drops the STL cap below it: 1/8 of the sphere's area (cap height 1 of diameter 8)
    assert r["n_stl_above_plane"] / r["n_stl_downsampled"] == pytest.approx(7 / 8, abs=0.03)
    full = dtu_chamfer(mesh, dtu_root, SCAN, density=0.1, thin_stl=False)
    assert full["n_stl_downsampled"] == full["n_stl_points"] == 20_000 > r["n_stl_downsampled"]
    assert full["accuracy"] < r["accuracy"]  # a denser reference is nearer


def test_offset_by_one_mm(tmp_path: Path, dtu_root: Path) -> None:
    mesh = _export(_sphere(RADIUS + 1.0), tmp_path / "m.ply")  # every point 1 mm off along the normal
    r = dtu_chamfer(mesh, dtu_root, SCAN)
    assert r["accuracy"] == pytest.approx(1.0, abs=0.1)
    assert r["completeness"] == pytest.approx(1.0, abs=0.1)


def test_floater_outside_obs_mask_is_culled(tmp_path: Path) -> None:
    floater = _sphere(1.0, CENTER + [14.0, 0, 0], subdivisions=3)  # ~9 mm from the surface, outside |x| <= 7
    both = _export(trimesh.util.concatenate([_sphere(), floater]), tmp_path / "both.ply")
    alone = _export(_sphere(), tmp_path / "m.ply")
    masked = _write_dtu(tmp_path / "masked", obs_half=7.0)
    full = _write_dtu(tmp_path / "full")
    base = dtu_chamfer(alone, masked, SCAN)
    r = dtu_chamfer(both, masked, SCAN)
    assert r["accuracy"] == pytest.approx(base["accuracy"], abs=0.01)
    assert r["n_data_in_obs_mask"] == pytest.approx(base["n_data_in_obs_mask"], rel=0.02)
    assert r["n_data_in_bbox"] > base["n_data_in_bbox"]  # the floater was sampled, then culled
    assert dtu_chamfer(both, full, SCAN)["accuracy"] > base["accuracy"] + 0.5  # not culled: it counts


def test_outliers_beyond_max_dist_are_discarded(tmp_path: Path, dtu_root: Path) -> None:
    floater = _sphere(1.0, CENTER + [0, 30.0, 0], subdivisions=3)  # ~25 mm from the surface, inside the ObsMask
    both = _export(trimesh.util.concatenate([_sphere(), floater]), tmp_path / "both.ply")
    base = dtu_chamfer(_export(_sphere(), tmp_path / "m.ply"), dtu_root, SCAN)
    r = dtu_chamfer(both, dtu_root, SCAN)
    assert r["n_accuracy_outliers"] > 0 and base["n_accuracy_outliers"] == 0
    assert r["accuracy"] == pytest.approx(base["accuracy"], abs=0.01)
    wide = dtu_chamfer(both, dtu_root, SCAN, max_dist=40.0)
    assert wide["n_accuracy_outliers"] == 0 and wide["accuracy"] > base["accuracy"] + 1.0


def test_scale_mat_maps_unit_sphere_to_mm(tmp_path: Path, dtu_root: Path) -> None:
    unit = _export(_sphere(1.0, np.zeros(3)), tmp_path / "unit.ply")
    scale = np.eye(4)
    scale[:3, :3] *= RADIUS
    scale[:3, 3] = CENTER
    np.savez(tmp_path / "cameras_sphere.npz", scale_mat_0=scale, world_mat_0=np.eye(4))
    r = dtu_chamfer(unit, dtu_root, SCAN, scale_mat=tmp_path / "cameras_sphere.npz")
    ref = dtu_chamfer(_export(_sphere(), tmp_path / "m.ply"), dtu_root, SCAN)
    assert r["accuracy"] == pytest.approx(ref["accuracy"], abs=1e-6)
    assert r["completeness"] == pytest.approx(ref["completeness"], abs=1e-6)
    with pytest.raises(AnisdfError, match="no point .* inside .*ObsMask65_10.mat"):
        dtu_chamfer(unit, dtu_root, SCAN)  # left in the unit sphere it misses the ObsMask


def _camera_dataset(folder: Path, mask_radius_px: float) -> Path:
    """One camera 100 mm in front of the sphere (looking along +z, 200x200 px, f = 400 px) and its mask."""
    (folder / "mask").mkdir(parents=True)
    k = np.array([[400.0, 0, 100], [0, 400.0, 100], [0, 0, 1]])
    cam_center = CENTER - [0, 0, 100.0]
    world = np.eye(4)
    world[:3, :4] = k @ np.concatenate([np.eye(3), -cam_center[:, None]], axis=1)
    np.savez(folder / "cameras_sphere.npz", world_mat_0=world, scale_mat_0=np.eye(4))
    yy, xx = np.mgrid[:200, :200]
    mask = ((xx - 100) ** 2 + (yy - 100) ** 2 <= mask_radius_px**2).astype(np.uint8) * 255
    Image.fromarray(np.repeat(mask[..., None], 3, axis=2)).save(folder / "mask" / "000.png")
    return folder


def test_mask_cull_removes_floater_outside_masks(tmp_path: Path, dtu_root: Path) -> None:
    floater = _sphere(1.0, CENTER + [14.0, 0, 0], subdivisions=3)  # projects 56 px from the centre
    far = _sphere(1.0, CENTER + [10.0, 0, -90.0], subdivisions=2)  # projects 400 px off centre: in no image
    both = _export(trimesh.util.concatenate([_sphere(), floater, far]), tmp_path / "both.ply")
    cams = _camera_dataset(tmp_path / "scene", mask_radius_px=18.0)  # the sphere covers 16 px
    base = dtu_chamfer(_export(_sphere(), tmp_path / "m.ply"), dtu_root, SCAN)
    assert dtu_chamfer(both, dtu_root, SCAN)["accuracy"] > base["accuracy"] + 0.5
    r = dtu_chamfer(both, dtu_root, SCAN, mask_cull=(cams / "cameras_sphere.npz", cams / "mask"))
    assert r["mask_cull_removed_vertices"] == len(floater.vertices) + len(far.vertices)
    assert r["n_mesh_vertices"] == len(_sphere().vertices)
    assert r["accuracy"] == pytest.approx(base["accuracy"], abs=0.01)
    with pytest.raises(AnisdfError, match="removed the whole mesh"):
        dtu_chamfer(_export(floater, tmp_path / "f.ply"), dtu_root, SCAN,
                    mask_cull=(cams / "cameras_sphere.npz", cams / "mask"))


def test_cli_last_line(tmp_path: Path, dtu_root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mesh = _export(_sphere(RADIUS + 1.0), tmp_path / "m.ply")
    cams = _camera_dataset(tmp_path / "scene", mask_radius_px=30.0)
    assert main(["dtu-chamfer", str(mesh), "--dtu-root", str(dtu_root), "--scan", str(SCAN),
                 "--mask-cull", str(cams), "--no-stl-thinning"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    m = re.fullmatch(r"accuracy (\d+\.\d{3}) completeness (\d+\.\d{3}) chamfer (\d+\.\d{3})", lines[-1])
    assert m, lines[-1]
    acc, comp, cd = map(float, m.groups())
    assert acc == pytest.approx(1.0, abs=0.1) and comp == pytest.approx(1.0, abs=0.1)
    assert cd == pytest.approx((acc + comp) / 2, abs=1e-3)
    assert any(line.startswith("mask_cull: ") and str(cams / "mask") in line for line in lines)
    assert "density_mm: 0.2" in lines and "max_dist_mm: 20.0" in lines and "thin_stl: False" in lines


def test_missing_files_name_the_expected_path(tmp_path: Path, dtu_root: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    mesh = _export(_sphere(), tmp_path / "m.ply")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["dtu-chamfer", str(mesh), "--dtu-root", str(empty), "--scan", "65"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(empty / "ObsMask" / "ObsMask65_10.mat") in err
    assert main(["dtu-chamfer", str(mesh), "--dtu-root", str(dtu_root), "--scan", "65",
                 "--scale-mat", str(tmp_path / "nope.npz")]) == 2
    assert str(tmp_path / "nope.npz") in capsys.readouterr().err
    assert main(["dtu-chamfer", str(mesh), "--dtu-root", str(dtu_root), "--scan", "65",
                 "--mask-cull", str(empty)]) == 2
    assert str(empty / "cameras_sphere.npz") in capsys.readouterr().err
    assert main(["dtu-chamfer", str(tmp_path / "none.ply"), "--dtu-root", str(dtu_root), "--scan", "65"]) == 2
    assert str(tmp_path / "none.ply") in capsys.readouterr().err
    (dtu_root / "Points" / "stl" / "stl065_total.ply").unlink()
    with pytest.raises(DataError, match=re.escape(str(dtu_root / "Points" / "stl" / "stl065_total.ply"))):
        dtu_chamfer(mesh, dtu_root, SCAN)
