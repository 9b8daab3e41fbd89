"""Opening a trained run: its model, its dataset in the model's frame, its cameras in the dataset's frame."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.run_dir import RunDir

log = logging.getLogger("anisdf")


def model_from_checkpoint(cfg, ck: dict[str, Any], device: torch.device | str = "cpu"):
    """The model of checkpoint ``ck`` built with ``cfg`` (eval mode, at the checkpoint's step), with the parts it
    trained with: a background, and the per-image parts whose auto switches were resolved from the dataset's format
    (camera corrections, appearance codes; shapes from the checkpoint)."""
    from anisdf.models.anisdf import AniSDFModel

    sd = ck["model"]
    learn_bg = any(k.startswith("background.") for k in sd)
    trained = sd.get("cameras.trained", sd.get("image_codes.trained"))
    model = AniSDFModel(cfg, learn_background=learn_bg, trained=trained, camera_poses=sd.get("cameras.poses"),
                        image_codes="image_codes.codes" in sd).to(device)
    model.load_state_dict(sd)
    model.set_step(ck["state"]["step"])
    return model.eval()


def load_run(run: Path, device: torch.device | str = "cpu"):
    """Config, model (eval mode, at the checkpoint's step) and checkpoint dict of a trained run."""
    from anisdf.config import config_from_dict
    from anisdf.training.checkpoint import load_checkpoint

    torch.set_flush_denormal(True)
    ck = load_checkpoint(RunDir(run).checkpoint, map_location=device)
    cfg = config_from_dict(ck["config"])
    return cfg, model_from_checkpoint(cfg, ck, device), ck


def scene_for_run(run: Path, cfg, ck: dict[str, Any], downscale: float | None = None, split: str | None = None):
    """The run's dataset in the frame the model was trained in (the checkpoint's normalisation), at the training
    resolution or at ``downscale``, every view or only ``split``'s; training cameras as refined when the run refined
    them (RUN/refined_cameras.json)."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.models.per_image import apply_refined_cameras

    scene = load_scene(RunDir(run).data_path(ck), downscale=cfg.data.downscale if downscale is None else downscale,
                       max_images=cfg.data.max_images if split in (None, "train") else 0,
                       images_dir=cfg.data.images_dir, split=split, to_world=np.asarray(ck["to_world"]),
                       alpha=cfg.data.alpha)
    refined = RunDir(run).read_refined_cameras()
    if refined is not None:  # training cameras as refined (cameras.refine); test cameras have no correction
        n = apply_refined_cameras(scene, refined, np.asarray(ck["to_world"]))
        if n:
            log.info("%d training camera(s) as refined (%s)", n, RunDir(run).refined_cameras.name)
    return scene


def dataset_camera(scene, i: int, ck: dict[str, Any]):
    """Camera ``i`` of ``scene`` in the dataset's frame (where baked assets live), as the reference renderer takes
    it."""
    from anisdf.export.reference_renderer import PinholeCamera

    T = np.asarray(ck["to_world"], dtype=np.float64)
    cams = scene.cameras
    c2w = np.eye(4)
    c2w[:3, :4] = cams.c2w[i].double().cpu().numpy()
    c2w = T @ c2w
    c2w[:3, :3] /= np.cbrt(np.linalg.det(T[:3, :3]))
    dist = None if cams.distortion is None else cams.distortion[i].double().cpu().numpy()
    return PinholeCamera(c2w, float(cams.fx[i]), float(cams.fy[i]), float(cams.cx[i]), float(cams.cy[i]),
                         cams.width, cams.height, dist)


def dataset_up(scene, ck: dict[str, Any], views: list[int] | None = None) -> np.ndarray:
    """The cameras' up direction (:func:`~anisdf.data.orbit.up_direction` of ``views``, default all) turned into the
    dataset's frame, where meshes and baked assets live."""
    from anisdf.data.orbit import up_direction

    c2w = scene.cameras.c2w if views is None else scene.cameras.c2w[views]
    up = np.asarray(ck["to_world"], dtype=np.float64)[:3, :3] @ up_direction(c2w.double().cpu()).numpy()
    return up / np.linalg.norm(up)
