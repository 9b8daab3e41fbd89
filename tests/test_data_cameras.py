"""Cameras: projection, ray generation and the OpenCV distortion model."""

from __future__ import annotations

import numpy as np
import torch
from scenes import look_at

from anisdf.data.cameras import Cameras, distort, undistort


def make_cameras(n: int = 3, distortion: tuple[float, float, float, float] | None = None) -> Cameras:
    poses = []
    for i in range(n):
        eye = np.array([3.0 * np.cos(i), 3.0 * np.sin(i), 0.5 * i])
        poses.append(look_at(eye, np.array([0.1, -0.2, 0.0]), np.array([0.0, 0.0, 1.0]))[:3])
    c2w = torch.tensor(np.stack(poses), dtype=torch.float32)
    f = torch.tensor([40.0, 42.0, 38.0][:n])
    return Cameras(
        c2w=c2w,
        fx=f,
        fy=f * 1.05,
        cx=torch.full((n,), 16.3),
        cy=torch.full((n,), 11.8),
        width=32,
        height=24,
        distortion=None if distortion is None else torch.tensor([distortion] * n, dtype=torch.float32),
    )


def point_ray_distance(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    v = points - origins
    return (v - (v * dirs).sum(-1, keepdim=True) * dirs).norm(dim=-1)


def test_undistort_inverts_distort() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1000, generator=g) * 1.2 - 0.6
    y = torch.rand(1000, generator=g) * 0.9 - 0.45
    k = torch.tensor([0.12, -0.05, 0.004, -0.003]).expand(1000, 4)
    xd, yd = distort(x, y, k)
    assert (xd - x).abs().max() > 1e-2  # the model does something
    xu, yu = undistort(xd, yd, k)
    assert torch.allclose(xu, x, atol=1e-6) and torch.allclose(yu, y, atol=1e-6)


def test_project_then_ray_passes_through_point() -> None:
    for dist in (None, (0.1, -0.04, 0.003, -0.002)):
        cams = make_cameras(distortion=dist)
        g = torch.Generator().manual_seed(1)
        pts = torch.randn(200, 3, generator=g) * 0.4
        for i in range(len(cams)):
            uv = cams.project(pts, i)
            assert ((uv[:, 0] > 0) & (uv[:, 0] < 32) & (uv[:, 1] > 0) & (uv[:, 1] < 24)).float().mean() > 0.5
            o, d = cams.rays(torch.full((200,), i), uv[:, 0], uv[:, 1])
            assert torch.allclose(d.norm(dim=-1), torch.ones(200), atol=1e-6)
            assert point_ray_distance(pts, o, d).max() < 1e-4


def test_principal_point_ray_is_optical_axis_and_axes_are_opencv() -> None:
    cams = make_cameras(distortion=(0.2, 0.1, 0.01, 0.01))  # distortion is the identity on the axis
    i = torch.tensor([1])
    o, d = cams.rays(i, cams.cx[1:2], cams.cy[1:2])
    assert torch.allclose(d[0], cams.c2w[1, :, 2], atol=1e-6)
    center = cams.c2w[1, :, 3]
    right, down, fwd = cams.c2w[1, :, 0], cams.c2w[1, :, 1], cams.c2w[1, :, 2]
    uv = cams.project(torch.stack([center + 3 * fwd + 0.1 * right, center + 3 * fwd + 0.1 * down]), 1)
    assert uv[0, 0] > cams.cx[1] and abs(float(uv[0, 1] - cams.cy[1])) < 0.5  # +x is to the right
    assert uv[1, 1] > cams.cy[1] and abs(float(uv[1, 0] - cams.cx[1])) < 0.5  # +y is down


def test_image_rays_are_pixel_centres_at_every_downscale() -> None:
    cams = make_cameras(distortion=(0.05, 0.0, 0.0, 0.0))
    o, d = cams.image_rays(2)
    assert o.shape == (24, 32, 3) and d.shape == (24, 32, 3)
    _, d_ref = cams.rays(torch.tensor([2]), torch.tensor([5.5]), torch.tensor([7.5]))
    assert torch.allclose(d[7, 5], d_ref[0], atol=1e-6)  # row 7, column 5 -> (5.5, 7.5)
    o4, d4 = cams.image_rays(2, downscale=4)
    assert d4.shape == (6, 8, 3)
    _, d_ref4 = cams.rays(torch.tensor([2]), torch.tensor([(3 + 0.5) * 4]), torch.tensor([(1 + 0.5) * 4]))
    assert torch.allclose(d4[1, 3], d_ref4[0], atol=1e-6)


def test_len_to_subset() -> None:
    cams = make_cameras(3, distortion=(0.01, 0.0, 0.0, 0.0))
    assert len(cams) == 3
    moved = cams.to("cpu")
    assert moved.c2w.device.type == "cpu" and moved.width == 32 and moved.distortion is not None
    sub = cams.subset([2, 0])
    assert len(sub) == 2 and torch.equal(sub.c2w[0], cams.c2w[2]) and torch.equal(sub.fx[1], cams.fx[0])
    assert torch.equal(sub.distortion, cams.distortion[[2, 0]])
