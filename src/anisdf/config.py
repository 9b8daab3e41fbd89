"""Dataclass configuration, YAML presets and ``key=value`` dotted overrides.

A run is described by one :class:`Config`. ``load_config("nerf-synthetic", ["geometry.kind=single"])``
starts from the defaults below, applies the preset file ``presets/<name>.yaml`` and then the
overrides, checking every key and converting every value to the field's type.
Defaults follow the paper (Sec. 4.1) and the authors' release (see NOTES.md).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from anisdf.errors import AnisdfError


@dataclass
class DataConfig:
    downscale: float = 1.0
    """Divide image width and height by this factor when loading."""
    background: str = "auto"
    """Training background for RGBA images: auto | white | black | random."""
    max_images: int = 0
    """Use at most this many training images (0 = all)."""
    train_split: str = "train"
    """train: the dataset's train split; all: every view, test views included (DTU, a geometry benchmark on which
    NeuS and the paper train on all 49 views)."""
    images_dir: str = ""
    """LLFF / COLMAP / NeuS: read images from this sub-folder instead of the default (e.g. ``images_4`` for the
    Mip-NeRF 360 outdoor scenes, ``images_2`` for the indoor ones); intrinsics follow the size on disk."""


@dataclass
class GeometryConfig:
    kind: str = "fused"
    """fused: coarse + fine hash grids in parallel (Sec. 3.2); single: one coarse-to-fine grid (ablation)."""
    n_levels: int = 16
    """L: number of levels of the fine grid (and of the single grid)."""
    coarse_levels: int = 10
    """m: the coarse grid holds levels 1..m, the fine grid levels m..L (Eq. 5); the fine grid starts with its first
    m levels active, so the fine set begins where the coarse set ends (the paper's "level m" ablation moves both)."""
    coarse_start_levels: int = 4
    """Active levels of the coarse grid (of the single grid with ``kind=single``) at the start."""
    level_start_step: int = 5000
    level_every: int = 1000
    """One more level on each grid every ``level_every`` steps after ``level_start_step`` (the first at
    ``level_start_step + level_every``): coarse 4 -> 10 and fine 10 -> 16, all active at step 11000 (NOTES.md)."""
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
    fusion: str = "sum"
    """sum (paper, Eq. 6) or mean (authors' release)."""
    normals: str = "analytic"
    """analytic (the exact gradient: closed form through the MLPs, autograd through the grids) or finite_difference
    (4-point tetrahedron, step fd_eps). Measured trade-off: benchmarks/RESULTS.md."""
    fd_eps: float = 0.0
    """Finite-difference step; <= 0 follows the cell size of the finest active level (Neuralangelo)."""
    encoding_backend: str = "auto"
    """auto | torch | fast: hash-grid implementation."""

    def per_level_scale(self) -> float:
        return math.exp(math.log(self.max_resolution / self.base_resolution) / max(self.n_levels - 1, 1))


@dataclass
class AppearanceConfig:
    kind: str = "blend"
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


@dataclass
class RendererConfig:
    radius: float = 1.0
    """Bounding sphere of the object in normalised coordinates."""
    grid_resolution: int = 128
    grid_update_every: int = 16
    grid_warmup_steps: int = 256
    occupancy_threshold: float = 0.01
    """A cell is empty when the NeuS density of any SDF value it can hold stays below this fraction of the density's
    peak: ``|sdf| > cell diagonal + ln(4 / threshold) / inv_s`` (the logistic density is ``<= 4 e^(-s|f|)`` of
    its peak)."""
    march_steps: int = 1024
    """Step size = sqrt(3) * 2 * radius / march_steps."""
    max_samples_per_ray: int = 1024
    variance_init: float = 0.3
    variance_scale: float = 10.0
    """inv_s = exp(variance_scale * variance)."""
    inv_s_max: float = 1e4
    cos_anneal_steps: int = 20000
    samples_per_step: int = 2**18
    min_rays: int = 256
    max_rays: int = 8192
    init_rays: int = 1024
    background_model: str = "nerf"
    """Opaque photos without masks, beyond the sphere: nerf (contracted hash-grid NeRF, Mip-NeRF 360 scenes) or
    environment (a colour per direction)."""
    background_samples: int = 32
    """Samples per ray of the background NeRF, uniform in disparity."""
    early_stop_eps: float = 1e-3
    """Samples whose transmittance (estimated by a cheap SDF-only pass) is below this are dropped; 0 = off."""
    color_weight_eps: float = 1e-4
    """The radiance heads run only on samples whose rendering weight exceeds this."""
    eval_chunk_rays: int = 4096


@dataclass
class LossConfig:
    rgb: str = "mse+l1"
    """mse | l1 | mse+l1."""
    eikonal: float = 0.1
    curvature: float = 1e-3
    curvature_ramp_steps: int = 5000
    """The curvature weight ramps linearly from 0 over these steps (release: Shiny 5k)."""
    curvature_decay: bool = False
    """After the ramp, divide the curvature weight by the per-level scale for every level switched on since the
    start (Neuralangelo; the release's DTU setting 'with decay')."""
    curvature_fraction: float = 0.25
    """Fraction of the step's samples (at least 1024) on which the curvature term is evaluated: it needs a second
    SDF query with gradients at perturbed points. Measured full vs subset: benchmarks/RESULTS.md."""
    orientation: float = 1e-3
    orientation_start: float = -1.0
    """Orientation weight at step 0, ramping linearly to ``orientation`` over ``orientation_ramp_steps``
    (release, Shiny Blender: 1e-2 -> 1e-3 over 20k steps); < 0: constant ``orientation``."""
    orientation_ramp_steps: int = 20000
    entropy: float = 1e-2
    """Binary cross-entropy of the accumulated opacity with itself (Eq. 17)."""
    mask: float = 0.0
    """BCE between accumulated opacity and the dataset mask (DTU-style), 0 = off."""
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
    """bf16 autocast of the radiance heads (CUDA only; the SDF is always float32). Off by default: the H100 profile
    found the step bound by kernel launches, not arithmetic (benchmarks/RESULTS.md); the heads' matrices are small
    and autocast adds about 130 cast kernels a step. The GPU A/B of this switch is still to be run."""
    compile: bool = False
    """``torch.compile`` the SDF MLPs (with their closed-form normals), the radiance heads and the NeuS opacity (not
    the hash grids, which have their own kernels), falling back to eager code with one warning. Meant for CUDA,
    where it fuses many small kernels of a launch-bound step; compiling costs about half a minute at start. On 2 CPU
    cores it made no measurable difference."""
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
    renderer: RendererConfig = field(default_factory=RendererConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


CHOICES: dict[str, tuple[str, ...]] = {
    "data.background": ("auto", "white", "black", "random"),
    "data.train_split": ("train", "all"),
    "geometry.kind": ("fused", "single"),
    "geometry.fusion": ("sum", "mean"),
    "geometry.normals": ("analytic", "finite_difference"),
    "renderer.background_model": ("nerf", "environment"),
    "geometry.encoding_backend": ("auto", "torch", "fast"),
    "appearance.kind": ("blend", "pe", "view"),
    "loss.rgb": ("mse", "l1", "mse+l1"),
}


def preset_names() -> list[str]:
    files = resources.files("anisdf").joinpath("presets").iterdir()
    return sorted(p.name[: -len(".yaml")] for p in files if p.name.endswith(".yaml"))


def _convert(value: Any, tp: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    try:
        if tp is bool:
            if isinstance(value, str):
                low = value.lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if tp is int:
            if isinstance(value, str) and "**" in value:
                base, exp = value.split("**")
                return int(base) ** int(exp)
            f = float(value)
            if f != int(f):
                raise ValueError(value)
            return int(f)
        if tp is float:
            return float(value)
        if tp is str:
            return str(value)
        if origin is tuple:
            if isinstance(value, str):
                value = yaml.safe_load(value.replace("(", "[").replace(")", "]"))
            args = typing.get_args(tp)
            if len(value) != len(args):
                raise ValueError(value)
            return tuple(_convert(v, a, key) for v, a in zip(value, args, strict=True))
        if origin in (types.UnionType, typing.Union):
            return value
    except (TypeError, ValueError):
        raise AnisdfError(f"config key '{key}': cannot read {value!r} as {getattr(tp, '__name__', tp)}") from None
    return value


def set_key(cfg: Config, key: str, value: Any) -> None:
    """Set a dotted ``key`` (e.g. ``geometry.n_levels``) with type conversion and validation."""
    parts = key.split(".")
    obj: Any = cfg
    for p in parts[:-1]:
        if not dataclasses.is_dataclass(obj) or not hasattr(obj, p):
            raise AnisdfError(f"unknown config key '{key}'")
        obj = getattr(obj, p)
    name = parts[-1]
    fields = {f.name: f for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else {}
    if name not in fields or dataclasses.is_dataclass(getattr(obj, name)):
        raise AnisdfError(f"unknown config key '{key}' (see `anisdf train --help-config`)")
    hints = typing.get_type_hints(type(obj))
    converted = _convert(value, hints[name], key)
    if key in CHOICES and converted not in CHOICES[key]:
        raise AnisdfError(f"config key '{key}' must be one of {', '.join(CHOICES[key])}, not {converted!r}")
    setattr(obj, name, converted)


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def apply_dict(cfg: Config, d: dict[str, Any]) -> Config:
    for key, value in _flatten(d).items():
        if key == "preset":
            cfg.preset = str(value)
            continue
        set_key(cfg, key, value)
    return cfg


def load_config(preset: str | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the preset (a name or a YAML path), then ``key=value`` overrides."""
    cfg = Config()
    if preset and preset != "default":
        path = Path(preset)
        if path.suffix in (".yaml", ".yml"):
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
            raise AnisdfError(f"preset {preset}: invalid YAML ({e})") from None
        apply_dict(cfg, data)
        cfg.preset = path.stem if path.suffix in (".yaml", ".yml") else preset
    for item in overrides or []:
        if "=" not in item:
            raise AnisdfError(f"override '{item}' is not of the form key=value")
        key, value = item.split("=", 1)
        set_key(cfg, key.strip(), yaml.safe_load(value) if value.strip() else value)
    return cfg


def config_from_dict(d: dict[str, Any]) -> Config:
    """Rebuild a config saved with :meth:`Config.to_dict` (e.g. from a checkpoint)."""
    return apply_dict(Config(), d)
