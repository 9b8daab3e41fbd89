"""RGBA colour conventions: premultiplied-in-linear images (path tracers) are told from straight ones and read as
straight colour, so that the loader's composites do not depend on how the renderer stored them."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from anisdf.data.alpha import detect, linear_to_srgb, srgb_to_linear, unpremultiply
from anisdf.data.dataparsers import load_scene
from anisdf.data.images import read_rgb
from anisdf.errors import AnisdfError


def premultiply(rgb: np.ndarray, a: np.ndarray) -> np.ndarray:
    """What Mitsuba writes: sRGB of the linear colour times coverage, 8-bit."""
    lin = srgb_to_linear(rgb / 255.0) * (a[..., None] / 255.0)
    return np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8)


@pytest.fixture(scope="module")
def straight_and_premultiplied(toy_scene: Path, tmp_path_factory) -> tuple[Path, Path]:
    """The toy scene (straight colour) and a copy whose RGBA images hold premultiplied colour."""
    pre = tmp_path_factory.mktemp("premultiplied") / "scene"
    shutil.copytree(toy_scene, pre)
    for path in list(pre.glob("train/r_*.png")) + list(pre.glob("test/r_*.png")):
        if path.name.endswith("_normal.png"):
            continue
        rgba = np.asarray(Image.open(path)).copy()
        rgba[..., :3] = premultiply(rgba[..., :3].astype(np.float64), rgba[..., 3])
        Image.fromarray(rgba, "RGBA").save(path)
    return toy_scene, pre


def test_unpremultiply_recovers_the_straight_colour() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (64, 64, 3)).astype(np.float64)
    a = rng.integers(64, 256, (64, 64)).astype(np.uint8)
    back = unpremultiply(premultiply(rgb, a), a).astype(np.float64)
    err = np.abs(back - rgb)
    assert err.mean() < 1.0 and err.max() <= 8  # 8-bit rounding, amplified by 1 / a at low coverage
    assert (unpremultiply(np.full((2, 2, 3), 9, np.uint8), np.zeros((2, 2), np.uint8)) == 0).all()


def test_detect_tells_the_conventions_apart(straight_and_premultiplied) -> None:
    straight, pre = straight_and_premultiplied
    for root, expected in ((straight, "straight"), (pre, "premultiplied")):
        samples = [read_rgb(p)[:2] for p in sorted((root / "train").glob("r_*[0-9].png"))[:8]]
        mode, evidence = detect(samples)
        assert mode == expected, evidence
    opaque = [(np.full((8, 8, 3), 200, np.uint8), np.full((8, 8), 255, np.uint8))]
    mode, evidence = detect(opaque)
    assert mode == "straight" and "fewer than" in evidence


def test_synthetic_scene_rims_carry_the_surface_colour(toy_scene: Path) -> None:
    """Partly covered pixels of the project's own renders hold the colour of the surface they see, not black."""
    rgb, a, _ = read_rgb(sorted((toy_scene / "train").glob("r_*[0-9].png"))[0])
    rim = rgb[(a > 0) & (a < 255)].astype(np.float64).mean()
    inside = rgb[a == 255].astype(np.float64).mean()
    assert rim > 0.6 * inside


def test_loader_reads_premultiplied_images_as_straight_colour(straight_and_premultiplied) -> None:
    straight, pre = straight_and_premultiplied
    a = load_scene(straight)
    b = load_scene(pre)
    assert a.alpha_mode.startswith("straight") and b.alpha_mode.startswith("premultiplied"), (a.alpha_mode,
                                                                                               b.alpha_mode)
    assert bool((a.alpha == b.alpha).all())
    covered = a.alpha >= 64
    diff = (a.images.float() - b.images.float()).abs()[covered]
    assert diff.mean() < 1.0 and diff.max() <= 8
    raw = load_scene(pre, alpha="straight")  # forced: the stored colour as it is, darker at the rims
    rim = (a.alpha > 0) & (a.alpha < 200)
    assert raw.alpha_mode.startswith("straight")
    assert (a.images.float() - raw.images.float())[rim].mean() > 10
    with pytest.raises(AnisdfError, match="data.alpha"):
        load_scene(pre, alpha="linear")
