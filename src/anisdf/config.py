"""Run configuration: the dataclasses below are the schema; OmegaConf's structured configs do the rest.

A run is described by one :class:`Config`. ``load_config("nerf-synthetic", ["geometry.kind=single"])`` starts from
the defaults below and merges into them, with OmegaConf, the preset file ``presets/<name>.yaml`` and then the
``key=value`` overrides: OmegaConf rejects unknown keys, converts every value to its field's type and holds the
choices to their ``Literal`` types. The result is a plain :class:`Config` again (cheap to read, picklable). This
module adds only the spellings OmegaConf does not read (``2**18`` or ``1e3`` for an int, ``(0.9, 0.99)`` for a
tuple) and turns OmegaConf's errors into one-line :class:`AnisdfError` messages.
Defaults follow the paper (Sec. 4.1) and the authors' released code and configuration.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import operator
import re
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException, ValidationError

from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")

@dataclass
class DataConfig:
    downscale: float = 1.0
    """Divide image width and height by this factor when loading."""
    min_size: int = 0
    """Lower ``downscale`` (not below 1) so that the images' longer side keeps at least this many pixels; 0: off."""
    background: Literal["auto", "white", "black", "random"] = "auto"
    """Training background for RGBA images: auto | white | black | random."""
    alpha: Literal["auto", "straight", "premultiplied"] = "auto"
    """RGBA colour: straight, premultiplied in linear light (path tracers; read as straight), auto: told apart."""
    max_images: int = 0
    """Use at most this many training images (0 = all)."""
    train_split: Literal["train", "all"] = "train"
    """train: the dataset's train split; all: every view, test views included (DTU: NeuS and the paper use all 49)."""
    images_dir: str = ""
    """LLFF / COLMAP / NeuS: images from this sub-folder (Mip-NeRF 360: ``images_4`` outdoor, ``images_2`` indoor)."""
    roi_center: tuple[float, ...] = ()
    """Centre x,y,z of the region of interest (the sphere the scene is normalised to) in the dataset's own frame and
    units, overriding the automatic one (``anisdf inspect`` prints it); empty: found automatically."""
    roi_radius: float = 0.0
    """Radius of the region of interest in the dataset's units, overriding the automatic one (0: automatic)."""


@dataclass
class GeometryConfig:
    kind: Literal["fused", "single"] = "fused"
    """fused: coarse + fine hash grids in parallel (Sec. 3.2); single: one coarse-to-fine grid (ablation)."""
    n_levels: int = 16
    """L: number of levels of the fine grid (and of the single grid)."""
    coarse_levels: int = 10
    """m: the coarse grid holds levels 1..m; the fine grid holds levels 1..L, its first m active and all trainable
    from step 0 (the release's layout; Eq. 5 writes m..L). The paper's "level m" ablation moves both grids."""
    coarse_start_levels: int = 4
    """Active levels of the coarse grid (of the single grid with ``kind=single``) at the start."""
    level_start_step: int = 5000
    level_every: int = 1000
    """One more level on each grid every ``level_every`` steps after ``level_start_step`` (the first at its sum):
    coarse 4 -> 10 and fine 10 -> 16, all active at step 11000 (the release's schedule)."""
    features_per_level: int = 2
    log2_hashmap_size: int = 19
    base_resolution: int = 32
    max_resolution: int = 2048
    """Resolution of level L; the per-level scale is derived from it."""
    hidden_dim: int = 64
    n_hidden: int = 2
    feature_dim: int = 64
    """Size of the geometry feature F passed to the appearance heads."""
    init_radius: float = 0.5
    fusion: Literal["sum", "mean"] = "sum"
    """sum (paper, Eq. 6) or mean (authors' release)."""
    normals: Literal["analytic", "finite_difference"] = "analytic"
    """analytic (the exact gradient: closed form through the MLPs, autograd through the grids) or finite_difference
    (4-point tetrahedron, step fd_eps). Measured trade-off: benchmarks/RESULTS.md."""
    fd_eps: float = 0.0
    """Finite-difference step; <= 0 follows the cell size of the finest active level (Neuralangelo)."""
    encoding_backend: Literal["auto", "torch", "fast"] = "auto"
    """auto | torch | fast: hash-grid implementation."""

    def per_level_scale(self) -> float:
        return math.exp(math.log(self.max_resolution / self.base_resolution) / max(self.n_levels - 1, 1))


@dataclass
class AppearanceConfig:
    kind: Literal["blend", "pe", "view"] = "blend"
    """blend: view + ASG reflection + weight field (Sec. 3.3); pe: positional encoding of the reflected
    direction instead of ASG (ablation); view: view branch only (ablation)."""
    sh_degree: int = 4
    view_hidden: int = 64
    view_layers: int = 2
    weight_hidden: int = 64
    weight_layers: int = 1
    asg_theta: int = 8
    asg_phi: int = 16
    par_hidden: int = 128
    ref_hidden: int = 128
    ref_layers: int = 2
    pe_frequencies: int = 6
    embedding: Literal["auto", "on", "off"] = "auto"
    """Something learned per training image that absorbs what changes from photo to photo (auto exposure, white
    balance, lighting), of kind ``embedding_kind``. auto: on for real photos (NeuS/DTU, LLFF, COLMAP, instant-ngp,
    process-data), off for rendered scenes and in the dtu and mipnerf360 presets (the paper). Views without their own
    (test views, orbits, exports) use the training images' mean. benchmarks/RESULTS.md, "Per-image appearance"."""
    embedding_kind: Literal["code", "affine", "gain"] = "gain"
    """code: a code the radiance heads take as an extra input (NeRF-W); affine: a colour transform of the image's
    rendering, ``c' = c + M c + b`` (12 numbers); gain: ``c' = c exp(g)``, a gain a channel (3 numbers)."""
    embedding_dim: int = 16  # the code's size (embedding_kind=code)
    embedding_lr: float = 1e-2  # the codes' or transforms' learning rate (the scene's warm-up and decay)


@dataclass
class CamerasConfig:
    refine: Literal["auto", "on", "off"] = "auto"
    """Learn a small rigid correction (an se(3) vector, zero at the start) of every training camera with the scene.
    auto: on for photos (NeuS/DTU, LLFF, COLMAP, instant-ngp, process-data), off for rendered scenes and in the dtu
    and mipnerf360 presets, as the paper. dtu_scan65 with cameras 1 deg off: 19.8 -> 25.0 dB, 0.2 dB short of clean
    cameras (benchmarks/RESULTS.md). Test cameras are never corrected (eval fits those of refined runs)."""
    lr: float = 5e-4
    """Learning rate of the corrections (Adam, with the scene's warm-up and decay): 1e-3 and 2e-3 jittered the
    cameras more and ended further from the clean cameras' score (benchmarks/RESULTS.md)."""
    start_step: int = 100
    """The corrections are frozen at zero until this schedule step, while the scene takes a first shape."""
    reg: float = 1e-2
    """Weight of the penalty ``mean over training cameras of |xi|^2`` that keeps the corrections small."""
    anchor: bool = True
    """Take the rigid motion common to all the corrections out of them: moving every camera and the scene together
    changes no training photo but moves the scene away from the held-out cameras (models/per_image.py)."""


@dataclass
class RendererConfig:
    radius: float = 1.0
    """Bounding sphere of the object in normalised coordinates."""
    grid_resolution: int = 128
    grid_refine: int = 1
    """Training rays march the occupancy grid refined by this factor (occupancy_grid.refine_march_grid: occupied cells
    split, children that cannot reach the density band dropped; 1: the grid itself) where a refined cell spans at
    least two march steps; over 400k queries (``models/anisdf.GRID_REFINE_BUDGET``) refined a share at a time."""
    grid_refine_every: int = 4
    """Grid updates between full refinements (``grid_refine``); in between only emptied and filled cells change."""
    grid_update_every: int = 16
    grid_warmup_steps: int = 256
    occupancy_threshold: float = 0.01
    """A cell is empty when the NeuS density of any SDF value it can hold stays below this fraction of its peak:
    ``|sdf| > cell diagonal + ln(4 / threshold) / inv_s`` (the logistic density is ``<= 4 e^(-s|f|)`` of its peak)."""
    march_steps: int = 1024
    """Step size = sqrt(3) * 2 * radius / march_steps."""
    max_samples_per_ray: int = 1024
    variance_init: float = 0.3
    variance_scale: float = 10.0
    inv_s_max: float = 1e4
    """inv_s = exp(variance_scale * variance), kept <= inv_s_max by projecting the parameter after each step."""
    cos_anneal_steps: int = 20000
    background_model: Literal["nerf", "environment"] = "nerf"
    """Unmasked photos beyond the sphere: nerf (a contracted hash-grid NeRF) or environment (a colour a direction)."""
    background_samples: int = 32
    """Samples per ray of the background NeRF, uniform in disparity."""
    background_levels: int = 12
    background_log2_hashmap_size: int = 17
    """Hash-grid levels of the background NeRF and log2 of its table size a level (the release: 16 and 22)."""
    background_hidden: int = 64
    background_layers: int = 1
    """Width and hidden layers of each of the background NeRF's density and colour heads (the release: 2 layers)."""
    background_grid_resolution: int = 0
    """Cells a side of the background NeRF's occupancy grid over the contracted ball (0: none; the release's
    nerfacc grid: 128). With it, the heads run only on samples in cells where density was seen."""
    early_stop_eps: float = 1e-3
    """Samples whose transmittance (estimated by a cheap SDF-only pass) is below this are dropped; 0 = off."""
    prune_after_query_below: float = 0.1
    """After a training step that pruned less than this share of its samples, prune by the query's SDF (no pass)."""
    color_weight_eps: float = 1e-4
    """The radiance heads run only on samples whose rendering weight exceeds this."""
    eval_normal_band: float = 6.0
    """Images of a fixed model query the normal only where ``|sdf| inv_s`` is below this (0: at every sample); the
    other samples' opacity comes from the prune pass's SDF values (neus_renderer.estimated_alpha)."""
    eval_chunk_rays: int = 4096
    image_grid_resolution: int = 256
    """Images of a fixed model (eval, render, export) march the occupancy grid refined to at least this many cells a
    side (its occupied cells split, occupancy_grid.refined): fewer samples a ray. 0: the training grid."""


@dataclass
class LossConfig:
    rgb: Literal["mse", "l1", "mse+l1"] = "mse+l1"
    """mse | l1 | mse+l1."""
    eikonal: float = 0.1
    curvature: float = 1e-3
    curvature_ramp_steps: int = 5000
    """The curvature weight ramps linearly from 0 over these steps (release: Shiny 5k)."""
    curvature_decay: Literal["off", "levels", "exponential"] = "off"
    """After the ramp: off keeps the weight; levels divides it by the per-level scale for every level the fine (or
    single) grid has switched on since the start, so it stops decaying once the last level is on (Neuralangelo);
    exponential multiplies it by ``exp(-(t - ramp_steps) ln(per_level_scale) / level_every)`` for the whole run (the
    release's DTU setting). A boolean (older configs and checkpoints) reads as levels (true) or off (false)."""
    curvature_target: Literal["fused", "coarse"] = "fused"
    """The normal compared at the tangent-shifted point ``x + eps t``: fused (the fused field's, PermutoSDF's form) or
    coarse (the coarse branch's, the paper's fused-granularity form and the release's: it ties the fine grid to the
    coarse one, Sec. 3.2). The coarse target is not detached, as in the release: the loss trains both branches. With
    ``geometry.kind=single`` both read the one grid. The shiny and dtu presets use coarse, cpu-quick fused: at CPU
    scale the two are within the seed spread (benchmarks/RESULTS.md, "Curvature forms")."""
    curvature_form: Literal["squared", "angle"] = "squared"
    """squared: ``(n . n_eps - 1)^2`` (Eq. 15); angle: ``acos(n . n_eps) / pi`` (the release, after PermutoSDF)."""
    curvature_eps: Literal["finest", "mean_cells"] = "finest"
    """Tangent step: finest, the cell of the fine grid's finest active level; mean_cells, the mean of the coarse and
    fine grids' finest active cells (the release's intent; its code reads the coarse grid's level count for both, so
    its step is in effect the coarse grid's cell)."""
    curvature_fraction: float = 0.25
    """Fraction of the step's samples (at least 1024) given the curvature term's second SDF query (the paper: all). In
    cpu-quick's 10 minutes 1.0 ran 27% fewer steps and ended worse (benchmarks/RESULTS.md, 2026-12-02)."""
    orientation: float = 1e-3
    orientation_start: float = -1.0
    """Orientation weight at step 0, ramping linearly to ``orientation`` over ``orientation_ramp_steps``
    (release, Shiny Blender: 1e-2 -> 1e-3 over 20k steps); < 0: constant ``orientation``."""
    orientation_ramp_steps: int = 20000
    entropy: float = 1e-2
    """Binary cross-entropy of the accumulated opacity with itself (Eq. 17)."""
    mask: float = 0.0
    """BCE between accumulated opacity and the dataset mask (DTU-style), 0 = off."""
    interior: float = 0.0
    """Weight of the interior prior (anisdf's; model_components/interior.py): the SDF held below minus half the depth
    deep inside the object, where no ray reaches, so that no pocket there crosses zero. 0 = off."""
    interior_start: int = 500
    """Schedule step from which the interior prior applies; its depths are renewed at every 16th grid update."""
    explode_factor: float = 50.0
    """Stop when the loss exceeds this multiple of its running mean."""


@dataclass
class OptimConfig:
    lr: float = 1e-2
    lr_variance: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-15
    weight_decay: float = 0.01
    """AdamW's decoupled weight decay; the release passes none, so PyTorch's default 0.01 applies."""
    warmup_steps: int = 500
    final_lr_factor: float = 0.1


@dataclass
class TrainConfig:
    seed: int = 0
    max_steps: int = 20000
    max_minutes: float = 0.0
    """Time budget of the whole run in minutes (0 = none). With a budget the schedule (level activation, cos anneal,
    curvature and orientation ramps, learning-rate warm-up and decay) is laid on time: it advances with the fraction
    of the budget spent, ``max_steps`` names the schedule's length in its own units, and the run ends at the deadline
    with its schedule complete however fast the machine is. Without one it is laid on steps (bit-exact resume)."""
    device: str = "auto"
    amp: bool = False
    """bf16 autocast of the radiance heads (CUDA only; the SDF stays float32). Off: the H100 step was launch-bound,
    the heads small, and autocast adds ~130 cast kernels a step (benchmarks/RESULTS.md); no GPU A/B yet."""
    compile: bool = False
    """``torch.compile`` the SDF MLPs, radiance heads and NeuS opacity (not the hash grids), else eager with a warning.
    For CUDA's launch-bound step (about half a minute to compile); on 2 CPU cores no measurable difference."""
    samples_per_step: int = 2**18
    """Rays per step follow this sample budget (per rank): the step's ray count is scaled so that the shaded samples
    come to about this many (and the cheap pruning pass's to 4x)."""
    min_rays: int = 256
    max_rays: int = 8192
    init_rays: int = 1024
    log_every: int = 25
    val_every: int = 1000
    ckpt_every: int = 1000
    val_downscale: int = 2


@dataclass
class Config:
    preset: str = "default"
    data: DataConfig = field(default_factory=DataConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    renderer: RendererConfig = field(default_factory=RendererConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def preset_names() -> list[str]:
    files = resources.files("anisdf").joinpath("presets").iterdir()
    return sorted(p.name[: -len(".yaml")] for p in files if p.name.endswith(".yaml"))


_hints = functools.cache(typing.get_type_hints)


def _hint(key: str) -> Any:
    """The schema's type for a dotted key; None for an unknown key (OmegaConf reports it)."""
    tp: Any = Config
    for part in key.split("."):
        tp = _hints(tp).get(part) if dataclasses.is_dataclass(tp) else None
    return tp


OLD_VALUES: dict[str, dict[bool, str]] = {"loss.curvature_decay": {True: "levels", False: "off"},
                                          "cameras.refine": {True: "on", False: "off"},
                                          "appearance.embedding": {True: "on", False: "off"}}
"""Choices that also read a boolean: keys that were booleans (presets, overrides, checkpoints), and on / off switches
(YAML reads ``on`` and ``off`` as booleans)."""


def _spelling(value: Any, key: str) -> Any:
    """Spellings OmegaConf does not read for the value of ``key``: ``(a, b)`` or ``"[a, b]"`` for a tuple, ``2**18``,
    ``1e3`` or ``2.0`` for an int (any other float is left for OmegaConf to refuse), a boolean of :data:`OLD_VALUES`."""
    tp = _hint(key)
    old = _parse(value) if isinstance(value, str) and key in OLD_VALUES else value
    if isinstance(old, bool) and key in OLD_VALUES:
        return OLD_VALUES[key][old]
    if isinstance(value, str) and typing.get_origin(tp) is tuple:
        if re.fullmatch(r"\s*[(\[].*[)\]]\s*", value):
            return _parse("[" + value.strip()[1:-1] + "]")
        if "," in value:  # data.roi_center=0.1,0,-0.2
            return _parse("[" + value + "]")
    if tp is int and isinstance(value, str | float):
        base, power, exp = str(value).partition("**")
        try:
            number = float(base) ** int(exp) if power else float(value)
        except (ValueError, OverflowError):
            return value
        return int(number) if number.is_integer() else value
    return value


def _parse(text: str) -> Any:
    """An override's value as YAML reads it (``true``, ``64``, ``[0.9, 0.99]``), else the text itself."""
    try:
        return yaml.safe_load(text) if text.strip() else text
    except yaml.YAMLError:
        return text


def _prepare(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    return {k: _prepare(v, f"{prefix}{k}.") if isinstance(v, dict) else _spelling(v, f"{prefix}{k}")
            for k, v in d.items()}


@contextmanager
def _errors(where: str = "") -> Iterator[None]:
    """Turn OmegaConf's exceptions into one-line :class:`AnisdfError` messages naming the key."""
    try:
        yield
    except OmegaConfBaseException as e:
        key = e.full_key or ""
        tp = _hint(key) if key else None
        if isinstance(e, ConfigAttributeError | ConfigKeyError):
            msg = f"unknown config key '{key}'"
        elif dataclasses.is_dataclass(tp):
            msg = f"config key '{key}' is a section; set its keys, e.g. {key}.{dataclasses.fields(tp)[0].name}=..."
        elif typing.get_origin(tp) is Literal:
            msg = f"config key '{key}' must be one of {', '.join(typing.get_args(tp))}, not {e.value!r}"
        elif isinstance(e, ValidationError) and tp is not None:
            msg = f"config key '{key}': cannot read {e.value!r} as {tp.__name__ if isinstance(tp, type) else tp}"
        else:
            msg = f"config: {str(e).splitlines()[0]}"
        raise AnisdfError(where + msg) from None


def set_key(cfg: Config, key: str, value: Any) -> None:
    """Set a dotted ``key`` (e.g. ``geometry.n_levels``) of ``cfg`` in place, converted and checked by OmegaConf."""
    key = _moved(key)
    node = OmegaConf.structured(cfg)
    with _errors():
        OmegaConf.update(node, key, _spelling(value, key), merge=True)
    parent, _, name = key.rpartition(".")
    value = operator.attrgetter(key)(OmegaConf.to_object(node))
    setattr(operator.attrgetter(parent)(cfg) if parent else cfg, name, value)


MOVED_KEYS = {f"renderer.{k}": f"train.{k}" for k in ("samples_per_step", "min_rays", "max_rays", "init_rays")}
"""Keys that moved to the section that uses them; the old spelling is still read (presets, overrides, checkpoints)."""


def _moved(key: str, warn: bool = True) -> str:
    new = MOVED_KEYS.get(key, key)
    if warn and new != key:
        log.warning("config: %s is now %s", key, new)
    return new


def _move_sections(d: dict[str, Any], warn: bool) -> dict[str, Any]:
    """``d`` (sections of keys) with moved keys under their new section."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in d.items()}
    for old, new in MOVED_KEYS.items():
        (s_old, k_old), (s_new, k_new) = old.split("."), new.split(".")
        if isinstance(out.get(s_old), dict) and k_old in out[s_old]:
            out.setdefault(s_new, {})[k_new] = out[s_old].pop(k_old)
            if warn:
                log.warning("config: %s is now %s", old, new)
    return out


def load_config(preset: str | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the preset (a name or a YAML path), then ``key=value`` overrides, merged by OmegaConf."""
    node = OmegaConf.structured(Config)
    if preset and preset != "default":
        path = Path(preset)
        is_path = path.suffix in (".yaml", ".yml")
        if is_path:
            if not path.is_file():
                raise AnisdfError(f"{path}: preset file not found")
            text = path.read_text()
        else:
            names = preset_names()
            if preset not in names:
                raise AnisdfError(f"unknown preset '{preset}'; choose one of: {', '.join(names)}")
            text = resources.files("anisdf").joinpath("presets", f"{preset}.yaml").read_text()
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as e:
            raise AnisdfError(f"preset {preset}: invalid YAML ({' '.join(str(e).split())})") from None
        if not isinstance(data, dict):
            raise AnisdfError(f"preset {preset}: expected a mapping of config sections, not {type(data).__name__}")
        with _errors(f"preset {preset}: "):
            node = OmegaConf.merge(node, _prepare(_move_sections(data, warn=True)))
        node.preset = path.stem if is_path else preset
    for item in overrides or []:
        key, eq, value = item.partition("=")
        if not eq:
            raise AnisdfError(f"override '{item}' is not of the form key=value")
        key = _moved(key.strip())
        with _errors():
            OmegaConf.update(node, key, _spelling(_parse(value), key), merge=True)
    return typing.cast(Config, OmegaConf.to_object(node))


def config_from_dict(d: dict[str, Any]) -> Config:
    """Rebuild a config saved with :meth:`Config.to_dict` (e.g. from a checkpoint)."""
    with _errors():
        node = OmegaConf.merge(OmegaConf.structured(Config), _prepare(_move_sections(d, warn=False)))
    return typing.cast(Config, OmegaConf.to_object(node))
