"""The paper's quantitative tables (AniSDF, Gao et al., Sec. 4), and how ``anisdf reproduce`` recognises their scenes.

Every number below is copied from the paper's row "Ours" of each table (the table is named beside it). Units are those
our metrics report (``docs/evaluation.md``): PSNR in dB, normal MAE in degrees, NeRF-synthetic Chamfer in scene units
(the paper prints it in units of 1e-3, so 4.39 there is 0.00439 here), DTU Chamfer in millimetres (the official DTU
protocol, as the paper's Table 3).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from anisdf.errors import AnisdfError

METRICS = ("psnr", "ssim", "chamfer", "normal_mae_deg")
"""The metrics of a reproduce row (absent ones are null)."""

# Table 1 (label tab_syn): NeRF Synthetic, row "Ours". PSNR in dB; Chamfer printed in units of 1e-3.
_SYN_PSNR = {"chair": 35.31, "drums": 26.23, "ficus": 33.15, "hotdog": 37.99, "lego": 35.69, "materials": 31.87,
             "mic": 35.44, "ship": 31.69}
_SYN_CD_E3 = {"chair": 4.39, "drums": 5.24, "ficus": 2.75, "hotdog": 7.81, "lego": 5.16, "materials": 3.03,
              "mic": 5.34, "ship": 5.41}
_SYN_AVG = {"psnr": 33.42, "chamfer": 4.89e-3}

# Table 2 (label tab_shiny): Shiny Blender, row "Ours": (PSNR dB, normal MAE degrees).
_SHINY = {"helmet": (34.44, 0.41), "toaster": (26.98, 1.15), "coffee": (33.24, 1.14), "car": (29.56, 0.70)}
_SHINY_MEAN = {"psnr": 31.05, "normal_mae_deg": 0.85}

# Table 3 (label dtu): DTU, row "Ours", Chamfer distance in mm (official DTU evaluation).
_DTU_CD_MM = {24: 0.52, 37: 0.82, 40: 0.65, 55: 0.43, 63: 0.76, 65: 0.64, 69: 0.71, 83: 0.97, 97: 0.86, 105: 0.64,
              106: 0.52, 110: 0.67, 114: 0.42, 118: 0.67, 122: 0.50}
_DTU_MEAN = {"chamfer": 0.65}

# Table 5 (label tab_360): Mip-NeRF 360, row "Ours", PSNR dB. Outdoor scenes are evaluated on images_4, indoor ones on
# images_2 (the Mip-NeRF 360 protocol the paper follows; presets/mipnerf360.yaml).
_360_OUTDOOR = {"bicycle": 25.36, "flowers": 22.32, "garden": 27.65, "stump": 26.63, "treehill": 23.02}
_360_INDOOR = {"room": 31.30, "counter": 30.23, "kitchen": 31.69, "bonsai": 33.25}
_360_MEANS = {"outdoor": 24.99, "indoor": 31.62}

# Table 4 (label ab_tab): ablation on NeRF Synthetic, means over its 8 scenes (PSNR dB, Chamfer 1e-3 -> scene units).
# The paper gives no per-scene ablation numbers; per scene only the full model's (Table 1) are known.
_ABLATION_MEANS = {
    "full": {"psnr": 33.42, "chamfer": 4.89e-3},              # w/ ASG, w/ Fused (Ours)
    "no-asg": {"psnr": 32.38, "chamfer": 5.16e-3},            # w/o ASG, w/ Fused
    "no-fusion": {"psnr": 33.19, "chamfer": 5.37e-3},         # w/ ASG, w/o Fused
    "no-asg-no-fusion": {"psnr": 30.25, "chamfer": 5.64e-3},  # w/o ASG, w/o Fused
}
ABLATION_CONFIGS: dict[str, tuple[str, ...]] = {
    "full": (),
    "no-asg": ("appearance.kind=pe",),
    "no-fusion": ("geometry.kind=single",),
    "no-asg-no-fusion": ("appearance.kind=pe", "geometry.kind=single"),
}
"""The paper's four ablation configurations (Sec. 4.3) as config overrides: ASG replaced by a positional encoding of
the reflected direction, and the fused coarse + fine grids replaced by one coarse-to-fine grid."""


def _paper(source: str, **metrics: float) -> dict[str, float | str | None]:
    return {**{m: metrics.get(m) for m in METRICS}, "source": source}


@dataclass(frozen=True)
class PaperTable:
    """One of the paper's tables: its scenes with the paper's figures, the preset that trains them and the dataset
    formats its scene folders come in."""

    name: str
    source: str
    """Where the numbers come from, e.g. "Table 1 (NeRF Synthetic)"."""
    preset: str
    formats: tuple[str, ...]
    """Dataset formats (``anisdf.data.dataparsers.detect_format``) a scene of this table comes in."""
    scenes: dict[str, dict[str, float | str | None]]
    """Scene key -> the paper's figures (``METRICS`` keys, null where the paper gives none, plus ``source``)."""
    configs: dict[str, tuple[str, ...]] = field(default_factory=lambda: {"full": ()})
    """Configuration name -> config overrides; ``ablation`` has four, the others one."""
    means: dict[str, dict[str, float]] = field(default_factory=dict)
    """The paper's own means: per configuration (ablation), or per group of scenes ("all", "outdoor", "indoor")."""
    scene_overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Per-scene config overrides of the paper's protocol (Mip-NeRF 360 indoor scenes on images_2)."""
    chamfer_unit: str = "scene units"

    def scene_key(self, folder_name: str) -> str | None:
        """The paper's name of the scene in folder ``folder_name`` (case-insensitive; DTU folders such as
        ``dtu_scan65`` or ``scan65`` are ``scan65``), or None when the paper does not list it."""
        name = folder_name.lower()
        if self.name == "dtu":
            m = re.search(r"scan_?(\d+)$", name)
            name = f"scan{int(m.group(1))}" if m else name
        return name if name in self.scenes else None

    def paper_row(self, folder_name: str, config: str) -> dict[str, float | str | None] | None:
        """The paper's figures for one (scene, configuration) row, or None for a scene the paper does not list."""
        key = self.scene_key(folder_name)
        if key is None:
            return None
        if config == "full":
            return dict(self.scenes[key])
        # ablation: the paper gives only means over its scenes (Table 4), no per-scene figures
        return _paper(f"{self.source}: no per-scene figure (the paper gives the mean over its scenes only)")

    def overrides_for(self, folder_name: str) -> tuple[str, ...]:
        key = self.scene_key(folder_name)
        return self.scene_overrides.get(key, ()) if key else ()


def _syn_scenes(source: str) -> dict[str, dict[str, float | str | None]]:
    return {s: _paper(source, psnr=_SYN_PSNR[s], chamfer=round(_SYN_CD_E3[s] * 1e-3, 8)) for s in _SYN_PSNR}


TABLES: dict[str, PaperTable] = {
    "nerf-synthetic": PaperTable(
        "nerf-synthetic", "Table 1 (NeRF Synthetic)", "nerf-synthetic", ("nerf-synthetic",),
        _syn_scenes("Table 1"), means={"all": _SYN_AVG}),
    "shiny": PaperTable(
        "shiny", "Table 2 (Shiny Blender)", "shiny", ("nerf-synthetic",),
        {s: _paper("Table 2", psnr=p, normal_mae_deg=m) for s, (p, m) in _SHINY.items()},
        means={"all": _SHINY_MEAN}),
    "dtu": PaperTable(
        "dtu", "Table 3 (DTU)", "dtu", ("neus",),
        {f"scan{s}": _paper("Table 3", chamfer=cd) for s, cd in _DTU_CD_MM.items()},
        means={"all": _DTU_MEAN}, chamfer_unit="mm"),
    "mipnerf360": PaperTable(
        "mipnerf360", "Table 5 (Mip-NeRF 360)", "mipnerf360", ("colmap", "llff"),
        {s: _paper("Table 5", psnr=p) for s, p in {**_360_OUTDOOR, **_360_INDOOR}.items()},
        means={g: {"psnr": v} for g, v in _360_MEANS.items()},
        scene_overrides={s: ("data.images_dir=images_2",) for s in _360_INDOOR}),
    "ablation": PaperTable(
        "ablation", "Table 4 (ablation, NeRF Synthetic)", "nerf-synthetic", ("nerf-synthetic",),
        _syn_scenes("Table 1 (full model)"), configs=dict(ABLATION_CONFIGS), means=_ABLATION_MEANS),
}


def get_table(name: str) -> PaperTable:
    if name not in TABLES:
        raise AnisdfError(f"unknown table '{name}'; choose one of: {', '.join(TABLES)}")
    return TABLES[name]


def _scene_format(path: Path) -> str | None:
    from anisdf.data.dataparsers import detect_format
    from anisdf.errors import DataError

    try:
        return detect_format(path)
    except DataError:
        return None


def find_scenes(table: PaperTable, root: Path, only: list[str] | None = None) -> list[tuple[str, Path]]:
    """The scenes of ``table`` under ``root`` as (name, folder), recognised by their files (NeRF-synthetic
    ``transforms_train.json``, DTU ``cameras_sphere.npz``, COLMAP / LLFF poses for Mip-NeRF 360).

    ``root`` is either one scene folder (run whatever its name; a scene the paper does not list gets paper = null)
    or a dataset root whose sub-folders named as the paper's scenes are run. ``only`` picks sub-folders by name
    (the paper's or not)."""
    root = Path(root)
    if not root.is_dir():
        raise AnisdfError(f"{root}: --data must be a dataset root or a scene folder, and it does not exist")
    fmt = _scene_format(root)
    if fmt is not None:
        if fmt not in table.formats:
            raise AnisdfError(f"{root}: a {fmt} scene, but table {table.name} wants {' or '.join(table.formats)}")
        if only and root.name not in only:
            raise AnisdfError(f"{root}: --scenes {','.join(only)} does not name this scene folder ({root.name})")
        return [(root.name, root)]
    subdirs = sorted(p for p in root.iterdir() if p.is_dir())
    found = [(p.name, p) for p in subdirs if _scene_format(p) in table.formats]
    if only:
        missing = [s for s in only if s not in {n for n, _ in found}]
        if missing:
            raise AnisdfError(f"{root}: --scenes names no {table.name} scene folder called {', '.join(missing)}")
        return [(n, p) for n, p in found if n in only]
    ours = [(n, p) for n, p in found if table.scene_key(n) is not None]
    if not ours:
        held = ", ".join(n for n, _ in found) or "none"
        raise AnisdfError(f"{root}: holds no scene of {table.source} (looked for {', '.join(table.scenes)} in "
                          f"{' or '.join(table.formats)} format; scene folders found: {held}); pass one scene "
                          "folder as --data, or --scenes NAME,... to run others")
    return ours
