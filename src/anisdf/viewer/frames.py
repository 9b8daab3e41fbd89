"""The browser's camera rendered by the project's own renderer (:func:`anisdf.models.views.render_rays_to_maps`).

viser reports a client's camera in the scene's frame (here anisdf's normalised frame) with OpenCV axes, as anisdf's
:class:`~anisdf.data.cameras.Cameras` take them, a vertical field of view and the canvas' aspect ratio.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from anisdf.data.cameras import Cameras
from anisdf.models.anisdf import AniSDFModel
from anisdf.models.views import map_to_image, render_rays_to_maps

FAR = 1000.0
"""Depth given to empty pixels, so that scene elements behind them (frustums, the mesh) stay visible."""


@dataclass(frozen=True)
class ViewCamera:
    """A pinhole view: camera-to-world pose (OpenCV axes), vertical field of view (radians), width / height."""

    c2w: np.ndarray
    fov_y: float
    aspect: float

    @classmethod
    def from_viser(cls, camera) -> ViewCamera:  # noqa: ANN001  (viser.CameraHandle; viser is an optional extra)
        from viser import transforms

        rot = transforms.SO3(np.asarray(camera.wxyz, dtype=np.float64)).as_matrix()
        pose = np.concatenate([rot, np.asarray(camera.position, dtype=np.float64)[:, None]], 1)
        return cls(pose, float(camera.fov), float(camera.aspect))

    def size(self, long_side: int) -> tuple[int, int]:
        """(height, width) of a picture whose longer side is ``long_side`` pixels."""
        if self.aspect >= 1.0:
            return max(1, round(long_side / self.aspect)), long_side
        return long_side, max(1, round(long_side * self.aspect))

    def cameras(self, long_side: int, device: torch.device) -> Cameras:
        h, w = self.size(long_side)
        f = 0.5 * h / math.tan(0.5 * self.fov_y)
        one = torch.ones(1)
        return Cameras(c2w=torch.as_tensor(self.c2w, dtype=torch.float32)[None], fx=one * f, fy=one * f,
                       cx=one * (w / 2), cy=one * (h / 2), width=w, height=h).to(device)


@dataclass
class Frame:
    """A rendered picture with its camera-space depth (for compositing with the 3D scene) and its cost."""

    image: np.ndarray
    """[H, W, 3] uint8."""
    depth: np.ndarray
    """[H, W] float32 distance along the view axis; :data:`FAR` where nothing was hit."""
    map: str
    """The map shown: the one asked for, or rgb when the model has none such."""
    seconds: float
    rays: int


def render_frame(model: AniSDFModel, view: ViewCamera, long_side: int, map_name: str, chunk: int) -> Frame:
    """Render ``view`` with ``long_side`` pixels on its longer side on white, as the map ``map_name``."""
    t0 = time.perf_counter()
    device = next(model.parameters()).device
    origins, dirs = view.cameras(long_side, device).image_rays(0)
    hw = dirs.shape[:2]
    dirs = dirs.reshape(-1, 3)
    maps = render_rays_to_maps(model, origins.reshape(-1, 3), dirs, torch.ones_like(dirs), hw, chunk)
    try:
        image, shown = map_to_image(maps, map_name), map_name
    except KeyError:  # c_view, c_ref, w of a model without the blended appearance
        image, shown = map_to_image(maps, "rgb"), "rgb"
    cos = (dirs.cpu().numpy() @ view.c2w[:, 2]).reshape(hw)
    depth = np.where(maps["opacity"][..., 0] > 0.5, maps["depth"][..., 0] * cos, FAR).astype(np.float32)
    return Frame(image, depth, shown, time.perf_counter() - t0, int(dirs.shape[0]))
