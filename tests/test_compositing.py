"""One compositing route (``anisdf.data.images.composite``) for training targets, metrics and saved pictures."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scenes import write_test_scene

from anisdf.data import RayDataset, load_scene
from anisdf.eval.metrics import composite_on_white
from anisdf.utils.images import composite, to_rgb_uint8


def test_composite_on_tensors_and_arrays() -> None:
    rgb = np.array([[0.2, 0.4, 0.6]] * 3, dtype=np.float32)
    alpha = np.array([[0.0], [1.0], [0.25]], dtype=np.float32)
    bg = np.array([[1.0, 0.0, 0.5]] * 3, dtype=np.float32)
    out = composite(rgb, alpha, bg)
    np.testing.assert_allclose(out[0], bg[0])  # transparent: the background
    np.testing.assert_allclose(out[1], rgb[1])  # opaque: the object
    np.testing.assert_allclose(out[2], 0.25 * rgb[2] + 0.75 * bg[2], rtol=1e-6)
    t = composite(torch.from_numpy(rgb), torch.from_numpy(alpha), torch.from_numpy(bg))
    assert isinstance(t, torch.Tensor) and np.array_equal(t.numpy(), out)
    np.testing.assert_allclose(composite(rgb, alpha, 1.0), composite(rgb, alpha, np.ones_like(rgb)))


@pytest.mark.parametrize("split", ["train", "test"])
def test_training_targets_metrics_and_pictures_agree(tmp_path, split: str) -> None:
    """A white-background target from RayDataset is what metrics and the picture writer make of the RGBA image."""
    root = tmp_path / "s"
    write_test_scene(root, "nerf-synthetic")
    scene = load_scene(root)
    assert scene.alpha is not None and (scene.alpha == 0).any() and ((scene.alpha > 0) & (scene.alpha < 255)).any()
    ds = RayDataset(scene, split, background="white")
    for i in range(len(ds)):
        cam = int(ds.indices[i])
        rgba = torch.cat([scene.images[cam], scene.alpha[cam][..., None]], dim=-1).numpy()  # uint8 HxWx4
        target = ds.target_image(i).numpy()
        np.testing.assert_allclose(composite_on_white(rgba), target, atol=1e-6)
        picture = to_rgb_uint8(rgba).astype(np.int16)
        assert np.abs(picture - np.round(target * 255)).max() <= 1
