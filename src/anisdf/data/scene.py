"""The dataset-independent scene every parser produces (see :func:`anisdf.data.load_scene`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch import Tensor

from anisdf.data.cameras import Cameras

FORMATS = ("nerf-synthetic", "neus", "instant-ngp", "llff", "colmap")
RENDERED_FORMATS = ("nerf-synthetic",)
"""Formats of rendered scenes: exact cameras and one exposure. Every other format holds photos (NeuS/DTU, LLFF,
COLMAP, instant-ngp; process-data writes instant-ngp's transforms.json)."""


def capture_switch(value: str, fmt: str) -> bool:
    """An ``auto`` / ``on`` / ``off`` switch of what real photos need (``cameras.refine``, ``appearance.embedding``)
    resolved for a scene of format ``fmt``: auto is on for photos, off for rendered scenes."""
    return value == "on" or (value == "auto" and fmt not in RENDERED_FORMATS)


@dataclass
class Scene:
    """Images, cameras and splits of one dataset, in the normalised frame.

    The normalised frame is the dataset's frame moved by a similarity (uniform scale + translation, no
    rotation, so world normals stay valid) that puts the region of interest inside the unit sphere.
    ``to_world`` maps normalised coordinates back: ``x_dataset = to_world @ [x_norm, 1]``.
    """

    format: str
    root: Path
    image_paths: list[Path]
    images: Tensor
    """[N,H,W,3] uint8 straight (not premultiplied) RGB."""
    alpha: Tensor | None
    """[N,H,W] uint8 coverage from RGBA images, or None."""
    masks: Tensor | None
    """[N,H,W] uint8 (0 or 255) object masks from mask files, or None."""
    normals: dict[int, Tensor]
    """image index -> [H,W,4] float32 world unit normal xyz + coverage (reference normal maps)."""
    cameras: Cameras
    splits: dict[str, list[int]]
    """"train", "test" (and "val" when the dataset has one): indices into ``image_paths``."""
    background: str
    """"rgba" (images carry alpha; composite on a chosen colour) or "opaque" (photo background)."""
    to_world: np.ndarray
    """[4,4] similarity mapping normalised coordinates to the dataset's own frame."""
    scene_radius: float
    """Radius of the region of interest in dataset units (the unit sphere maps to it)."""
    warnings: list[str] = field(default_factory=list)
    roi_method: str = ""
    """How the region of interest was found: scale_mat | sparse-points (process-data) | visual-hull | camera-axes |
    forward-facing."""
    alpha_mode: str = ""
    """How the RGBA images held colour, with the evidence: ``straight (...)``, or ``premultiplied (...)`` (turned
    straight on loading; :mod:`anisdf.data.alpha`); empty without alpha."""
    downscale: float = 1.0
    """The factor the images were divided by (``data.downscale``, lowered by ``data.min_size``)."""

    @property
    def n_images(self) -> int:
        return len(self.image_paths)

    @property
    def height(self) -> int:
        return self.cameras.height

    @property
    def width(self) -> int:
        return self.cameras.width

    @property
    def scale(self) -> float:
        """Dataset units per normalised unit."""
        return float(self.to_world[0, 0])

    @property
    def center(self) -> np.ndarray:
        """Centre of the region of interest in the dataset frame."""
        return self.to_world[:3, 3].copy()

    def coverage(self) -> Tensor | None:
        """[N,H,W] uint8 object coverage: the mask files when present, else the alpha channel, else None."""
        return self.masks if self.masks is not None else self.alpha

    def to_dataset_frame(self, points: np.ndarray) -> np.ndarray:
        """Map normalised points ``[...,3]`` to the dataset's frame."""
        return points @ self.to_world[:3, :3].T + self.to_world[:3, 3]

    def to_normalised_frame(self, points: np.ndarray) -> np.ndarray:
        """Map dataset-frame points ``[...,3]`` to the normalised frame."""
        inv = np.linalg.inv(self.to_world)
        return points @ inv[:3, :3].T + inv[:3, 3]
