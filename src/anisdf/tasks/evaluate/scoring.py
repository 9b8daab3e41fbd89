"""Scoring one run: each view's PSNR / SSIM / normal MAE (and a baked asset's scores), their means, and the Chamfer
distance of the mesh eval chooses."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir

log = logging.getLogger("anisdf")

BAKED_KEYS = ("baked_psnr", "baked_ssim", "baked_vs_neural_psnr")


def baked_for_eval(folder: Path, step: int):
    """The baked asset in ``folder``, checked to come from the checkpoint being evaluated."""
    from anisdf.export.reference_renderer import BakedAsset

    asset = BakedAsset.load(folder)
    if asset.manifest.get("step") != step:
        raise AnisdfError(f"--baked {folder} was exported at step {asset.manifest.get('step')} but the checkpoint is "
                          f"at step {step}; run anisdf export again")
    return asset


def ground_truth_alpha(scene, index: int, reference: np.ndarray) -> np.ndarray:
    """[H, W] coverage of view ``index`` in [0, 1]: ``Scene.coverage()``, else the normal map's own alpha."""
    cover = scene.coverage()
    return cover[index].float().numpy() / 255.0 if cover is not None else reference[..., 3]


def normal_weights(scene, index: int, reference: np.ndarray, opacity: np.ndarray, normal_mask: str) -> np.ndarray:
    """Pixel weights of view ``index``'s normal MAE: the ground-truth alpha (:func:`ground_truth_alpha`), times the
    rendered opacity for ``refnerf`` (Ref-NeRF's eval.py)."""
    gt_alpha = ground_truth_alpha(scene, index, reference)
    if normal_mask == "refnerf":
        return gt_alpha * np.clip(opacity[..., 0], 0.0, 1.0)
    return gt_alpha


def normal_map_skip(path: Path | None, scene, index: int, reference: np.ndarray) -> dict[str, str] | None:
    """``{"file", "reason"}`` when the normal map at ``path`` (view ``index``'s reference) does not hold unit normals
    as ``(n + 1) / 2`` over the covered pixels (:func:`anisdf.eval.metrics.normal_map_problem`), else None."""
    from anisdf.data.images import read_normal_raw
    from anisdf.eval.metrics import normal_map_problem

    if path is None:
        return None
    raw = read_normal_raw(path, (scene.width, scene.height))
    problem = normal_map_problem(raw, ground_truth_alpha(scene, index, reference))
    return None if problem is None else {"file": path.name, "reason": problem}


def score_view(model, data, i: int, index: int, scene, ck: dict[str, Any], chunk_rays: int, normal_mask: str,
               asset=None, right_half: bool = False
               ) -> tuple[dict[str, Any], dict[str, Any], str | None, dict[str, str] | None]:
    """Render view ``i`` of ``data`` (``scene``'s image ``index``) and score it. Returns its row of eval.json's
    ``per_view``, the render (for :func:`anisdf.models.views.panel`; with ``baked`` / ``baked_psnr`` when ``asset``
    is scored too), the name pattern of its reference normal map (``<image>_normal.png``; None without one or when
    it is skipped) and, when that map is skipped rather than scored, ``{"file", "reason"}`` (:func:`normal_map_skip`).
    ``right_half``: PSNR and SSIM of the columns ``>= W // 2`` only (NeRF-W's protocol, evaluate/appearance.py).
    """
    import torch

    from anisdf.data.dataparsers.blender import find_normal_map
    from anisdf.eval.metrics import normal_mae_deg, psnr, ssim
    from anisdf.models.views import render_view
    from anisdf.tasks.loading import dataset_camera

    res = render_view(model, data, i, scene, chunk_rays, fine_grid=True)
    pred = np.clip(res["maps"]["rgb"], 0.0, 1.0)
    image = scene.image_paths[index]
    half = np.s_[:, pred.shape[1] // 2:] if right_half else np.s_[:, :]
    row: dict[str, Any] = {"view": i, "image": image.name, "psnr": psnr(pred[half], res["gt"][half]),
                           "ssim": ssim(pred[half], res["gt"][half])}
    if asset is not None:
        from anisdf.export.reference_renderer import render as render_baked

        img, _ = render_baked(asset, dataset_camera(scene, index, ck),
                              supersample=int(asset.manifest.get("supersample", 1)))
        res["baked"], res["baked_psnr"] = img, psnr(img, res["gt"])
        row.update(baked_psnr=res["baked_psnr"], baked_ssim=ssim(img, res["gt"]), baked_vs_neural_psnr=psnr(img, pred))
    ref = scene.normals.get(index)
    if ref is None:
        return row, res, None, None
    ref_np = ref.cpu().numpy() if isinstance(ref, torch.Tensor) else np.asarray(ref)
    found = find_normal_map(image)
    skipped = normal_map_skip(found, scene, index, ref_np)
    if skipped is not None:
        return row, res, None, skipped
    weights = normal_weights(scene, index, ref_np, res["maps"]["opacity"], normal_mask)
    if float(weights.sum()) > 0:
        row["normal_mae_deg"] = normal_mae_deg(res["maps"]["normal"], ref_np[..., :3], weights=weights)
    else:  # Ref-NeRF's 0 / 0: nothing rendered where the object is
        log.warning("eval: view %d (%s) has no pixel with weight > 0 for the normal MAE (%s); left out", i,
                    image.name, normal_mask)
    return row, res, None if found is None else "<image>" + found.name[len(image.stem):], None


def mean_scores(per_view: list[dict[str, Any]], split: str, baked: bool) -> dict[str, Any]:
    """eval.json's headline numbers: means over views (the normal MAE over the views that have one)."""
    metrics: dict[str, Any] = {
        "split": split, "n_views": len(per_view),
        "psnr": float(np.mean([r["psnr"] for r in per_view])),
        "ssim": float(np.mean([r["ssim"] for r in per_view])),
    }
    maes = [r["normal_mae_deg"] for r in per_view if "normal_mae_deg" in r]
    if maes:
        metrics["normal_mae_deg"] = float(np.mean(maes))
    if baked:
        for key in BAKED_KEYS:
            metrics[key] = float(np.mean([r[key] for r in per_view]))
    return metrics


def mesh_to_score(run: Path, mesh_info: dict[str, Any] | None, requested: dict[str, Any], re_extract: bool,
                  device: str, progress: bool) -> dict[str, Any]:
    """The mesh the Chamfer distance scores: ``mesh_info`` (the one extract-mesh wrote, as
    :func:`anisdf.tasks.mesh.mesh_for_eval` chose it), else one extracted now with ``requested``'s settings (None:
    the mesh task's defaults). Returns its mesh.json record with its ``path``."""
    from anisdf.tasks.mesh import describe_mesh, extract_mesh

    if mesh_info is not None:
        log.info("eval: scoring %s written by %s (%s)", mesh_info["path"], mesh_info.get("written_by", "?"),
                 describe_mesh(mesh_info))
        return mesh_info
    settings = {k: v for k, v in requested.items() if v is not None}
    mesh_path = extract_mesh(run, device=device, progress=progress,
                             written_by="eval --re-extract" if re_extract else "eval", **settings)
    mesh_info = {**RunDir(run).read_mesh_info(), "path": str(mesh_path)}
    log.info("eval: extracted %s (%s)", mesh_path, describe_mesh(mesh_info))
    return mesh_info


def chamfer_scores(mesh_path: Path, gt, gt_mesh: Path, points: int, seed: int, mesh=None) -> dict[str, Any]:
    """eval.json's Chamfer numbers for the mesh at ``mesh_path`` (``mesh`` when already read) against the reference
    ``gt`` (read from ``gt_mesh``)."""
    from anisdf.eval.metrics import chamfer_distance, load_mesh

    cd = chamfer_distance(load_mesh(mesh_path) if mesh is None else mesh, gt, n_points=points, seed=seed)
    return {"chamfer": cd["chamfer"], "chamfer_accuracy": cd["accuracy"], "chamfer_completeness": cd["completeness"],
            "chamfer_points": points, "gt_mesh": str(gt_mesh), "mesh": str(mesh_path)}


CHAMFER_FRAME_SHARE = 0.1
"""A Chamfer distance above this share of the scene sphere's diameter says the reference is in another frame."""


def chamfer_frame_warning(chamfer: float, radius: float, to_world: np.ndarray) -> str | None:
    """A warning when ``chamfer`` (dataset units) exceeds :data:`CHAMFER_FRAME_SHARE` of the diameter of the run's
    scene sphere (``radius`` in model units, mapped to the dataset frame by the similarity ``to_world``), else
    None: a reference mesh in another frame or scale than the dataset's cameras gives such numbers."""
    scale = float(abs(np.linalg.det(np.asarray(to_world, dtype=np.float64)[:3, :3])) ** (1.0 / 3.0))
    diameter = 2.0 * float(radius) * scale
    if not chamfer > CHAMFER_FRAME_SHARE * diameter:
        return None
    return (f"the Chamfer distance {chamfer:.4g} is {chamfer / diameter:.0%} of the scene sphere's diameter "
            f"({diameter:.4g} dataset units): the reference mesh may be in another frame or scale than the dataset's "
            "cameras")
