"""Scoring a run: PSNR, SSIM, normal MAE on a split, Chamfer against a reference mesh, a baked asset."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir

log = logging.getLogger("anisdf")

NORMAL_MASKS = ("refnerf", "alpha")
"""Pixel weights of the normal MAE: refnerf = rendered opacity x ground-truth alpha (Ref-NeRF's eval.py),
alpha = ground-truth alpha alone (holes in the render count in full)."""


def _baked_for_eval(folder: Path, step: int):
    """The baked asset in ``folder``, checked to come from the checkpoint being evaluated."""
    from anisdf.export.reference_renderer import BakedAsset

    asset = BakedAsset.load(folder)
    if asset.manifest.get("step") != step:
        raise AnisdfError(f"--baked {folder} was exported at step {asset.manifest.get('step')} but the checkpoint is "
                          f"at step {step}; run anisdf export again")
    return asset


def _view_selection(scene, split: str) -> str:
    """How the dataset's parser chose the views of ``split`` (for the protocol record)."""
    if split == "test" and scene.format == "nerf-synthetic" and (scene.root / "transforms_test.json").is_file():
        return "transforms_test.json"
    if split == "test":
        return "every 8th image in name order from the first (LLFF hold-out; Mip-NeRF 360, Table 5)"
    if split == "train" and scene.format != "nerf-synthetic":
        return "the images not held out (all but every 8th in name order)"
    return f"transforms_{split}.json" if scene.format == "nerf-synthetic" else split


def evaluate(run: Path, split: str = "test", max_views: int = 0, gt_mesh: Path | None = None,
             device: str | None = None, chamfer_points: int = 1_000_000, mesh_resolution: int | None = None,
             remove_floaters: bool | None = None, remove_inner: bool | None = None, re_extract: bool = False,
             eval_downscale: float = 1.0, normal_mask: str = "refnerf", chamfer_seed: int = 0,
             baked: Path | None = None, progress: bool = True) -> dict[str, Any]:
    """PSNR / SSIM (and normal MAE where the dataset has normal maps) on a split, Chamfer against ``gt_mesh``;
    writes RUN/eval.json (with a "protocol" object recording every choice), RUN/eval/ images and a report
    (protocols: docs/evaluation.md).

    Views are rendered at the dataset's own resolution divided by ``eval_downscale`` (1: the images on disk, in
    ``data.images_dir`` when the run reads another folder), whatever ``data.downscale`` training used. The Chamfer
    distance scores the mesh ``extract-mesh`` wrote (RUN/mesh.json) when there is one; eval extracts one (same
    defaults: ``mesh_resolution`` 512, not cleaned) only when there is none, or with ``re_extract``.
    ``mesh_resolution`` / ``remove_floaters`` / ``remove_inner`` left at None mean "as the existing mesh, else the
    defaults"; given, they must match the existing mesh (else pass ``re_extract``).
    ``baked``: a folder ``anisdf export`` wrote from this run; its asset is rendered by the reference renderer (what
    the viewer page draws) from the same cameras and scored too (``baked_psnr``, ``baked_ssim``).
    """
    from tqdm import tqdm

    from anisdf.data.dataparsers.blender import find_normal_map
    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.eval.metrics import chamfer_distance, load_mesh, normal_mae_deg, psnr, ssim
    from anisdf.eval.report import write_report
    from anisdf.models.views import panel, render_view
    from anisdf.tasks.loading import dataset_camera, load_run, scene_for_run
    from anisdf.tasks.mesh import MESH_DEFAULTS, describe_mesh, extract_mesh, mesh_for_eval
    from anisdf.utils.devices import pick_device
    from anisdf.utils.images import save_image

    if normal_mask not in NORMAL_MASKS:
        raise AnisdfError(f"--normal-mask must be one of {', '.join(NORMAL_MASKS)}, got {normal_mask!r}")
    if not (eval_downscale > 0 and np.isfinite(eval_downscale)):
        raise AnisdfError(f"--eval-downscale must be a positive number, got {eval_downscale}")
    if chamfer_points <= 0:
        raise AnisdfError(f"--chamfer-points must be positive, got {chamfer_points}")
    requested = {"resolution": mesh_resolution, "remove_floaters": remove_floaters, "remove_inner": remove_inner}
    if gt_mesh is None and (re_extract or any(v is not None for v in requested.values())):
        raise AnisdfError("--re-extract, --mesh-resolution, --remove-floaters and --remove-inner choose the mesh the "
                          "Chamfer distance scores: pass --gt-mesh too")
    dev = pick_device(device or "auto")
    if gt_mesh is not None:
        gt = load_mesh(gt_mesh)  # fail early on a bad reference mesh
    cfg, model, ck = load_run(run, dev)
    step = int(ck["state"]["step"])
    mesh_info = mesh_for_eval(run, step, requested, re_extract) if gt_mesh is not None else None
    asset = _baked_for_eval(baked, step) if baked is not None else None
    scene = scene_for_run(run, cfg, ck, downscale=eval_downscale, split=split)
    if asset is not None and eval_background(scene) != "white":
        raise AnisdfError(f"--baked: {scene.root} has photos without alpha or masks; a baked asset has no background "
                          "to score against them")
    data = RayDataset(scene, split, device=dev, background=eval_background(scene))
    ids = scene.splits[split]
    n = len(data) if max_views <= 0 else min(max_views, len(data))
    held_out = split != "train" and cfg.data.train_split != "all"
    if not held_out:
        log.warning("eval: the %s views were used in training (data.train_split=%s): not a held-out score",
                    split, cfg.data.train_split)
    log.info("eval: %d %s views at %dx%d (dataset resolution / %g; training used / %g)", n, split, scene.width,
             scene.height, eval_downscale, cfg.data.downscale)
    alpha_source = ("masks" if scene.masks is not None else "alpha" if scene.alpha is not None
                    else "normal-map coverage")  # as Scene.coverage() picks them
    per_view: list[dict[str, Any]] = []
    images: list[Path] = []
    normal_names: set[str] = set()
    for i in tqdm(range(n), desc=f"eval {split}", unit="view", disable=not progress):
        res = render_view(model, data, i, scene, cfg.renderer.eval_chunk_rays)
        pred = np.clip(res["maps"]["rgb"], 0.0, 1.0)
        row: dict[str, Any] = {"view": i, "image": scene.image_paths[ids[i]].name,
                               "psnr": psnr(pred, res["gt"]), "ssim": ssim(pred, res["gt"])}
        if asset is not None:
            from anisdf.export.reference_renderer import render as render_baked

            img, _ = render_baked(asset, dataset_camera(scene, ids[i], ck),
                                  supersample=int(asset.manifest.get("supersample", 1)))
            res["baked"], res["baked_psnr"] = img, psnr(img, res["gt"])
            row.update(baked_psnr=res["baked_psnr"], baked_ssim=ssim(img, res["gt"]),
                       baked_vs_neural_psnr=psnr(img, pred))
        ref = scene.normals.get(ids[i])
        if ref is not None:
            ref_np = ref.cpu().numpy() if isinstance(ref, torch.Tensor) else np.asarray(ref)
            cover = scene.coverage()
            gt_alpha = cover[ids[i]].float().numpy() / 255.0 if cover is not None else ref_np[..., 3]
            weights = gt_alpha
            if normal_mask == "refnerf":
                weights = gt_alpha * np.clip(res["maps"]["opacity"][..., 0], 0.0, 1.0)
            if float(weights.sum()) > 0:
                row["normal_mae_deg"] = normal_mae_deg(res["maps"]["normal"], ref_np[..., :3], weights=weights)
            else:  # Ref-NeRF's 0 / 0: nothing rendered where the object is
                log.warning("eval: view %d (%s) has no pixel with weight > 0 for the normal MAE (%s); left out", i,
                            scene.image_paths[ids[i]].name, normal_mask)
            image = scene.image_paths[ids[i]]
            found = find_normal_map(image)
            if found is not None:
                normal_names.add("<image>" + found.name[len(image.stem):])
        per_view.append(row)
        img_path = RunDir(run).eval_images / f"{i:03d}.png"
        save_image(img_path, panel(res))
        images.append(img_path)
    metrics: dict[str, Any] = {
        "split": split, "n_views": n,
        "psnr": float(np.mean([r["psnr"] for r in per_view])),
        "ssim": float(np.mean([r["ssim"] for r in per_view])),
    }
    maes = [r["normal_mae_deg"] for r in per_view if "normal_mae_deg" in r]
    if maes:
        metrics["normal_mae_deg"] = float(np.mean(maes))
    if asset is not None:
        for key in ("baked_psnr", "baked_ssim", "baked_vs_neural_psnr"):
            metrics[key] = float(np.mean([r[key] for r in per_view]))
    background = eval_background(scene)
    protocol: dict[str, Any] = {
        "split": split, "views": n, "view_selection": _view_selection(scene, split), "held_out": held_out,
        "eval_downscale": float(eval_downscale), "train_downscale": float(cfg.data.downscale),
        "images_dir": cfg.data.images_dir or None, "image_size": [scene.width, scene.height],
        "background": ("white: renders on white, ground-truth RGBA (or masked photos) composited on white"
                       if background == "white" else "none: photos as photographed, the model's learned background"),
        "psnr": "mean over views of -10 log10(MSE), float renders in [0, 1] against 8-bit ground truth",
        "ssim": "skimage structural_similarity: gaussian_weights, sigma 1.5, population covariance, data_range 1, "
                "mean over channels; mean over views",
        "normal_mae": None, "mesh": None, "chamfer": None, "baked": None,
    }
    if asset is not None:
        man = asset.manifest
        protocol["baked"] = {
            "dir": str(baked), "faces": man.get("faces"), "texture": man.get("texture"),
            "specular_texture": man.get("specular_texture"), "lobes": man.get("lobes"),
            "supersample": man.get("supersample", 1), "pixel_filter": man.get("pixel_filter", 0.0),
            "renderer": "anisdf.export.reference_renderer as the viewer page draws: supersample x supersample rays per "
                        "pixel through the centres of a finer pixel grid, filtered into pixels (a Gaussian of "
                        "pixel_filter pixels; 0: each pixel's own samples averaged); the same ground truth and "
                        "background as the neural render",
        }
    if maes:
        protocol["normal_mae"] = {
            "views": len(maes), "reference": sorted(normal_names), "space": "world, (n + 1) / 2 in RGB",
            "mask": normal_mask,
            "weights": ("rendered opacity x ground-truth " + alpha_source if normal_mask == "refnerf"
                        else "ground-truth " + alpha_source),
        }
    if gt_mesh is not None:
        if mesh_info is None:
            settings = {k: MESH_DEFAULTS[k] if v is None else v for k, v in requested.items()}
            mesh_path = extract_mesh(run, resolution=int(settings["resolution"]), device=str(dev),
                                     remove_floaters=bool(settings["remove_floaters"]),
                                     remove_inner=bool(settings["remove_inner"]), progress=progress,
                                     written_by="eval --re-extract" if re_extract else "eval")
            mesh_info = {**RunDir(run).read_mesh_info(), "path": str(mesh_path)}
            log.info("eval: extracted %s (%s)", mesh_path, describe_mesh(mesh_info))
        else:
            log.info("eval: scoring %s written by %s (%s)", mesh_info["path"], mesh_info.get("written_by", "?"),
                     describe_mesh(mesh_info))
        mesh_path = Path(mesh_info["path"])
        cd = chamfer_distance(load_mesh(mesh_path), gt, n_points=chamfer_points, seed=chamfer_seed)
        metrics.update(chamfer=cd["chamfer"], chamfer_accuracy=cd["accuracy"],
                       chamfer_completeness=cd["completeness"], chamfer_points=chamfer_points,
                       gt_mesh=str(gt_mesh), mesh=str(mesh_path))
        protocol["mesh"] = {k: mesh_info.get(k) for k in ("path", "written_by", "step", "resolution",
                                                          "remove_floaters", "floater_min_fraction", "remove_inner",
                                                          "two_pass", "margin", "frame")}
        protocol["chamfer"] = {"points": chamfer_points, "seed_pred": chamfer_seed, "seed_gt": chamfer_seed + 1,
                               "gt_mesh": str(gt_mesh), "units": "dataset",
                               "distance": "(accuracy + completeness) / 2, nearest neighbours both ways"}
    metrics.update(steps=step, train_seconds=float(ck["state"]["train_seconds"]), preset=cfg.preset)
    RunDir(run).write_eval({**metrics, "protocol": protocol, "per_view": per_view})
    write_report(run, metrics, per_view, images, protocol=protocol)
    return {**metrics, "protocol": protocol}


