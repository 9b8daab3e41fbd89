"""Pinhole cameras with optional OpenCV (k1, k2, p1, p2) distortion and ray generation.

Conventions used throughout anisdf:

* camera-to-world matrices ``c2w`` are OpenCV style: camera x right, y down, z forward;
* pixel ``(i, j)`` (column, row) covers ``[i, i+1] x [j, j+1]``, so its centre is ``(i + 0.5, j + 0.5)``
  and ``cx, cy`` are given in this corner-origin convention (a centred principal point is ``W/2, H/2``);
* the OpenCV distortion model maps undistorted normalised coordinates ``(x, y) = (X/Z, Y/Z)`` to
  distorted ones: ``xd = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)`` and
  ``yd = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y``.

All arithmetic is torch, so everything runs on the device of the tensors.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

UNDISTORT_ITERS = 10


def distort(x: Tensor, y: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Apply the OpenCV radial-tangential model; ``k`` is ``[..., 4]`` (k1, k2, p1, p2) broadcast to x."""
    k1, k2, p1, p2 = k.unbind(-1)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort(xd: Tensor, yd: Tensor, k: Tensor, iters: int = UNDISTORT_ITERS) -> tuple[Tensor, Tensor]:
    """Invert :func:`distort` with Newton's method on the 2x2 system (vectorised, any device)."""
    k1, k2, p1, p2 = k.unbind(-1)
    x, y = xd.clone(), yd.clone()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        d_radial = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(x) = d_radial * x
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        a = radial + d_radial * x * x + 2.0 * p1 * y + 6.0 * p2 * x  # d fx / dx
        b = d_radial * x * y + 2.0 * p1 * x + 2.0 * p2 * y  # d fx / dy == d fy / dx
        d = radial + d_radial * y * y + 6.0 * p1 * y + 2.0 * p2 * x  # d fy / dy
        det = a * d - b * b
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        x = x - (d * fx - b * fy) / det
        y = y - (a * fy - b * fx) / det
    return x, y


@dataclass
class Cameras:
    """A set of pinhole cameras sharing one image size (see the module docstring for conventions)."""

    c2w: Tensor
    """[N,3,4] float32 camera-to-world (OpenCV axes), in the normalised scene frame."""
    fx: Tensor
    fy: Tensor
    cx: Tensor
    cy: Tensor
    """[N] float32 intrinsics in pixels at the loaded resolution."""
    width: int
    height: int
    distortion: Tensor | None = None
    """[N,4] OpenCV k1, k2, p1, p2, or None when every camera is distortion free."""

    def __post_init__(self) -> None:
        if self.c2w.ndim != 3 or self.c2w.shape[1:] != (3, 4):
            raise ValueError(f"c2w must be [N,3,4], got {tuple(self.c2w.shape)}")
        n = self.c2w.shape[0]
        for name in ("fx", "fy", "cx", "cy"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must be [{n}], got {tuple(getattr(self, name).shape)}")
        if self.distortion is not None and self.distortion.shape != (n, 4):
            raise ValueError(f"distortion must be [{n},4], got {tuple(self.distortion.shape)}")

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def centers(self) -> Tensor:
        """[N,3] camera centres."""
        return self.c2w[:, :, 3]

    def to(self, device: torch.device | str) -> Cameras:
        return replace(
            self,
            c2w=self.c2w.to(device),
            fx=self.fx.to(device),
            fy=self.fy.to(device),
            cx=self.cx.to(device),
            cy=self.cy.to(device),
            distortion=None if self.distortion is None else self.distortion.to(device),
        )

    def subset(self, idx: list[int] | Tensor) -> Cameras:
        """The cameras at the given indices (same image size)."""
        i = torch.as_tensor(idx, dtype=torch.long, device=self.device)
        return replace(
            self,
            c2w=self.c2w[i],
            fx=self.fx[i],
            fy=self.fy[i],
            cx=self.cx[i],
            cy=self.cy[i],
            distortion=None if self.distortion is None else self.distortion[i],
        )

    def rays(self, cam_idx: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
        """World-space rays through pixel coordinates ``(px, py)`` (pixel centres are ``i + 0.5``).

        Returns origins ``[B,3]`` and unit directions ``[B,3]``; with distortion the direction is that of
        the undistorted ray, found by inverting the OpenCV model (:func:`undistort`).
        """
        cam_idx = cam_idx.to(self.device).long()
        px = px.to(self.device, torch.float32)
        py = py.to(self.device, torch.float32)
        x = (px - self.cx[cam_idx]) / self.fx[cam_idx]
        y = (py - self.cy[cam_idx]) / self.fy[cam_idx]
        if self.distortion is not None:
            x, y = undistort(x, y, self.distortion[cam_idx])
        d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        pose = self.c2w[cam_idx]
        d_world = (pose[:, :, :3] @ d_cam.unsqueeze(-1)).squeeze(-1)
        d_world = d_world / d_world.norm(dim=-1, keepdim=True)
        return pose[:, :, 3].clone(), d_world

    def project(self, points: Tensor, cam_idx: int, return_depth: bool = False) -> Tensor:
        """Project world points ``[M,3]`` into camera ``cam_idx``: ``[M,2]`` pixel coordinates (distorted).

        Points behind the camera give meaningless coordinates; ask for ``return_depth`` ([M,3] with the
        camera-space z appended) to filter them.
        """
        pose = self.c2w[cam_idx]
        rot, t = pose[:, :3], pose[:, 3]
        p_cam = (points.to(self.device, torch.float32) - t) @ rot  # R^T (p - t), row-vector form
        z = p_cam[:, 2]
        x = p_cam[:, 0] / z
        y = p_cam[:, 1] / z
        if self.distortion is not None:
            x, y = distort(x, y, self.distortion[cam_idx])
        u = self.fx[cam_idx] * x + self.cx[cam_idx]
        v = self.fy[cam_idx] * y + self.cy[cam_idx]
        out = [u, v, z] if return_depth else [u, v]
        return torch.stack(out, dim=-1)

    def image_size(self, downscale: int = 1) -> tuple[int, int]:
        """``(H', W')`` of the image grid used by :meth:`image_rays` at ``downscale``."""
        return max(1, self.height // downscale), max(1, self.width // downscale)

    def pixel_grid(self, downscale: int = 1) -> tuple[Tensor, Tensor]:
        """Pixel-centre coordinates ``px, py`` ``[H',W']`` of a ``downscale``-reduced image, expressed in the
        loaded resolution (a resize maps the full image extent onto the smaller grid)."""
        h2, w2 = self.image_size(downscale)
        sx, sy = self.width / w2, self.height / h2
        cols = (torch.arange(w2, device=self.device, dtype=torch.float32) + 0.5) * sx
        rows = (torch.arange(h2, device=self.device, dtype=torch.float32) + 0.5) * sy
        py, px = torch.meshgrid(rows, cols, indexing="ij")
        return px, py

    def image_rays(self, cam_idx: int, downscale: int = 1) -> tuple[Tensor, Tensor]:
        """Rays through every pixel centre of camera ``cam_idx``: origins and directions ``[H',W',3]``."""
        px, py = self.pixel_grid(downscale)
        idx = torch.full((px.numel(),), int(cam_idx), dtype=torch.long, device=self.device)
        o, d = self.rays(idx, px.reshape(-1), py.reshape(-1))
        shape = (*px.shape, 3)
        return o.reshape(shape), d.reshape(shape)
