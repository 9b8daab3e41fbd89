"""Orbit camera paths and video writing (MP4 through imageio-ffmpeg, GIF as the fallback)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import imageio.v2 as imageio_v2
import imageio.v3 as iio
import numpy as np
import torch

from anisdf.errors import AnisdfError
from anisdf.utils.atomic import atomic_path
from anisdf.utils.images import to_rgb_uint8

_UP = {
    "x": (1.0, 0.0, 0.0),
    "y": (0.0, 1.0, 0.0),
    "z": (0.0, 0.0, 1.0),
    "-x": (-1.0, 0.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "-z": (0.0, 0.0, -1.0),
}


def _prepare_frames(frames: Sequence[np.ndarray]) -> list[np.ndarray]:
    if len(frames) == 0:
        raise AnisdfError("write_video: no frames to write")
    out = [to_rgb_uint8(f) for f in frames]
    shape = out[0].shape
    for i, f in enumerate(out):
        if f.shape != shape:
            raise AnisdfError(f"write_video: frame {i} has shape {f.shape}, frame 0 has {shape}")
    return out


def _write_mp4(frames: list[np.ndarray], path: Path, fps: float) -> None:
    h, w = frames[0].shape[:2]
    ph, pw = h % 2, w % 2  # libx264 with yuv420p needs even sizes: pad with white
    with atomic_path(path) as tmp:
        writer = imageio_v2.get_writer(
            tmp,
            format="FFMPEG",
            mode="I",
            fps=fps,
            codec="libx264",
            quality=8,
            pixelformat="yuv420p",
            macro_block_size=1,
            ffmpeg_log_level="error",
        )
        try:
            for f in frames:
                if ph or pw:
                    f = np.pad(f, ((0, ph), (0, pw), (0, 0)), constant_values=255)
                writer.append_data(f)
        finally:
            writer.close()


def write_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 24) -> Path:
    """Write frames (uint8 or float [0, 1], HxWx3/4/HxW, all one size) as an MP4 at ``path``, atomically.

    If MP4 writing fails (no ffmpeg, codec error), a GIF is written next to it (``path`` with suffix
    .gif) with a warning. Returns the path actually written.
    """
    path = Path(path)
    rgb = _prepare_frames(frames)
    if path.suffix.lower() != ".gif":
        try:
            _write_mp4(rgb, path, fps)
            return path
        except Exception as e:  # imageio/ffmpeg raise assorted types
            path = path.with_suffix(".gif")
            warnings.warn(
                f"MP4 writing failed ({type(e).__name__}: {e}); writing {path} instead", stacklevel=2
            )
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, np.stack(rgb), extension=".gif", duration=1000.0 / fps, loop=0)
    return path


def _up_vector(up: str | Sequence[float] | np.ndarray) -> np.ndarray:
    if isinstance(up, str):
        if up not in _UP:
            raise ValueError(f"up must be one of {sorted(_UP)} or a 3-vector, got {up!r}")
        v = np.array(_UP[up])
    else:
        v = np.asarray(up, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not n > 0:
        raise ValueError("the up vector must be non-zero")
    return v / n


def orbit_poses(
    n_frames: int,
    radius: float,
    elevation_deg: float,
    up: str | Sequence[float] | np.ndarray = "z",
    look_at: Sequence[float] = (0.0, 0.0, 0.0),
    start_azimuth_deg: float = 0.0,
) -> torch.Tensor:
    """Camera-to-world poses [n, 3, 4] (float32) on a circular orbit, OpenCV convention.

    Camera axes: x right, y down, z forward (towards ``look_at``). The cameras sit at distance
    ``radius`` from ``look_at``, ``elevation_deg`` above the plane orthogonal to ``up``, at azimuths
    ``start_azimuth_deg + 360 * i / n`` (counter-clockwise seen from above, i.e. around ``up``).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be at least 1, got {n_frames}")
    if abs(elevation_deg) >= 89.9:
        raise ValueError(
            "elevation must be strictly between -89.9 and 89.9 degrees (the view would be along up)"
        )
    u = _up_vector(up)
    target = np.asarray(look_at, dtype=np.float64).reshape(3)
    # an orthonormal basis (e1, e2, u) of the orbit
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - np.dot(helper, u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    el = math.radians(elevation_deg)
    poses = np.zeros((n_frames, 3, 4))
    for i in range(n_frames):
        az = math.radians(start_azimuth_deg) + 2.0 * math.pi * i / n_frames
        pos = target + radius * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * u)
        z = target - pos
        z /= np.linalg.norm(z)
        x = np.cross(z, u)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        poses[i, :, 0], poses[i, :, 1], poses[i, :, 2], poses[i, :, 3] = x, y, z, pos
    return torch.from_numpy(poses).to(torch.float32)
