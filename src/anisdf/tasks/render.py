"""Rendering a run's views with their maps, and an orbit video."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.options import int_at_least, option

log = logging.getLogger("anisdf")


@dataclass(kw_only=True)
class RenderOptions:
    """What ``anisdf render`` / :func:`render` renders."""

    split: str = option("test", "the split whose views are rendered")
    video: bool = option(False, "also write an orbit video (MP4)")
    max_views: int = option(0, "at most this many views (0: all)", int_at_least(0))
    downscale: int = option(1, "render at the training resolution divided by this", int_at_least(1))
    device: str | None = option(None, "auto | cpu | cuda[:N]")
    n_video_frames: int = option(60, "frames of the orbit video", int_at_least(2), cli=False)


def render(run: Path, options: RenderOptions | None = None, **changes: Any) -> Path:
    """Render every view of a split with its maps into RUN/renders/<split>/, and optionally an orbit video;
    ``changes`` replace fields of ``options``. Returns the folder of the renders."""
    from tqdm import tqdm

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.models.views import MAP_NAMES, map_to_image, render_view
    from anisdf.tasks.loading import load_run, scene_for_run
    from anisdf.utils.devices import pick_device
    from anisdf.utils.images import save_image

    o = dataclasses.replace(options or RenderOptions(), **changes)
    run = Path(run)
    dev = pick_device(o.device or "auto")
    cfg, model, ck = load_run(run, dev)
    scene = scene_for_run(run, cfg, ck)
    if not scene.splits.get(o.split):
        raise AnisdfError(f"split '{o.split}' is empty for {scene.root}; choose one of {sorted(scene.splits)}")
    data = RayDataset(scene, o.split, device=dev, background=eval_background(scene), downscale=o.downscale)
    n = len(data) if o.max_views <= 0 else min(o.max_views, len(data))
    out_dir = RunDir(run).renders(o.split)
    for i in tqdm(range(n), desc=f"render {o.split}", unit="view"):
        res = render_view(model, data, i, scene, cfg.renderer.eval_chunk_rays, fine_grid=True)
        for name in MAP_NAMES:
            key = "weight" if name == "w" else name
            if key in res["maps"]:
                save_image(out_dir / f"{i:03d}_{key}.png", map_to_image(res["maps"], name))
    if o.video:
        render_orbit(model, scene, cfg, RunDir(run).orbit_video, o.n_video_frames, o.downscale, dev)
    return out_dir


def render_orbit(model, scene, cfg, path: Path, n_frames: int, downscale: int, dev: torch.device) -> Path:
    """An orbit around the object at the train cameras' mean distance and elevation, with rgb | normal frames."""
    from tqdm import tqdm

    from anisdf.data.orbit import up_direction
    from anisdf.models.views import render_rays_to_maps
    from anisdf.utils.images import normal_to_image, to_uint8
    from anisdf.utils.video import orbit_poses, write_video

    cams = scene.cameras
    train_idx = scene.splits["train"]
    centres = cams.c2w[train_idx, :, 3]
    dist = float(centres.norm(dim=-1).mean())
    up = up_direction(cams.c2w[train_idx])
    elev = float(torch.rad2deg(torch.asin((centres / centres.norm(dim=-1, keepdim=True) @ up).mean().clamp(-1, 1))))
    poses = orbit_poses(n_frames, dist, elev, up=up.numpy(), look_at=(0.0, 0.0, 0.0))
    from anisdf.data.cameras import Cameras

    k = train_idx[0]  # borrow the intrinsics of a train camera
    orbit = Cameras(c2w=torch.as_tensor(np.asarray(poses), dtype=torch.float32),
                    fx=cams.fx[k].repeat(n_frames), fy=cams.fy[k].repeat(n_frames),
                    cx=cams.cx[k].repeat(n_frames), cy=cams.cy[k].repeat(n_frames),
                    width=cams.width, height=cams.height).to(dev)
    frames = []
    for i in tqdm(range(n_frames), desc="orbit video", unit="frame"):
        origins, dirs = orbit.image_rays(i, max(int(downscale), 1))
        hw = dirs.shape[:2]
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        maps = render_rays_to_maps(model, origins, dirs, torch.ones_like(dirs), hw, cfg.renderer.eval_chunk_rays,
                                   fine_grid=True)
        fg = maps["opacity"][..., 0:1] > 0.5
        frames.append(np.concatenate([to_uint8(maps["rgb"]), normal_to_image(maps["normal"] * fg)], axis=1))
    return write_video(frames, path)


