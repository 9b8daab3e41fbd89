"""Views made up around the object from where the training cameras are: their common up direction and look-at poses
(OpenCV axes, as :class:`~anisdf.data.cameras.Cameras` take them)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def up_direction(c2w: Tensor | np.ndarray) -> Tensor:
    """The unit mean of the cameras' up axes (OpenCV y points down, so up is -y) of ``c2w`` [N, 3|4, 4], in its dtype.

    When the up axes cancel out (mean shorter than 1e-8), the first camera's up axis."""
    c2w = torch.as_tensor(c2w)
    up = -c2w[:, :3, 1].mean(0)
    norm = up.norm()
    if norm < 1e-8:
        return -c2w[0, :3, 1] / c2w[0, :3, 1].norm()
    return up / norm


def look_at(eye: Tensor | np.ndarray, target: Tensor | np.ndarray, up: Tensor | np.ndarray) -> Tensor:
    """[3, 4] camera-to-world pose (float64, OpenCV axes) at ``eye`` looking at ``target``, ``up`` up on the picture.

    Looking along ``up`` itself, any horizontal direction is taken for the picture's x axis."""
    eye, target, up = (torch.as_tensor(v, dtype=torch.float64).reshape(3) for v in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-9 * max(float(up.norm()), 1e-30):  # looking straight up or down
        helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(z[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=torch.float64)
        x = torch.linalg.cross(z, helper)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z, eye], dim=1)
