"""Evaluating a run: PSNR, SSIM, normal MAE on a split, Chamfer against a reference mesh, a baked asset's scores
(:mod:`.scoring`), the record of how they were measured (:mod:`.protocol`) and the report a user opens
(:mod:`.report`)."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.eval.metrics import CHAMFER_POINTS
from anisdf.run_dir import RunDir
from anisdf.tasks.evaluate.appearance import PROTOCOLS as APPEARANCE_PROTOCOLS
from anisdf.tasks.evaluate.view_cameras import PROTOCOLS as CAMERA_PROTOCOLS
from anisdf.tasks.mesh import MeshOptions
from anisdf.utils.options import float_at_least, int_at_least, option

log = logging.getLogger("anisdf")

NORMAL_MASKS = ("refnerf", "alpha")
"""Pixel weights of the normal MAE: refnerf = rendered opacity x ground-truth alpha (Ref-NeRF's eval.py),
alpha = ground-truth alpha alone (holes in the render count in full)."""

_MESH_NOTE = "; the mesh extract-mesh wrote is scored as it is, this must match it (or pass --re-extract)"


@dataclass(kw_only=True)
class EvalOptions:
    """What ``anisdf eval`` scores and how (docs/evaluation.md)."""

    split: str = option("test", "the split whose views are scored")
    max_views: int = option(0, "at most this many views (0: all)", int_at_least(0))
    eval_downscale: float = option(1.0, "render and score at the dataset's resolution divided by this (default 1, "
                                   "whatever data.downscale training used)", float_at_least(0.0, strict=True))
    normal_mask: str = option("refnerf", "normal MAE weights: rendered opacity x ground-truth alpha (Ref-NeRF), or "
                              "the alpha alone", choices=NORMAL_MASKS)
    gt_mesh: Path | None = option(None, "reference mesh for the Chamfer distance", Path)
    chamfer_points: int = option(CHAMFER_POINTS, "points sampled on each mesh for the Chamfer distance",
                                 int_at_least(1))
    chamfer_seed: int = option(0, "seed of the prediction's points (reference: +1)", int_at_least(0))
    mesh_resolution: int | None = option(None, "marching cubes resolution when eval extracts the mesh (default "
                                         f"{MeshOptions().resolution})" + _MESH_NOTE, int_at_least(2))
    remove_floaters: bool | None = option(None, "clean small pieces when eval extracts the mesh (default: not "
                                          "cleaned)" + _MESH_NOTE)
    remove_inner: bool | None = option(None, "drop enclosed inner shells when eval extracts the mesh (default: "
                                       "kept)" + _MESH_NOTE)
    re_extract: bool = option(False, "extract a new RUN/mesh.ply (and mesh.json) even when extract-mesh wrote one")
    baked: Path | None = option(None, "also score the asset anisdf export wrote to DIR, rendered as its viewer page "
                                "draws it (baked_psnr, baked_ssim)", Path, metavar="DIR")
    appearance: str = option("mean", "runs with per-image appearance codes (appearance.embedding): render each view "
                             "with the mean code, or fit a code to the left half of the image and score the right "
                             "half (NeRF-W)", choices=APPEARANCE_PROTOCOLS)
    cameras: str = option("auto", "render each view from the dataset's pose (given), or from that pose corrected by an "
                          "se(3) fitted to the view's image with the scene frozen (fit: test-time pose optimisation, "
                          "BARF; for runs with cameras.refine, whose frame the photos fix only up to a small rigid "
                          "motion, and real captures whose held-out poses are as noisy as the training ones); auto: "
                          "fit when the run refined its cameras, else given", choices=CAMERA_PROTOCOLS)
    relight: Path | None = option(None, "also relight the PBR asset of `anisdf materials` under each light of FOLDER "
                                  "(LIGHT/r_i.png, LIGHT_world.exr) and score it (relight: psnr, ssim per light; "
                                  "material errors where FOLDER/material.json gives the truth)", Path,
                                  metavar="FOLDER")
    device: str | None = option(None, "auto | cpu | cuda[:N] (default auto)")
    progress: bool = option(True, "show a progress bar over the views", cli=False)


def _check(o: EvalOptions) -> dict[str, Any]:
    """Refuse contradictory or out-of-range options before any work; returns the mesh settings asked for."""
    if o.normal_mask not in NORMAL_MASKS:
        raise AnisdfError(f"--normal-mask must be one of {', '.join(NORMAL_MASKS)}, got {o.normal_mask!r}")
    if o.appearance not in APPEARANCE_PROTOCOLS:
        raise AnisdfError(f"--appearance must be one of {', '.join(APPEARANCE_PROTOCOLS)}, got {o.appearance!r}")
    if o.cameras not in CAMERA_PROTOCOLS:
        raise AnisdfError(f"--cameras must be one of {', '.join(CAMERA_PROTOCOLS)}, got {o.cameras!r}")
    if not (o.eval_downscale > 0 and np.isfinite(o.eval_downscale)):
        raise AnisdfError(f"--eval-downscale must be a positive number, got {o.eval_downscale}")
    if o.chamfer_points <= 0:
        raise AnisdfError(f"--chamfer-points must be positive, got {o.chamfer_points}")
    requested = {"resolution": o.mesh_resolution, "remove_floaters": o.remove_floaters,
                 "remove_inner": o.remove_inner}
    if o.gt_mesh is None and (o.re_extract or any(v is not None for v in requested.values())):
        raise AnisdfError("--re-extract, --mesh-resolution, --remove-floaters and --remove-inner choose the mesh the "
                          "Chamfer distance scores: pass --gt-mesh too")
    return requested


def _score_mesh(mesh_path: Path, gt, o: EvalOptions, radius: float,
                to_world) -> tuple[dict[str, Any], dict[str, Any]]:
    """The scored mesh's Chamfer numbers and inner-shell share, and their protocol entries (``chamfer`` with a
    ``warning`` when the distance says the reference is in another frame, ``inner_shells``)."""
    from anisdf.eval.metrics import load_mesh
    from anisdf.tasks.evaluate import protocol as record
    from anisdf.tasks.evaluate import scoring
    from anisdf.tasks.evaluate.shells import inner_shells, inner_shells_record

    mesh = load_mesh(mesh_path)
    metrics = scoring.chamfer_scores(mesh_path, gt, o.gt_mesh, o.chamfer_points, o.chamfer_seed, mesh=mesh)
    chamfer = record.chamfer_record(o.chamfer_points, o.chamfer_seed, o.gt_mesh)
    warning = scoring.chamfer_frame_warning(metrics["chamfer"], radius, to_world)
    if warning is not None:
        log.warning("eval: %s", warning)
        chamfer["warning"] = warning
    shells = inner_shells(mesh)
    metrics["inner_shell_share"] = shells["share"]
    (log.warning if shells["inner_components"] else log.info)(
        "eval: inner shells: %.1f%% of the mesh's area in %d of %d components that no camera outside sees",
        100.0 * shells["share"], shells["inner_components"], shells["components"])
    return metrics, {"chamfer": chamfer, "inner_shells": inner_shells_record(shells)}


def evaluate(run: Path, options: EvalOptions | None = None, **changes: Any) -> dict[str, Any]:
    """PSNR / SSIM (and normal MAE where the dataset has normal maps) on a split, Chamfer against ``gt_mesh``;
    writes RUN/eval.json (with a "protocol" object recording every choice), RUN/eval/ images and a report
    (protocols: docs/evaluation.md). ``changes`` replace fields of ``options`` (:class:`EvalOptions`).

    Views are rendered at the dataset's own resolution divided by ``eval_downscale`` (1: the images on disk, in
    ``data.images_dir`` when the run reads another folder), whatever ``data.downscale`` training used. The Chamfer
    distance scores the mesh ``extract-mesh`` wrote (RUN/mesh.json) when there is one; eval extracts one (with the
    mesh task's defaults, not cleaned) only when there is none, or with ``re_extract``.
    ``mesh_resolution`` / ``remove_floaters`` / ``remove_inner`` left at None mean "as the existing mesh, else the
    defaults"; given, they must match the existing mesh (else pass ``re_extract``).
    ``baked``: a folder ``anisdf export`` wrote from this run; its asset is rendered by the reference renderer (what
    the viewer page draws) from the same cameras and scored too (``baked_psnr``, ``baked_ssim``).

    References are checked before they are scored: a normal map whose covered pixels do not decode to unit vectors
    as ``(n + 1) / 2`` is skipped (protocol ``normal_maps_skipped``: file and reason); a Chamfer distance above a
    tenth of the scene sphere's diameter is written with a warning (protocol ``chamfer.warning``) that the reference
    mesh may be in another frame. ``inner_shell_share``: the scored mesh's area in closed components no camera
    outside sees (:mod:`.shells`).
    """
    from tqdm import tqdm

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.eval.metrics import load_mesh
    from anisdf.models.views import panel
    from anisdf.tasks.evaluate import appearance as codes
    from anisdf.tasks.evaluate import protocol as record
    from anisdf.tasks.evaluate import scoring
    from anisdf.tasks.evaluate import view_cameras as poses
    from anisdf.tasks.evaluate.report import write_run_report
    from anisdf.tasks.loading import dataset_up, load_run, scene_for_run
    from anisdf.tasks.mesh import mesh_for_eval
    from anisdf.utils.devices import pick_device
    from anisdf.utils.images import save_image

    o = dataclasses.replace(options or EvalOptions(), **changes)
    run, rd = Path(run), RunDir(run)
    requested = _check(o)
    dev = pick_device(o.device or "auto")
    gt = load_mesh(o.gt_mesh) if o.gt_mesh is not None else None  # fail early on a bad reference mesh
    cfg, model, ck = load_run(run, dev)
    cameras = poses.resolve_protocol(o.cameras, model.cameras is not None)
    step = int(ck["state"]["step"])
    mesh_info = mesh_for_eval(run, step, requested, o.re_extract) if o.gt_mesh is not None else None
    asset = scoring.baked_for_eval(o.baked, step) if o.baked is not None else None
    scene = scene_for_run(run, cfg, ck, downscale=o.eval_downscale, split=o.split)
    background = eval_background(scene)
    if asset is not None and background != "white":
        raise AnisdfError(f"--baked: {scene.root} has photos without alpha or masks; a baked asset has no background "
                          "to score against them")
    data = RayDataset(scene, o.split, device=dev, background=background)
    ids = scene.splits[o.split]
    n = len(data) if o.max_views <= 0 else min(o.max_views, len(data))
    held_out = o.split != "train" and cfg.data.train_split != "all"
    if not held_out:
        log.warning("eval: the %s views were used in training (data.train_split=%s): not a held-out score",
                    o.split, cfg.data.train_split)
    log.info("eval: %d %s views at %dx%d (dataset resolution / %g; training used / %g)", n, o.split, scene.width,
             scene.height, o.eval_downscale, cfg.data.downscale)
    per_view: list[dict[str, Any]] = []
    images: list[Path] = []
    normal_names: set[str] = set()
    skipped: list[dict[str, str]] = []
    half = o.appearance == "fit-left-half"
    for i in tqdm(range(n), desc=f"eval {o.split}", unit="view", disable=not o.progress):
        with poses.view_camera(model, data, i, cameras, left_half=half) as fit, \
                codes.view_code(model, data, i, o.appearance):
            row, res, normal_name, skip = scoring.score_view(
                model, data, i, ids[i], scene, ck, cfg.renderer.eval_chunk_rays, o.normal_mask, asset,
                right_half=half)
        per_view.append({**row, **fit})
        if normal_name is not None:
            normal_names.add(normal_name)
        if skip is not None:
            skipped.append(skip)
        images.append(save_image(rd.eval_images / f"{i:03d}.png", panel(res)))
    metrics = scoring.mean_scores(per_view, o.split, baked=asset is not None)
    protocol = record.views_record(scene, cfg, o.split, n, held_out, o.eval_downscale, background)
    protocol["cameras"] = codes.cameras_record(model, o.split, rd.read_refined_cameras() is not None)
    protocol["cameras"]["scored_views"] = poses.view_cameras_record(cameras, half, requested=o.cameras)
    protocol["appearance"] = codes.appearance_record(model, o.appearance)
    if asset is not None:
        protocol["baked"] = record.baked_record(o.baked, asset.manifest)
    n_maes = sum("normal_mae_deg" in r for r in per_view)
    if n_maes:
        protocol["normal_mae"] = record.normal_mae_record(n_maes, normal_names, o.normal_mask,
                                                          record.alpha_source(scene))
    if skipped:
        log.warning("eval: %d reference normal map(s) not scored (%s: %s)%s", len(skipped), skipped[0]["file"],
                    skipped[0]["reason"], f"; normal_mae_deg over the {n_maes} other view(s)" if n_maes else
                    "; no normal_mae_deg")
        protocol["normal_maps_skipped"] = skipped
    if o.gt_mesh is not None:
        mesh_info = scoring.mesh_to_score(run, mesh_info, requested, o.re_extract, str(dev), o.progress)
        mesh_metrics, mesh_protocol = _score_mesh(Path(mesh_info["path"]), gt, o, cfg.renderer.radius, ck["to_world"])
        metrics.update(mesh_metrics)
        protocol["mesh"] = record.mesh_record(mesh_info)
        protocol.update(mesh_protocol)
    if o.relight is not None:
        from anisdf.tasks.evaluate.relight import relight_scores

        metrics["relight"], protocol["relight"] = relight_scores(run, o.relight, o.progress)
    metrics.update(steps=step, train_seconds=float(ck["state"]["train_seconds"]), preset=cfg.preset)
    rd.write_eval({**metrics, "protocol": protocol, "per_view": per_view})
    write_run_report(run, metrics, per_view, images, protocol=protocol, up=dataset_up(scene, ck))
    return {**metrics, "protocol": protocol}
