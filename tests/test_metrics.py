"""Tests for anisdf.eval.metrics and the report writer (anisdf.tasks.evaluate.report)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from skimage.metrics import structural_similarity

from anisdf.errors import AnisdfError, DataError
from anisdf.eval.metrics import (
    chamfer_distance,
    chamfer_main,
    composite_on_white,
    decode_normal_png,
    load_mesh,
    normal_mae_deg,
    psnr,
    sample_surface,
    ssim,
)
from anisdf.tasks.evaluate.report import format_value, write_report

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _rect(x0: float, x1: float, y0: float, y1: float, z: float = 0.0) -> trimesh.Trimesh:
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


# ---------------------------------------------------------------- PSNR / SSIM


def test_psnr_known_values_and_mask() -> None:
    gt = np.full((8, 10, 3), 0.5)
    pred = gt + 0.1  # MSE 0.01 -> 20 dB
    assert psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert psnr(torch.tensor(pred), torch.tensor(gt)) == pytest.approx(20.0, abs=1e-9)
    assert psnr(gt, gt) == math.inf
    # error only in the right half: masked to the left half the images are identical
    pred2 = gt.copy()
    pred2[:, 5:] += 0.2
    mask = np.zeros((8, 10), dtype=bool)
    mask[:, :5] = True
    assert psnr(pred2, gt, mask=mask) == math.inf
    assert psnr(pred2, gt, mask=~mask) == pytest.approx(-10 * math.log10(0.04), abs=1e-9)
    assert psnr(pred2, gt) == pytest.approx(-10 * math.log10(0.02), abs=1e-9)
    with pytest.raises(AnisdfError):
        psnr(pred2, gt, mask=np.zeros((8, 10), dtype=bool))
    with pytest.raises(ValueError):
        psnr(pred2, gt[:4])


def test_psnr_uint8_is_scaled() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    assert psnr(a, b) == pytest.approx(psnr(a / 255.0, b / 255.0), abs=1e-9)


def _smooth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    chans = []
    for _ in range(3):
        fx, fy, ph = rng.uniform(1, 4), rng.uniform(1, 4), rng.uniform(0, 6)
        chans.append(0.5 + 0.4 * np.sin(2 * np.pi * (fx * x + fy * y) + ph))
    return np.stack(chans, axis=-1)


def _ssim_pair(kind: str, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    if kind == "gray":
        rng = np.random.default_rng(2)
        a = rng.random((h, w))
        return a, np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    rng = np.random.default_rng(1)
    if kind == "random":
        a = rng.random((h, w, 3))
        return a, np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    a = _smooth(rng, h, w)
    return a, np.clip(0.9 * a + 0.05 + rng.normal(0, 0.03, a.shape), 0, 1)


# SSIM of these pairs by the hand-written implementation anisdf used before it called scikit-image (separable
# 11x11 Gaussian "valid" convolution in float64, sigma 1.5, population covariances, mean over channels), computed
# with that code before it was deleted: the switch changed no number beyond 1e-15.
OLD_SSIM = {
    ("random", (32, 32)): 0.8192024002197034,
    ("random", (41, 57)): 0.8204037938225615,
    ("smooth", (32, 32)): 0.9867334282589509,
    ("smooth", (41, 57)): 0.9735788347963054,
    ("gray", (23, 19)): 0.9314993753223252,
}


@pytest.mark.parametrize(("kind", "shape"), list(OLD_SSIM))
def test_ssim_is_skimage_and_keeps_the_previous_numbers(kind: str, shape: tuple[int, int]) -> None:
    a, b = _ssim_pair(kind, shape)
    got = ssim(torch.tensor(a, dtype=torch.float64), b)
    assert got == pytest.approx(OLD_SSIM[(kind, shape)], abs=1e-12)
    ref = structural_similarity(a, b, channel_axis=-1 if a.ndim == 3 else None, data_range=1,
                                gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert got == pytest.approx(ref, abs=1e-12)
    assert got < 0.99  # the pair is genuinely different
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    u8 = np.round(a * 255).astype(np.uint8)  # integer images are scaled by 1/255
    assert ssim(u8, b) == pytest.approx(ssim(u8 / 255.0, b), abs=1e-12)


def test_ssim_rejects_tiny_images() -> None:
    with pytest.raises(ValueError):
        ssim(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


def test_composite_on_white() -> None:
    rgba = np.zeros((2, 2, 4))
    rgba[0, 0] = [1, 0, 0, 1]  # opaque red
    rgba[0, 1] = [0, 0, 0, 0.25]  # mostly transparent black
    out = composite_on_white(rgba)
    np.testing.assert_allclose(out[0, 0], [1, 0, 0])
    np.testing.assert_allclose(out[0, 1], [0.75, 0.75, 0.75])
    np.testing.assert_allclose(out[1, 1], [1, 1, 1])


# ---------------------------------------------------------------- sampling and Chamfer


def test_sample_surface_seeded_and_area_weighted() -> None:
    # two disjoint rectangles with areas 1 and 3: a quarter of the points on the first
    mesh = trimesh.util.concatenate([_rect(0, 1, 0, 1), _rect(2, 5, 0, 1)])
    p1 = sample_surface(mesh, 20_000, seed=3)
    p2 = sample_surface(mesh, 20_000, seed=3)
    p3 = sample_surface(mesh, 20_000, seed=4)
    assert p1.shape == (20_000, 3)
    np.testing.assert_array_equal(p1, p2)
    assert not np.array_equal(p1, p3)
    frac_small = float(np.mean(p1[:, 0] < 1.5))
    assert abs(frac_small - 0.25) < 0.015
    assert np.all(p1[:, 2] == 0) and p1[:, 1].min() >= 0 and p1[:, 1].max() <= 1


def test_chamfer_self_is_sampling_noise() -> None:
    # Two independent uniform samplings of a surface of area A with N points each are
    # 0.5 * sqrt(A / N) apart on average (Poisson nearest neighbour in 2D). Unit sphere, 100k points:
    # 0.0056 (0.00177 at 1M); a mesh is never compared with its own point set.
    n = 100_000
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    r = chamfer_distance(sphere, sphere, n_points=n, seed=0)
    expected = 0.5 * math.sqrt(sphere.area / n)
    assert r["chamfer"] == pytest.approx(expected, rel=0.05)
    assert r["chamfer"] == pytest.approx(0.5 * (r["accuracy"] + r["completeness"]))
    assert r["n_points"] == n
    again = chamfer_distance(sphere, sphere, n_points=n, seed=0)
    assert again["chamfer"] == r["chamfer"]  # deterministic


def test_chamfer_shift_along_normal() -> None:
    # a plane shifted by 0.01 along its normal: every nearest neighbour is >= 0.01 away
    a = _rect(0, 1, 0, 1, z=0.0)
    b = _rect(0, 1, 0, 1, z=0.01)
    r = chamfer_distance(a, b, n_points=100_000, seed=0)
    assert 0.01 <= r["chamfer"] < 0.0108
    # a sphere shifted by 0.01 along x: the surfaces are |0.01 cos(theta)| apart, 0.005 on average,
    # which adds to the sampling noise: clearly above the unshifted value
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    t = s.copy()
    t.apply_translation([0.01, 0, 0])
    base = chamfer_distance(s, s, n_points=50_000)["chamfer"]
    shifted = chamfer_distance(s, t, n_points=50_000)["chamfer"]
    assert shifted > base + 0.001


def test_chamfer_accuracy_vs_completeness_direction() -> None:
    # prediction covers only half of the reference: accurate but incomplete
    pred = _rect(0, 1, 0, 1)
    ref = _rect(0, 2, 0, 1)
    r = chamfer_distance(pred, ref, n_points=40_000, seed=0)
    assert r["accuracy"] < 0.01
    # half of the reference points lie in [1, 2] x [0, 1], on average 0.5 away from the square
    assert r["completeness"] == pytest.approx(0.5 * 0.5, abs=0.01)


def test_load_mesh_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="not found") as e:
        load_mesh(tmp_path / "missing.ply")
    assert "missing.ply" in str(e.value)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat nonsense\n\x00\x01garbage")
    with pytest.raises(DataError) as e2:
        load_mesh(bad)
    assert "bad.ply" in str(e2.value)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(cloud)
    with pytest.raises(DataError):
        load_mesh(cloud)
    good = tmp_path / "good.obj"
    trimesh.creation.box().export(good)
    m = load_mesh(good)
    assert len(m.faces) == 12


def test_chamfer_main(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    _rect(0, 1, 0, 1).export(a)
    _rect(0, 1, 0, 1, z=0.02).export(b)
    value = chamfer_main(str(a), str(b), n_points=20_000, seed=0)
    out = capsys.readouterr().out
    assert 0.02 <= value < 0.025
    assert "accuracy" in out and "completeness" in out and "20000" in out


# ---------------------------------------------------------------- normals


def _encode(n: np.ndarray, cov: np.ndarray) -> np.ndarray:
    rgb = np.round((n + 1) / 2 * 255).astype(np.uint8)
    return np.concatenate([rgb, np.round(cov * 255).astype(np.uint8)[..., None]], axis=-1)


def test_decode_normal_png() -> None:
    n = np.zeros((2, 2, 3))
    n[..., 2] = 1.0
    n[0, 0] = [-1, 0, 0]
    cov = np.array([[1.0, 0.0], [1.0, 1.0]])
    dec = decode_normal_png(_encode(n, cov))
    assert dec.shape == (2, 2, 4) and dec.dtype == np.float32
    np.testing.assert_allclose(dec[..., :3], n, atol=1.001 / 255)  # 8-bit rounding
    np.testing.assert_allclose(dec[..., 3], cov)
    rgb_only = decode_normal_png(_encode(n, cov)[..., :3])
    assert np.all(rgb_only[..., 3] == 1)


def test_normal_mae() -> None:
    rng = np.random.default_rng(0)
    n = rng.normal(size=(16, 16, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cov = np.ones((16, 16))
    cov[:, :4] = 0  # background
    gt = np.concatenate([n, cov[..., None]], axis=-1)
    assert normal_mae_deg(n, gt) == 0.0
    # rotate every normal by 10 degrees about z ... only those not parallel to z move by exactly 10,
    # so use normals in the xy plane
    n_xy = n.copy()
    n_xy[..., 2] = 0
    n_xy /= np.linalg.norm(n_xy, axis=-1, keepdims=True)
    c, s = math.cos(math.radians(10)), math.sin(math.radians(10))
    rot = n_xy @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    gt_xy = np.concatenate([n_xy, cov[..., None]], axis=-1)
    assert normal_mae_deg(3.0 * rot, gt_xy) == pytest.approx(10.0, abs=1e-6)  # scale does not matter
    # background pixels (coverage 0) do not count even when totally wrong
    pred = n_xy.copy()
    pred[:, :4] = -pred[:, :4]
    assert normal_mae_deg(torch.tensor(pred), gt_xy) == pytest.approx(0.0, abs=1e-9)
    # an explicit mask overrides the coverage: 1/4 of the pixels at 180 degrees
    assert normal_mae_deg(pred, gt_xy, mask=np.ones((16, 16), dtype=bool)) == pytest.approx(45.0, abs=1e-6)
    with pytest.raises(AnisdfError):
        normal_mae_deg(n, np.concatenate([n, np.zeros((16, 16, 1))], axis=-1))


def test_normal_mae_weights_as_ref_nerf() -> None:
    """Weighted mean as Ref-NeRF's compute_weighted_mae(acc * alpha, n, n_gt), here with known angles."""
    gt = np.zeros((4, 4, 3))
    gt[..., 2] = 1.0
    pred = np.zeros((4, 4, 3))
    angles = np.array([0.0, 30.0, 60.0, 90.0])[None, :].repeat(4, axis=0)  # per column
    pred[..., 0], pred[..., 2] = np.sin(np.radians(angles)), np.cos(np.radians(angles))
    opacity = np.ones((4, 4))
    alpha = np.ones((4, 4))
    alpha[:, 3] = 0.0  # the 90-degree column is background in the ground truth
    opacity[:, 2] = 0.5  # the 60-degree column is half transparent in the render
    w = opacity * alpha
    expected = (0 + 30 + 0.5 * 60) / 2.5
    assert normal_mae_deg(pred, gt, weights=w) == pytest.approx(expected, abs=1e-9)
    # the same as Ref-NeRF's formula (arccos of the clipped dot product) on random normals, up to its clip
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(20, 30, 3)), rng.normal(size=(20, 30, 3))
    wr = rng.random((20, 30)) * (rng.random((20, 30)) > 0.3)
    an, bn = (v / np.linalg.norm(v, axis=-1, keepdims=True) for v in (a, b))
    one_eps = 1 - np.finfo(np.float32).eps
    ref = (wr * np.arccos(np.clip((an * bn).sum(-1), -one_eps, one_eps))).sum() / wr.sum() * 180 / np.pi
    assert normal_mae_deg(a, b, weights=wr) == pytest.approx(ref, abs=0.03)
    with pytest.raises(AnisdfError):
        normal_mae_deg(pred, gt, weights=np.zeros((4, 4)))
    with pytest.raises(ValueError):
        normal_mae_deg(pred, gt, weights=-w)
    with pytest.raises(ValueError):
        normal_mae_deg(pred, gt, weights=np.ones((3, 4)))


def test_normal_png_from_dataset() -> None:
    path = DATA / "bunny_plastic" / "test" / "r_0_normal.png"
    if not path.is_file():
        pytest.skip("shared data not present")
    import imageio.v3 as iio

    dec = decode_normal_png(iio.imread(path))
    fg = dec[..., 3] > 0.5
    assert 0.05 < fg.mean() < 0.95
    norms = np.linalg.norm(dec[..., :3][fg], axis=-1)
    assert abs(float(np.median(norms)) - 1.0) < 0.02
    assert normal_mae_deg(dec[..., :3], dec) == 0.0


# ---------------------------------------------------------------- report


def test_format_value() -> None:
    assert format_value(33.42137) == "33.4214"
    assert format_value(0.0048912) == "4.8912e-03"
    assert format_value(7) == "7"
    assert format_value(np.float32(0.5)) == "0.5000"
    assert format_value(None) == "-"


def test_write_report(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    img_dir = out / "images"
    img_dir.mkdir(parents=True)
    img = img_dir / "r_0 side.png"
    img.write_bytes(b"\x89PNG")
    metrics = {"psnr": 31.23456, "ssim": 0.95123, "chamfer": 0.0048912, "normal_mae": 2.5}
    per_view = [
        {"view": "r_0", "psnr": 30.0, "ssim": 0.9, "normal_mae": 2.0},
        {"view": "r_<1>", "psnr": 32.0, "ssim": 0.95, "normal_mae": 3.0},
    ]
    html_path, md_path = write_report(out, metrics, per_view, [img])
    assert html_path == out / "report.html" and md_path == out / "report.md"
    html_text, md_text = html_path.read_text(), md_path.read_text()
    for text in (html_text, md_text):
        for number in ("31.2346", "0.9512", "4.8912e-03", "2.5000", "30.0000", "32.0000", "0.9500"):
            assert number in text
        assert "31.0000" in text and "0.9250" in text  # mean row
    assert "r_&lt;1&gt;" in html_text and "<1>" not in html_text
    assert 'src="images/r_0 side.png"' in html_text
    assert "(images/r_0%20side.png)" in md_text
    assert html_text.lstrip().startswith("<!DOCTYPE html>")
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left
