"""Views made up around the object: the training cameras' up direction and look-at poses (OpenCV axes)."""

from __future__ import annotations

import numpy as np
import torch

from anisdf.data.orbit import look_at, up_direction
from anisdf.utils.video import orbit_poses


def test_up_is_the_unit_mean_of_the_cameras_up_axes_in_their_dtype():
    poses = orbit_poses(8, 3.0, 30.0, up="z")  # float32, OpenCV y down
    up = up_direction(poses)
    assert up.dtype == torch.float32 and torch.allclose(up, torch.tensor([0.0, 0.0, 1.0]), atol=1e-6)
    turned = poses[0].numpy() * [-1, -1, 1, 1]  # the same camera turned upside down about its view axis
    both = np.stack([poses[0].numpy(), turned]).astype(np.float64)
    assert up_direction(both).dtype == torch.float64
    assert torch.allclose(up_direction(both), -torch.as_tensor(both[0, :, 1]))  # opposite ups: the first one's


def test_look_at_puts_the_target_ahead_and_up_on_the_picture():
    pose = look_at([0.0, -3.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    x, y, z, eye = pose.unbind(1)
    assert torch.allclose(pose[:, :3].T @ pose[:, :3], torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(z, -eye / eye.norm()) and float(x[0]) > 0.99 and float(y[2]) < 0  # right is +x, up is -y
    assert torch.allclose(pose.float(), orbit_poses(1, 10 ** 0.5, float(np.degrees(np.arcsin(1 / 10 ** 0.5))),
                                                    start_azimuth_deg=-90.0)[0], atol=1e-6)
    straight_down = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert torch.isfinite(straight_down).all() and torch.allclose(straight_down[:, 2], torch.tensor([0.0, 0, -1.0],
                                                                                                    dtype=torch.float64))
