"""RayDataset: sampling, background compositing, whole images and downscaling."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from scenes import write_test_scene

from anisdf.data import RayBatch, RayDataset, Scene, load_scene
from anisdf.data.rays import eval_background
from anisdf.errors import DataError


@pytest.fixture(scope="module")
def rgba_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    root = tmp_path_factory.mktemp("rgba") / "s"
    write_test_scene(root, "nerf-synthetic")
    return load_scene(root)


@pytest.fixture(scope="module")
def masked_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    root = tmp_path_factory.mktemp("masked") / "s"
    write_test_scene(root, "colmap", masks=True, distortion=(0.05, 0.01, 0.0, 0.0))
    return load_scene(root)


def straight(scene: Scene, batch: RayBatch) -> tuple[torch.Tensor, torch.Tensor | None]:
    px, py = batch.pixels[:, 0].long(), batch.pixels[:, 1].long()
    rgb = scene.images[batch.cam_idx, py, px].float() / 255
    a = None if scene.alpha is None else scene.alpha[batch.cam_idx, py, px].float() / 255
    return rgb, a


def test_sample_is_deterministic_and_covers_the_split(rgba_scene: Scene) -> None:
    ds = RayDataset(rgba_scene, "train")
    assert len(ds) == 4
    a = ds.sample(2048, torch.Generator().manual_seed(3))
    b = ds.sample(2048, torch.Generator().manual_seed(3))
    c = ds.sample(2048, torch.Generator().manual_seed(4))
    for name in ("origins", "directions", "rgb", "background", "cam_idx", "pixels"):
        assert torch.equal(getattr(a, name), getattr(b, name))
    assert not torch.equal(a.pixels, c.pixels)
    assert set(a.cam_idx.tolist()) == set(rgba_scene.splits["train"])
    frac = a.pixels - a.pixels.floor()
    assert torch.all(frac == 0.5)  # pixel centres
    # The rays are the cameras' rays through those pixels.
    o, d = rgba_scene.cameras.rays(a.cam_idx, a.pixels[:, 0], a.pixels[:, 1])
    assert torch.allclose(a.origins, o) and torch.allclose(a.directions, d)


def test_rgba_training_targets_composite_on_random_background(rgba_scene: Scene) -> None:
    ds = RayDataset(rgba_scene, "train")
    batch = ds.sample(4096, torch.Generator().manual_seed(0))
    assert batch.background.std(dim=0).min() > 0.2  # random colours
    rgb, a = straight(rgba_scene, batch)
    assert a is not None and (a == 0).any() and (a == 1).any()
    expected = rgb * a[:, None] + batch.background * (1 - a[:, None])
    assert torch.allclose(batch.rgb, expected, atol=1e-6)
    assert batch.mask is not None and torch.equal(batch.mask, a)


def test_test_split_image_is_row_major_on_white(rgba_scene: Scene) -> None:
    ds = RayDataset(rgba_scene, "test")
    batch, (h, w) = ds.image(1)
    assert (h, w) == (12, 16) and len(batch) == h * w
    assert torch.equal(batch.pixels[w + 3], torch.tensor([3.5, 1.5]))  # row 1, column 3
    assert torch.all(batch.cam_idx == rgba_scene.splits["test"][1])
    assert torch.all(batch.background == 1.0)
    rgb, a = straight(rgba_scene, batch)
    assert torch.allclose(batch.rgb, rgb * a[:, None] + (1 - a[:, None]), atol=1e-6)
    black = RayDataset(rgba_scene, "test", background="black").image(0)[0]
    assert torch.all(black.background == 0.0) and black.rgb.mean() < batch.rgb.mean()


def test_masks_composite_opaque_photos_like_alpha(masked_scene: Scene) -> None:
    batch = RayDataset(masked_scene, "train").sample(1024, torch.Generator().manual_seed(0))
    rgb, _ = straight(masked_scene, batch)
    px, py = batch.pixels[:, 0].long(), batch.pixels[:, 1].long()
    assert batch.mask is not None
    assert torch.equal(batch.mask, masked_scene.masks[batch.cam_idx, py, px].float() / 255)
    m = batch.mask[:, None]
    assert batch.background.std(dim=0).min() > 0.2  # random colours while training
    assert torch.allclose(batch.rgb, rgb * m + batch.background * (1 - m), atol=1e-6)
    white = RayDataset(masked_scene, "test").image(0)[0]
    assert torch.all(white.background == 1.0)
    assert eval_background(masked_scene) == "white"


def test_photos_without_masks_are_kept_as_photographed(tmp_path: Path) -> None:
    write_test_scene(tmp_path / "s", "colmap")
    scene = load_scene(tmp_path / "s")
    assert eval_background(scene) == "auto"
    for split in ("train", "test"):
        batch = RayDataset(scene, split, background=eval_background(scene)).sample(512, torch.Generator())
        rgb, _ = straight(scene, batch)
        assert torch.equal(batch.rgb, rgb) and torch.all(batch.background == 0) and batch.mask is None


def test_explicit_background_needs_alpha_or_masks(tmp_path: Path) -> None:
    write_test_scene(tmp_path / "s", "colmap")
    scene = load_scene(tmp_path / "s")
    with pytest.raises(DataError, match="needs RGBA images or object masks"):
        RayDataset(scene, "train", background="white")


def test_downscaled_evaluation_images(rgba_scene: Scene) -> None:
    ds = RayDataset(rgba_scene, "test", downscale=2)
    batch, (h, w) = ds.image(0)
    assert (h, w) == (6, 8) and len(batch) == 48
    assert torch.equal(batch.pixels[0], torch.tensor([1.0, 1.0]))  # centre of the first 2x2 block
    full, _ = RayDataset(rgba_scene, "test").image(0)
    # Premultiplied area average: the composite on white of the small image is the block mean.
    block = full.rgb.reshape(6, 2, 8, 2, 3).mean(dim=(1, 3)).reshape(-1, 3)
    assert (batch.rgb - block).abs().max() < 2.0 / 255
    o, d = rgba_scene.cameras.image_rays(int(batch.cam_idx[0]), downscale=2)
    assert torch.allclose(batch.directions, d.reshape(-1, 3), atol=1e-6)


def test_split_all_and_unknown(rgba_scene: Scene) -> None:
    assert len(RayDataset(rgba_scene, "all")) == rgba_scene.n_images
    with pytest.raises(Exception, match="unknown split"):
        RayDataset(rgba_scene, "val")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(masked_scene: Scene) -> None:
    cpu = RayDataset(masked_scene, "train").sample(512, torch.Generator().manual_seed(5))
    gpu = RayDataset(masked_scene, "train", device="cuda").sample(512, torch.Generator().manual_seed(5))
    assert gpu.origins.is_cuda and gpu.rgb.is_cuda and gpu.cam_idx.is_cuda
    assert torch.equal(gpu.cam_idx.cpu(), cpu.cam_idx) and torch.equal(gpu.rgb.cpu(), cpu.rgb)
    assert torch.allclose(gpu.directions.cpu(), cpu.directions, atol=1e-5)
    cams = masked_scene.cameras.to("cuda")
    uv = cams.project(torch.zeros(1, 3, device="cuda"), 0)
    assert uv.is_cuda and torch.allclose(uv.cpu(), masked_scene.cameras.project(torch.zeros(1, 3), 0), atol=1e-4)
