"""Training a run, or resuming one: the configuration it goes on with, the preset ``auto`` picks, and the budget that
ends it."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from anisdf.config import Config, config_from_dict, load_config, preset_names, set_key
from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.utils.options import float_at_least, int_at_least, option, positional

if TYPE_CHECKING:
    from anisdf.training.trainer import Trainer

log = logging.getLogger("anisdf")

Setup = Callable[["Trainer"], Callable[[], None] | None]
"""``train(setup=...)``: called once on rank 0 with the Trainer before the first step (it may add to
``trainer.step_hooks``); the function it returns, if any, is called when training ends."""


@dataclass(kw_only=True)
class TrainOptions:
    """How ``anisdf train`` / :func:`train` trains a run (``preset=None``: the built-in defaults)."""

    preset: str | None = option(
        "auto", f"preset name ({', '.join(preset_names())}) or a YAML file; auto (default): nerf-synthetic for objects "
        "(alpha or masks), mipnerf360 for opaque photos without masks")
    overrides: list[str] = positional(
        "config overrides, e.g. geometry.kind=single appearance.kind=pe renderer.grid_resolution=64",
        metavar="key=value", nargs="*", default=[])
    max_steps: int | None = option(
        None, "train this many steps, with no time budget unless --max-minutes is given too (a preset's "
        "train.max_steps is the length of its schedule, laid on its time budget when it has one)", int_at_least(1))
    max_minutes: float | None = option(
        None, "stop cleanly and save after this many minutes of training in all (0: no limit)", float_at_least(0.0))
    device: str | None = option(None, "auto | cpu | cuda[:N]")
    resume: bool = option(False, "continue from RUN/checkpoints/last.pt")
    progress: bool = option(True, "show a progress bar", cli=False)


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _resume_config(out: Path, saved: Config, preset: str | None, overrides: list[str], data: Path) -> Config:
    """The config a resumed run goes on with: its own (``config.yaml``), with any ``train.*`` overrides applied.

    ``--preset`` and other overrides may be repeated on ``--resume`` as long as they give the settings the run
    already has; a setting outside ``train.*`` that would change is an error naming the key. (``train.*`` values of
    the named preset are not compared: the run's budget and schedule stand unless a ``train.*`` override changes
    them. ``data.downscale`` is compared as ``data.min_size`` makes it for ``data``'s images, as the run records it.)
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
    if wanted.data.min_size > 0 and wanted.data.downscale > 1.0:
        from anisdf.data.dataparsers import image_size_of
        from anisdf.data.images import capped_downscale

        size = image_size_of(data, wanted.data.images_dir)
        wanted.data.downscale = capped_downscale(*size, wanted.data.downscale, wanted.data.min_size)
    have, want = _flat(saved.to_dict()), _flat(wanted.to_dict())
    for key, value in want.items():
        if key in CAPTURE_SWITCHES and value == "auto":  # auto stands for what the run resolved it to
            continue
        if not key.startswith("train.") and have.get(key) != value:
            raise AnisdfError(f"--resume: {key} is {have.get(key)!r} in {RunDir(out).config}, the given preset and "
                              f"overrides make it {value!r}; only train.* settings may change on --resume")
    cfg = config_from_dict(saved.to_dict())
    for item in train_items:
        key, _, value = item.partition("=")
        set_key(cfg, key.strip(), value)
    return cfg


CAPTURE_SWITCHES = {"cameras.refine": "cameras.", "appearance.embedding": "image_codes."}
"""The ``auto`` switches of real photos and the prefix of the model parts they add (training/trainer.build_model)."""


def _settle_switches(cfg: Config, model_keys: list[str]) -> None:
    """A resumed run keeps the parts its checkpoint has: an ``auto`` switch of a run that trained without its part
    (a rendered scene, or a run from before the switch existed) is set off."""
    for key, prefix in CAPTURE_SWITCHES.items():
        section, name = key.split(".")
        if getattr(getattr(cfg, section), name) == "auto" and not any(k.startswith(prefix) for k in model_keys):
            set_key(cfg, key, "off")


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
    import torch

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


def _config(data: Path, out: Path, o: TrainOptions) -> tuple[Config, dict[str, Any] | None]:
    """The configuration the run trains with: the preset (or the saved one on resume), the overrides, then
    ``max_steps`` / ``max_minutes``; and the checkpoint it resumes from (None for a new run)."""
    from anisdf.training.checkpoint import load_checkpoint

    ckpt_path = RunDir(out).checkpoint
    ck = None
    if o.resume:
        ck = load_checkpoint(ckpt_path)
        cfg = _resume_config(out, config_from_dict(ck["config"]), None if o.preset == "auto" else o.preset,
                             o.overrides or [], data)
        _settle_switches(cfg, list(ck["model"]))
    else:
        if ckpt_path.exists():
            raise AnisdfError(f"{out}: already holds a run; pass --resume to continue it or choose another --out")
        preset, extra = o.preset, []
        if preset == "auto":
            preset, extra = auto_preset(data)
        cfg = load_config(preset, [*extra, *(o.overrides or [])])
    if o.max_steps:
        cfg.train.max_steps = o.max_steps
        if o.max_minutes is None and not o.resume:  # `--max-steps N` alone asks for N steps, not the preset's budget
            cfg.train.max_minutes = 0.0
    if o.max_minutes is not None:
        cfg.train.max_minutes = o.max_minutes
    return cfg, ck


def _say_budget(cfg: Config, o: TrainOptions) -> None:
    """Log which budget ends the run, and warn when a ``train.max_steps`` override reads as a step budget but names
    the length of a schedule laid on a time budget."""
    t = cfg.train
    if t.max_minutes > 0:
        hint = "" if o.max_steps else "; --max-steps N for a step count"
        log.info("budget: %g min (the schedule's %d steps laid on it)%s", t.max_minutes, t.max_steps, hint)
    else:
        log.info("budget: %d steps", t.max_steps)
    given = [v for k, _, v in (item.partition("=") for item in o.overrides or []) if k.strip() == "train.max_steps"]
    if given and t.max_minutes > 0 and not o.max_steps:
        steps = given[-1].strip()
        log.warning("warning: train.max_steps=%s sets the length of the schedule laid on the %g min time budget, not "
                    "a step budget; for %s steps pass --max-steps %s (or add train.max_minutes=0)", steps,
                    t.max_minutes, steps, steps)


def train(data: Path, out: Path, options: TrainOptions | None = None, *, setup: Setup | None = None,
          **changes: Any) -> dict[str, Any]:
    """Train a run into ``out`` (``resume``: continue it) and return its summary; ``changes`` replace fields of
    ``options``. ``setup`` (rank 0 only) sees the Trainer before the first step, e.g. to serve the model live in the
    browser, and may return a function called at the end. Under torchrun every rank calls this and joins the job
    (training/distributed.py); the summary is the same on every rank."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.training import distributed
    from anisdf.training.trainer import Trainer
    from anisdf.utils.devices import pick_device

    o = dataclasses.replace(options or TrainOptions(), **changes)
    data, out = Path(data), Path(out)
    cfg, ck = _config(data, out, o)
    ctx = distributed.init_from_env(o.device or cfg.train.device)
    dev = ctx.device if ctx is not None else pick_device(o.device or cfg.train.device)
    close: Callable[[], None] | None = None
    finished = False
    try:
        scene = load_scene(data, downscale=cfg.data.downscale, max_images=cfg.data.max_images,
                           images_dir=cfg.data.images_dir, roi_center=cfg.data.roi_center,
                           roi_radius=cfg.data.roi_radius, min_size=cfg.data.min_size, alpha=cfg.data.alpha)
        if scene.downscale != cfg.data.downscale and (ctx is None or ctx.is_main):
            log.info("images at %dx%d: downscale %g instead of %g (data.min_size=%d)", scene.width, scene.height,
                     scene.downscale, cfg.data.downscale, cfg.data.min_size)
        cfg.data.downscale = scene.downscale  # what was used (data.min_size), for eval and resume
        if ctx is None or ctx.is_main:
            for w in scene.warnings:
                log.warning("warning: %s", w)
            if scene.alpha_mode.startswith("premultiplied"):
                log.info("RGBA colour premultiplied in linear light, read as straight colour: %s", scene.alpha_mode)
            _say_budget(cfg, o)
        trainer = Trainer(cfg, scene, out, dev, progress=o.progress, dist=ctx)
        if ck is not None:
            trainer.load_state_dict(ck)
            if trainer.is_main:
                log.info("resuming %s at step %d", out, trainer.state.step)
        if setup is not None and trainer.is_main:
            close = setup(trainer)
        summary = trainer.fit()
        finished = True
        return summary
    finally:
        if close is not None:
            close()
        distributed.shutdown(ctx, finished=finished)
