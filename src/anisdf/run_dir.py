"""The run folder: the one place that knows its layout.

A run folder (``anisdf train DATA --out RUN``) holds::

    config.yaml            the resolved configuration
    run.json               dataset path and format, preset, normalisation, status, step
    checkpoints/last.pt    the last checkpoint (atomic; --resume continues from it)
    log.jsonl, tb/         training log (one JSON line per logged step) and TensorBoard events
    val/                   validation panels written during training, their PSNR in val/psnr.jsonl
    mesh.<ply|obj|glb>     extract-mesh's mesh, with its settings in mesh.json
    eval.json, eval/       eval's figures and panels; report.html / report.md
    renders/<split>/       render's images; renders/orbit.mp4
    refined_cameras.json   the training cameras as given and as refined (cameras.refine), the dataset's frame
    job.json               a batch / reproduce runner's record of its attempts
    materials/             anisdf materials: surface.ply, fit.pt (the fit, resumable), light.hdr, materials.json
    relight/<light>/       eval --relight's renders under each light

Every module that reads or writes these goes through :class:`RunDir`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from anisdf.errors import AnisdfError
from anisdf.utils.atomic import write_text_atomic

MESH_FORMATS = ("ply", "obj", "glb")


@dataclass(frozen=True)
class RunDir:
    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    # ------------------------------------------------------------------------------------------ layout
    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def info(self) -> Path:
        return self.root / "run.json"

    @property
    def checkpoint(self) -> Path:
        return self.root / "checkpoints" / "last.pt"

    @property
    def log(self) -> Path:
        return self.root / "log.jsonl"

    @property
    def tensorboard(self) -> Path:
        return self.root / "tb"

    def validation_image(self, step: int) -> Path:
        return self.root / "val" / f"step_{step:06d}.png"

    @property
    def validation_log(self) -> Path:
        """One JSON line per validation: ``{"step", "time", "val_psnr"}`` (the first test view's PSNR)."""
        return self.root / "val" / "psnr.jsonl"

    def mesh(self, fmt: str = "ply") -> Path:
        return self.root / f"mesh.{fmt}"

    @property
    def mesh_info(self) -> Path:
        return self.root / "mesh.json"

    @property
    def eval_json(self) -> Path:
        return self.root / "eval.json"

    @property
    def eval_images(self) -> Path:
        return self.root / "eval"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    @property
    def report_md(self) -> Path:
        return self.root / "report.md"

    def renders(self, split: str) -> Path:
        return self.root / "renders" / split

    @property
    def orbit_video(self) -> Path:
        return self.root / "renders" / "orbit.mp4"

    @property
    def job(self) -> Path:
        return self.root / "job.json"

    @property
    def refined_cameras(self) -> Path:
        """The training cameras as given and as refined (``cameras.refine``), in the dataset's frame."""
        return self.root / "refined_cameras.json"

    @property
    def materials(self) -> Path:
        """``anisdf materials``'s folder."""
        return self.root / "materials"

    @property
    def materials_surface(self) -> Path:
        """The surface the material lives on (dataset frame, with vertex normals)."""
        return self.materials / "surface.ply"

    @property
    def materials_visibility(self) -> Path:
        """The surface's vertex visibility of the light's directions (``anisdf materials --shadows``)."""
        return self.materials / "visibility.pt"

    @property
    def materials_checkpoint(self) -> Path:
        """The material and light fit (atomic; a later ``anisdf materials`` continues from it)."""
        return self.materials / "fit.pt"

    @property
    def materials_light(self) -> Path:
        """The fitted light, an equirectangular map in the dataset's frame."""
        return self.materials / "light.hdr"

    @property
    def materials_info(self) -> Path:
        return self.materials / "materials.json"

    def relight(self, light: str) -> Path:
        """eval --relight's renders under ``light``."""
        return self.root / "relight" / light

    # ------------------------------------------------------------------------------------------ reading
    def has_checkpoint(self) -> bool:
        return self.checkpoint.is_file()

    def read_info(self) -> dict[str, Any] | None:
        """run.json's content, or None when the run has none yet (or it cannot be read)."""
        try:
            return json.loads(self.info.read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def status(self) -> str | None:
        """``running``, ``done`` or ``interrupted`` as run.json says, None before the first write."""
        info = self.read_info()
        return None if info is None else info.get("status")

    def data_path(self, checkpoint: dict[str, Any] | None = None) -> Path:
        """The dataset this run was trained on (run.json, else the checkpoint's record); an error when it is gone."""
        info = self.read_info()
        data = (info or {}).get("data") or (checkpoint or {}).get("data")
        if not data or not Path(data).exists():
            raise AnisdfError(f"{self.root}: the dataset this run was trained on ({data}) is no longer there")
        return Path(data)

    def read_mesh_info(self) -> dict[str, Any] | None:
        """mesh.json (what extract-mesh wrote and how), None when there is none; an error when it is unreadable."""
        if not self.mesh_info.is_file():
            return None
        try:
            info = json.loads(self.mesh_info.read_text())
            str(info["mesh"])
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise AnisdfError(f"{self.mesh_info}: unreadable ({e}); pass --re-extract to write a new mesh") from None
        return info

    def existing_mesh(self) -> Path | None:
        """The mesh mesh.json names, else any mesh.<fmt> present, else None."""
        try:
            info = self.read_mesh_info()
        except AnisdfError:
            info = None
        if info is not None and (self.root / str(info["mesh"])).is_file():
            return self.root / str(info["mesh"])
        return next((p for p in (self.mesh(f) for f in MESH_FORMATS) if p.is_file()), None)

    def read_eval(self) -> dict[str, Any] | None:
        try:
            return json.loads(self.eval_json.read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def read_refined_cameras(self) -> dict[str, Any] | None:
        """refined_cameras.json, None when the run refines no camera (or it cannot be read)."""
        try:
            return json.loads(self.refined_cameras.read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def eval_panels(self) -> list[Path]:
        return sorted(self.eval_images.glob("*.png"))

    # ------------------------------------------------------------------------------------------ writing
    def write_json(self, path: Path, content: dict[str, Any]) -> Path:
        """Write ``content`` as JSON to ``path`` (one of this folder's files) atomically."""
        return write_text_atomic(path, json.dumps(content, indent=2) + "\n")

    def write_info(self, content: dict[str, Any]) -> Path:
        return self.write_json(self.info, content)

    def write_config(self, config: dict[str, Any]) -> Path:
        import yaml

        return write_text_atomic(self.config, yaml.safe_dump(config, sort_keys=False))

    def write_mesh_info(self, content: dict[str, Any]) -> Path:
        return self.write_json(self.mesh_info, content)

    def write_eval(self, content: dict[str, Any]) -> Path:
        return self.write_json(self.eval_json, content)

    def write_refined_cameras(self, content: dict[str, Any]) -> Path:
        return self.write_json(self.refined_cameras, content)
