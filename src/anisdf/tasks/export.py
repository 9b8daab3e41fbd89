"""Baking a run into a real-time asset (model.glb, lobe textures, a WebGL page)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.export.baked_format import MAX_LOBES
from anisdf.run_dir import RunDir
from anisdf.tasks.loading import dataset_camera, dataset_up, scene_for_run
from anisdf.utils.options import count_at_least, float_at_least, int_at_least, option

if TYPE_CHECKING:
    from anisdf.export.bake import BakeOptions

log = logging.getLogger("anisdf")

_FACES, _TEXTURE = 200_000, 1024
"""Defaults of ``--faces`` and ``--texture`` (named here so that their help text reads them)."""


@dataclasses.dataclass(kw_only=True)
class ExportOptions:
    """``anisdf export``'s options (:func:`export`)."""

    faces: int = option(_FACES, f"triangle budget of the decimated mesh, e.g. 300k (default {_FACES // 1000}k)",
                        count_at_least(4))
    texture: int = option(_TEXTURE, f"diffuse texture size in texels ({_TEXTURE})", int_at_least(16))
    specular_texture: int = option(0, "lobe texture size in texels; 0: half of --texture", int_at_least(0))
    lobes: int = option(3, f"spherical Gaussian lobes per texel (0: diffuse only; at most {MAX_LOBES})",
                        int_at_least(0))
    directions: int = option(64, "reflected directions each texel's lobes are fitted to", int_at_least(4))
    resolution: int = option(512, "marching cubes resolution", int_at_least(16))
    supersample: int = option(2, "the page's default antialiasing: s x s samples per pixel (1-4; eval --baked uses it "
                                 "too)", int_at_least(1))
    pixel_filter: float = option(0.6, "sigma in pixels of the Gaussian that filters those samples into pixels (0: each "
                                      "pixel's own s x s box); 0.6 matches the path-traced training images best "
                                      "(benchmarks/RESULTS.md)", float_at_least(0.0))
    pbr: bool = option(False, "write the PBR asset of `anisdf materials` instead: model.glb with baseColorTexture and "
                              "metallicRoughnessTexture, light.hdr (the fitted light) and export.json")
    device: str | None = option(None, "auto (CUDA if available) | cpu | cuda[:N]")
    progress: bool = option(True, "show progress bars", cli=False)

    def bake_options(self) -> BakeOptions:
        """The :class:`anisdf.export.bake.BakeOptions` of these options."""
        from anisdf.export.bake import BakeOptions

        return BakeOptions(faces=self.faces, texture=self.texture, specular_texture=self.specular_texture,
                           lobes=self.lobes, directions=self.directions)

    def validate(self) -> None:
        """Raise an :class:`AnisdfError` naming the first option out of its range."""
        self.bake_options().validate()
        if not 1 <= self.supersample <= 4:
            raise AnisdfError(f"--supersample must be between 1 and 4, got {self.supersample}")
        if not 0.0 <= self.pixel_filter <= 2.0:
            raise AnisdfError(f"--pixel-filter must be between 0 and 2 pixels, got {self.pixel_filter}")


def _export_camera(run: Path, cfg, ck: dict[str, Any]) -> tuple[dict[str, Any] | None, list[float] | None]:
    """The page's first camera (the first test view, dataset frame) and the scene's up direction (the mean of the
    test cameras' up axes), or (None, None) when the dataset is not at hand."""
    try:
        scene = scene_for_run(run, cfg, ck, downscale=1.0, split="test")
    except AnisdfError as e:
        log.warning("export: %s; the page starts from a default view", e)
        return None, None
    split = scene.splits.get("test") or scene.splits.get("train") or [0]
    cam = dataset_camera(scene, split[0], ck).to_json()
    return cam, dataset_up(scene, ck, split).tolist()


def export(run: Path, out: Path, options: ExportOptions | None = None, **changes: Any) -> dict[str, Any]:
    """Bake RUN into a real-time asset in OUT (:mod:`anisdf.export.bake`): model.glb, specular_*.png, index.html and
    export.json (settings, file sizes, timings). ``changes`` replace fields of ``options``. Returns export.json's
    content. OUT's files are replaced together at the end; an export that fails leaves OUT as it was."""
    import time

    from anisdf import __version__
    from anisdf.export import baked_format as fmt
    from anisdf.export import require_bake_modules
    from anisdf.tasks.loading import load_run
    from anisdf.utils.devices import pick_device

    o = dataclasses.replace(options or ExportOptions(), **changes)
    rd, out = RunDir(run), Path(out)
    if out.exists() and not out.is_dir():
        raise AnisdfError(f"--out {out} is an existing file, not a folder")
    if out.resolve() == rd.root.resolve():
        raise AnisdfError("--out must not be the run folder itself")
    o.validate()
    require_bake_modules()
    if o.pbr:
        return _export_pbr(rd, out, o)
    from anisdf.export.asset_files import AssetFolder, write_asset
    from anisdf.export.bake import bake
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.export.sg_fit import SHARPNESS_RANGE

    opts = o.bake_options()
    dev = pick_device(o.device or "auto")
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def tick(name: str) -> None:
        now = time.perf_counter()
        timings[name] = round(now - clock[0], 2)
        clock[0] = now

    cfg, model, ck = load_run(rd.root, dev)
    if cfg.appearance.kind != "blend":
        log.info("export: appearance.kind=%s; the lobes are fitted to its colour all the same", cfg.appearance.kind)
    camera, up = _export_camera(rd.root, cfg, ck)
    tick("load")
    mesh = mc(model.geometry.distance, radius=model.radius, resolution=o.resolution, device=dev, progress=o.progress)
    tick("marching_cubes")
    baked = bake(model, mesh, opts, progress=o.progress, timer=tick)
    manifest: dict[str, Any] = {
        "format": fmt.FORMAT, "version": fmt.VERSION, "anisdf": __version__, "run": str(rd.root.resolve()),
        "step": int(ck["state"]["step"]), "frame": "dataset",
        "faces": len(baked.faces), "vertices": len(baked.vertices), "marching_cubes_resolution": o.resolution,
        "faces_requested": o.faces, "texture": opts.texture, "specular_texture": opts.spec_size,
        "lobes": opts.lobes, "directions": opts.directions, "diffuse_directions": opts.diffuse_directions,
        "fit_iters": opts.fit_iters, "sharpness_range": list(SHARPNESS_RANGE), "supersample": o.supersample,
        "pixel_filter": o.pixel_filter,
        "diffuse": "view-independent part of the blended colour w c_view + (1 - w) c_ref: the per-texel fit's "
                   "constant term (hemisphere mean with K = 0)",
        "up": up, "camera": camera, "stats": baked.stats,
    }
    with AssetFolder(out) as folder:
        sizes = write_asset(folder, baked, np.asarray(ck["to_world"]), manifest)
        tick("write")
        manifest.update(files=sizes, total_bytes=int(sum(sizes.values())), timings=timings,
                        seconds=round(sum(timings.values()), 2))
        folder.write(fmt.MANIFEST, (json.dumps(manifest, indent=2) + "\n").encode("utf-8"))
    log.info("export: %d faces, %d px diffuse, %d px lobes x %d -> %s (%.1f MB: %s) in %.0f s", len(baked.faces),
             opts.texture, opts.spec_size, opts.lobes, out, manifest["total_bytes"] / 1e6,
             ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sizes.items()), manifest["seconds"])
    return manifest


def _export_pbr(rd: RunDir, out: Path, o: ExportOptions) -> dict[str, Any]:
    """``--pbr``: the fitted material as glTF PBR textures (:mod:`anisdf.materials.pbr_asset`), the light beside, and
    the page that draws them under the fitted light, the bundled studio light or the user's own
    (:mod:`anisdf.materials.pbr_viewer`)."""
    import tempfile
    import time

    from anisdf import __version__
    from anisdf.config import config_from_dict
    from anisdf.export.asset_files import AssetFolder
    from anisdf.materials import pbr_asset
    from anisdf.materials.asset import load_fitted
    from anisdf.materials.environment import studio_light, write_env
    from anisdf.materials.pbr_viewer import PAGE, pbr_page_html
    from anisdf.training.checkpoint import load_checkpoint

    start = time.perf_counter()
    fitted = load_fitted(rd.root)
    ck = load_checkpoint(rd.checkpoint)
    camera, up = _export_camera(rd.root, config_from_dict(ck["config"]), ck)
    glb, stats = pbr_asset.bake_pbr(fitted, o.faces, o.texture)
    with tempfile.TemporaryDirectory() as tmp:
        light = write_env(Path(tmp) / pbr_asset.LIGHT, fitted.light.numpy()).read_bytes()
    manifest: dict[str, Any] = {"format": "anisdf-pbr", "anisdf": __version__, "run": str(rd.root.resolve()),
                                "frame": "dataset", "light_frame": "dataset, z up (equirectangular)",
                                "supersample": o.supersample, "pixel_filter": o.pixel_filter, "up": up,
                                "camera": camera, **stats}
    page = pbr_page_html(manifest, glb, {"estimated": fitted.light.numpy(), "studio": studio_light().numpy()})
    with AssetFolder(out, stale=()) as folder:
        sizes = {pbr_asset.GLB: folder.write(pbr_asset.GLB, glb), pbr_asset.LIGHT: folder.write(pbr_asset.LIGHT, light),
                 PAGE: folder.write(PAGE, page.encode("utf-8"))}
        manifest.update(files=sizes, total_bytes=int(sum(sizes.values())),
                        seconds=round(time.perf_counter() - start, 2))
        folder.write(pbr_asset.MANIFEST, (json.dumps(manifest, indent=2) + "\n").encode("utf-8"))
    log.info("export --pbr: %d faces, %d px textures -> %s (open %s in a browser)", stats["faces"], o.texture, out,
             out / PAGE)
    return manifest
