"""Training a run, or resuming one: the configuration it goes on with and the preset ``auto`` picks."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch

from anisdf.config import Config, config_from_dict, load_config, set_key
from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")

def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _resume_config(out: Path, saved: Config, preset: str | None, overrides: list[str]) -> Config:
    """The config a resumed run goes on with: its own (``config.yaml``), with any ``train.*`` overrides applied.

    ``--preset`` and other overrides may be repeated on ``--resume`` as long as they give the settings the run
    already has; a setting outside ``train.*`` that would change is an error naming the key. (``train.*`` values of
    the named preset are not compared: the run's budget and schedule stand unless a ``train.*`` override changes
    them.)
    """
    train_items = [o for o in overrides if o.partition("=")[0].strip().startswith("train.")]
    other = [o for o in overrides if o not in train_items]
    if preset:
        wanted = load_config(preset, other)
    else:
        wanted = config_from_dict(saved.to_dict())
        for item in other:
            key, eq, value = item.partition("=")
            if not eq:
                raise AnisdfError(f"override '{item}' is not of the form key=value")
            set_key(wanted, key.strip(), value)
    have, want = _flat(saved.to_dict()), _flat(wanted.to_dict())
    for key, value in want.items():
        if not key.startswith("train.") and have.get(key) != value:
            raise AnisdfError(f"--resume: {key} is {have.get(key)!r} in {out / 'config.yaml'}, the given preset and "
                              f"overrides make it {value!r}; only train.* settings may change on --resume")
    cfg = config_from_dict(saved.to_dict())
    for item in train_items:
        key, _, value = item.partition("=")
        set_key(cfg, key.strip(), value)
    return cfg


AUTO_PRESETS = {"object": "nerf-synthetic", "unbounded": "mipnerf360"}
"""``--preset auto``: the paper's preset for the kind of data (objects: images with alpha or masks; unbounded: opaque
photos without masks, whose surroundings the background field carries)."""


def data_kind(data: Path) -> str:
    """``object`` when the dataset has masks or images with transparent pixels, else ``unbounded``; reads the
    cameras and the first image only."""
    from PIL import Image

    from anisdf.data.dataparsers import parse_dataset

    parsed = parse_dataset(data)
    if parsed.mask_paths:
        return "object"
    with Image.open(parsed.image_paths[0]) as im:
        if "A" in im.getbands() and im.getchannel("A").getextrema()[0] < 255:
            return "object"
    return "unbounded"


def auto_preset(data: Path) -> tuple[str, list[str]]:
    """The preset ``--preset auto`` picks for ``data`` and the overrides it needs, said in the log."""
    kind = data_kind(data)
    preset, extra = AUTO_PRESETS[kind], []
    # Mip-NeRF 360's preset reads images_4 as the paper does; a capture without that folder keeps its own images
    images_dir = load_config(preset).data.images_dir
    if images_dir and not (data / images_dir).is_dir():
        extra.append("data.images_dir=")
    why = ("images with alpha or masks: an object" if kind == "object"
           else "opaque photos without masks: an unbounded scene, the background field learns the surroundings")
    log.info("preset auto: %s (%s)%s", preset, why,
             "; on a CPU, --preset cpu-quick trains in 10 minutes" if not torch.cuda.is_available() else "")
    return preset, extra


def train(data: Path, out: Path, preset: str | None = None, overrides: list[str] | None = None,
          max_steps: int | None = None, max_minutes: float | None = None, device: str | None = None,
          resume: bool = False, progress: bool = True, viewer_port: int | None = None,
          viewer_host: str = "127.0.0.1") -> dict[str, Any]:
    """Train a run (``resume``: continue it); with ``viewer_port`` also serve it live in the browser (viewer/) between
    steps (rank 0 only). Under torchrun every rank calls this and joins the job (training/distributed.py); the summary
    is the same on every rank."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.training import distributed
    from anisdf.training.checkpoint import load_checkpoint
    from anisdf.training.trainer import Trainer
    from anisdf.utils.devices import pick_device

    ckpt_path = out / "checkpoints" / "last.pt"
    ck = None
    if resume:
        ck = load_checkpoint(ckpt_path)
        cfg = _resume_config(out, config_from_dict(ck["config"]), None if preset == "auto" else preset,
                             overrides or [])
    else:
        if ckpt_path.exists():
            raise AnisdfError(f"{out}: already holds a run; pass --resume to continue it or choose another --out")
        extra: list[str] = []
        if preset == "auto":
            preset, extra = auto_preset(data)
        cfg = load_config(preset, [*extra, *(overrides or [])])
    if max_steps:
        cfg.train.max_steps = max_steps
        if max_minutes is None and not resume:  # `--max-steps N` alone asks for N steps, not the preset's budget
            cfg.train.max_minutes = 0.0
    if max_minutes is not None:
        cfg.train.max_minutes = max_minutes
    ctx = distributed.init_from_env(device or cfg.train.device)
    dev = ctx.device if ctx is not None else pick_device(device or cfg.train.device)
    viewer = None
    try:
        scene = load_scene(data, downscale=cfg.data.downscale, max_images=cfg.data.max_images,
                           images_dir=cfg.data.images_dir)
        if ctx is None or ctx.is_main:
            for w in scene.warnings:
                log.warning("warning: %s", w)
        trainer = Trainer(cfg, scene, out, dev, progress=progress, dist=ctx)
        if ck is not None:
            trainer.load_state_dict(ck)
            if trainer.is_main:
                log.info("resuming %s at step %d", out, trainer.state.step)
        if viewer_port is not None and trainer.is_main:
            from anisdf.viewer import Viewer

            viewer = Viewer(trainer.model, scene, port=viewer_port, host=viewer_host, live=True,
                            title=f"anisdf · {out.name} (training)")
            trainer.step_hooks.append(viewer.on_step)
            print(viewer.announce(), flush=True)
        return trainer.fit()
    finally:
        if viewer is not None:
            viewer.close()
        distributed.shutdown(ctx)


