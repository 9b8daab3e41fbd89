"""What the CLI's train / extract-mesh / render / eval commands do, as plain functions."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anisdf.config import Config, config_from_dict, load_config, set_key
from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")


def _data_path(run: Path, ck: dict[str, Any]) -> Path:
    info_path = run / "run.json"
    data = json.loads(info_path.read_text())["data"] if info_path.is_file() else ck.get("data")
    if not data or not Path(data).exists():
        raise AnisdfError(f"{run}: the dataset this run was trained on ({data}) is no longer there")
    return Path(data)


def _scene_for_run(run: Path, cfg, ck: dict[str, Any], downscale: float | None = None, split: str | None = None):
    """The run's dataset in the frame the model was trained in (the checkpoint's normalisation), at the training
    resolution or at ``downscale``, every view or only ``split``'s."""
    from anisdf.data.dataparsers import load_scene

    return load_scene(_data_path(run, ck), downscale=cfg.data.downscale if downscale is None else downscale,
                      max_images=cfg.data.max_images if split in (None, "train") else 0,
                      images_dir=cfg.data.images_dir, split=split, to_world=np.asarray(ck["to_world"]))


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
    steps (rank 0 only). Under torchrun every rank calls this and joins the job (systems/distributed.py); the summary
    is the same on every rank."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.systems import distributed
    from anisdf.systems.checkpoint import load_checkpoint
    from anisdf.systems.trainer import Trainer, pick_device

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


MESH_SIDECAR = "mesh.json"
FLOATER_MIN_FRACTION = 0.01
"""``remove_floaters``: components under this fraction of the largest one's face count are dropped."""
MESH_DEFAULTS: dict[str, Any] = {"resolution": 512, "remove_floaters": False, "remove_inner": False}
"""What ``extract-mesh`` and ``eval`` use unless told otherwise: the mesh as marching cubes found it, not cleaned."""


def extract_mesh(run: Path, resolution: int = 512, fmt: str = "ply", device: str | None = None,
                 remove_floaters: bool = False, remove_inner: bool = False, progress: bool = True,
                 written_by: str = "extract-mesh") -> Path:
    """Marching cubes on the SDF, vertex colours from the view branch, written in the dataset's frame as
    RUN/mesh.<fmt>, with its settings in RUN/mesh.json (which ``eval`` reads). Not cleaned unless asked:
    ``remove_floaters`` drops small disconnected pieces, ``remove_inner`` the shells around pockets enclosed inside
    the object (docs/evaluation.md)."""
    from anisdf.export.atomic import write_text_atomic
    from anisdf.export.mesh import color_vertices, save_mesh, to_world
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.export.mesh import remove_floaters as drop_floaters
    from anisdf.systems.trainer import load_run, pick_device

    dev = pick_device(device or "auto")
    cfg, model, ck = load_run(run, dev)
    mesh = mc(model.geometry.sdf, radius=model.radius, resolution=resolution, device=dev, progress=progress,
              keep_inner=not remove_inner)
    if remove_floaters:
        mesh = drop_floaters(mesh, min_fraction=FLOATER_MIN_FRACTION)
    mesh = color_vertices(mesh, model.diffuse_color, device=dev)
    mesh = to_world(mesh, np.asarray(ck["to_world"], dtype=np.float64))
    path = run / f"mesh.{fmt}"
    save_mesh(mesh, path, fmt)
    info = {"mesh": path.name, "written_by": written_by, "step": int(ck["state"]["step"]),
            "resolution": int(resolution), "remove_floaters": bool(remove_floaters),
            "floater_min_fraction": FLOATER_MIN_FRACTION if remove_floaters else None,
            "remove_inner": bool(remove_inner), "two_pass": True, "margin": 0.1, "frame": "dataset",
            "vertices": len(mesh.vertices), "faces": len(mesh.faces)}
    write_text_atomic(run / MESH_SIDECAR, json.dumps(info, indent=2) + "\n")
    log.info("mesh: %d vertices, %d faces -> %s (%s)", len(mesh.vertices), len(mesh.faces), path,
             _describe_mesh(info))
    return path


def _describe_mesh(info: dict[str, Any]) -> str:
    return (f"resolution {info['resolution']}, floaters {'removed' if info['remove_floaters'] else 'kept'}, "
            f"inner shells {'removed' if info['remove_inner'] else 'kept'}, step {info['step']}")


def _mesh_for_eval(run: Path, step: int, requested: dict[str, Any], re_extract: bool) -> dict[str, Any] | None:
    """The mesh ``eval`` scores: the one ``extract-mesh`` wrote (RUN/mesh.json) when there is one, else None (extract
    one). Raises when that mesh does not fit (another step, other settings asked for, no sidecar) and
    ``re_extract`` is off, rather than scoring or replacing it silently."""
    sidecar = run / MESH_SIDECAR
    if re_extract:
        return None
    if sidecar.is_file():
        try:
            info = json.loads(sidecar.read_text())
            mesh_name = str(info["mesh"])
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            raise AnisdfError(f"{sidecar}: unreadable ({e}); pass --re-extract to write a new mesh") from None
        mesh_path = run / mesh_name
        if not mesh_path.is_file():
            raise AnisdfError(f"{sidecar} names {mesh_name}, which is missing; run extract-mesh or pass --re-extract")
        if info.get("step") != step:
            raise AnisdfError(f"{mesh_path} was extracted at step {info.get('step')} but the checkpoint is at step "
                              f"{step}; run extract-mesh again or pass --re-extract")
        for key, value in requested.items():
            if value is not None and info.get(key) != value:
                raise AnisdfError(f"{mesh_path} was extracted with {key}={info.get(key)} ({MESH_SIDECAR}), not "
                                  f"{value}; pass --re-extract to replace it, or drop the option to score it")
        return {**info, "path": str(mesh_path)}
    old = [p for p in (run / "mesh.ply", run / "mesh.obj", run / "mesh.glb") if p.is_file()]
    if old:
        raise AnisdfError(f"{old[0]} has no {MESH_SIDECAR} (an older anisdf wrote it; its settings are unknown); "
                          "pass --re-extract to replace it")
    return None


def render(run: Path, split: str = "test", video: bool = False, max_views: int = 0, downscale: int = 1,
           device: str | None = None, n_video_frames: int = 60) -> Path:
    """Render every view of a split with its maps into RUN/renders/<split>/, and optionally an orbit video."""
    from tqdm import tqdm

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.export.visualize import save_image
    from anisdf.systems.rendering import MAP_NAMES, map_to_image, render_view
    from anisdf.systems.trainer import load_run, pick_device

    dev = pick_device(device or "auto")
    cfg, model, ck = load_run(run, dev)
    scene = _scene_for_run(run, cfg, ck)
    if not scene.splits.get(split):
        raise AnisdfError(f"split '{split}' is empty for {scene.root}; choose one of {sorted(scene.splits)}")
    data = RayDataset(scene, split, device=dev, background=eval_background(scene), downscale=downscale)
    n = len(data) if max_views <= 0 else min(max_views, len(data))
    out_dir = run / "renders" / split
    for i in tqdm(range(n), desc=f"render {split}", unit="view"):
        res = render_view(model, data, i, scene, cfg.renderer.eval_chunk_rays)
        for name in MAP_NAMES:
            key = "weight" if name == "w" else name
            if key in res["maps"]:
                save_image(out_dir / f"{i:03d}_{key}.png", map_to_image(res["maps"], name))
    if video:
        render_orbit(model, scene, cfg, run / "renders" / "orbit.mp4", n_video_frames, downscale, dev)
    return out_dir


def render_orbit(model, scene, cfg, path: Path, n_frames: int, downscale: int, dev: torch.device) -> Path:
    """An orbit around the object at the train cameras' mean distance and elevation, with rgb | normal frames."""
    from tqdm import tqdm

    from anisdf.export.video import orbit_poses, write_video
    from anisdf.export.visualize import normal_to_image, to_uint8
    from anisdf.systems.rendering import render_rays_to_maps

    cams = scene.cameras
    train_idx = scene.splits["train"]
    centres = cams.c2w[train_idx, :, 3]
    dist = float(centres.norm(dim=-1).mean())
    up = -cams.c2w[train_idx, :, 1].mean(0)  # OpenCV y points down
    up = up / up.norm()
    elev = float(torch.rad2deg(torch.asin((centres / centres.norm(dim=-1, keepdim=True) @ up).mean().clamp(-1, 1))))
    poses = orbit_poses(n_frames, dist, elev, up=up.numpy(), look_at=(0.0, 0.0, 0.0))
    from anisdf.data.cameras import Cameras

    k = train_idx[0]  # borrow the intrinsics of a train camera
    orbit = Cameras(c2w=torch.as_tensor(np.asarray(poses), dtype=torch.float32),
                    fx=cams.fx[k].repeat(n_frames), fy=cams.fy[k].repeat(n_frames),
                    cx=cams.cx[k].repeat(n_frames), cy=cams.cy[k].repeat(n_frames),
                    width=cams.width, height=cams.height).to(dev)
    frames = []
    for i in tqdm(range(n_frames), desc="orbit video", unit="frame"):
        origins, dirs = orbit.image_rays(i, max(int(downscale), 1))
        hw = dirs.shape[:2]
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        maps = render_rays_to_maps(model, origins, dirs, torch.ones_like(dirs), hw, cfg.renderer.eval_chunk_rays)
        fg = maps["opacity"][..., 0:1] > 0.5
        frames.append(np.concatenate([to_uint8(maps["rgb"]), normal_to_image(maps["normal"] * fg)], axis=1))
    return write_video(frames, path)


NORMAL_MASKS = ("refnerf", "alpha")
"""Pixel weights of the normal MAE: refnerf = rendered opacity x ground-truth alpha (Ref-NeRF's eval.py),
alpha = ground-truth alpha alone (holes in the render count in full)."""


def _baked_for_eval(folder: Path, step: int):
    """The baked asset in ``folder``, checked to come from the checkpoint being evaluated."""
    from anisdf.export.baked_renderer import BakedAsset

    asset = BakedAsset.load(folder)
    if asset.manifest.get("step") != step:
        raise AnisdfError(f"--baked {folder} was exported at step {asset.manifest.get('step')} but the checkpoint is "
                          f"at step {step}; run anisdf export again")
    return asset


def _dataset_camera(scene, i: int, ck: dict[str, Any]):
    """Camera ``i`` of ``scene`` in the dataset's frame (where baked assets live), as the reference renderer takes
    it."""
    from anisdf.export.baked_renderer import PinholeCamera

    T = np.asarray(ck["to_world"], dtype=np.float64)
    cams = scene.cameras
    c2w = np.eye(4)
    c2w[:3, :4] = cams.c2w[i].double().cpu().numpy()
    c2w = T @ c2w
    c2w[:3, :3] /= np.cbrt(np.linalg.det(T[:3, :3]))
    dist = None if cams.distortion is None else cams.distortion[i].double().cpu().numpy()
    return PinholeCamera(c2w, float(cams.fx[i]), float(cams.fy[i]), float(cams.cx[i]), float(cams.cy[i]),
                         cams.width, cams.height, dist)


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
    from anisdf.export.visualize import save_image
    from anisdf.systems.rendering import panel, render_view
    from anisdf.systems.trainer import load_run, pick_device

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
    mesh_info = _mesh_for_eval(run, step, requested, re_extract) if gt_mesh is not None else None
    asset = _baked_for_eval(baked, step) if baked is not None else None
    scene = _scene_for_run(run, cfg, ck, downscale=eval_downscale, split=split)
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
            from anisdf.export.baked_renderer import render as render_baked

            img, _ = render_baked(asset, _dataset_camera(scene, ids[i], ck),
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
        img_path = run / "eval" / f"{i:03d}.png"
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
            "renderer": "anisdf.export.baked_renderer as the viewer page draws: supersample x supersample rays per "
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
            mesh_info = {**json.loads((run / MESH_SIDECAR).read_text()), "path": str(mesh_path)}
            log.info("eval: extracted %s (%s)", mesh_path, _describe_mesh(mesh_info))
        else:
            log.info("eval: scoring %s written by %s (%s)", mesh_info["path"], mesh_info.get("written_by", "?"),
                     _describe_mesh(mesh_info))
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
    (run / "eval.json").write_text(json.dumps({**metrics, "protocol": protocol, "per_view": per_view}, indent=2))
    write_report(run, metrics, per_view, images, protocol=protocol)
    return {**metrics, "protocol": protocol}


def _export_camera(run: Path, cfg, ck: dict[str, Any]) -> tuple[dict[str, Any] | None, list[float] | None]:
    """The page's first camera (the first test view, dataset frame) and the scene's up direction (the mean of the
    test cameras' up axes), or (None, None) when the dataset is not at hand."""
    try:
        scene = _scene_for_run(run, cfg, ck, downscale=1.0, split="test")
    except AnisdfError as e:
        log.warning("export: %s; the page starts from a default view", e)
        return None, None
    split = scene.splits.get("test") or scene.splits.get("train") or [0]
    T = np.asarray(ck["to_world"], dtype=np.float64)
    up = -scene.cameras.c2w[split, :, 1].double().mean(0).numpy()  # OpenCV y points down
    up = (T[:3, :3] @ up) / np.linalg.norm(T[:3, :3] @ up)
    cam = _dataset_camera(scene, split[0], ck).to_json()
    return cam, up.tolist()


def export(run: Path, out: Path, faces: int = 200_000, texture: int = 1024, specular_texture: int = 0,
           lobes: int = 3, directions: int = 64, resolution: int = 512, supersample: int = 2,
           pixel_filter: float = 0.6,
           device: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Bake RUN into a real-time asset in OUT (:mod:`anisdf.export.bake`): model.glb, specular_*.png, index.html and
    export.json (settings, file sizes, timings). Returns export.json's content."""
    import time

    from anisdf import __version__
    from anisdf.export import baked_format as fmt
    from anisdf.export.atomic import write_text_atomic
    from anisdf.export.bake import BakeOptions, bake, write_asset
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.export.sg_fit import SHARPNESS_RANGE
    from anisdf.systems.trainer import load_run, pick_device

    if out.exists() and not out.is_dir():
        raise AnisdfError(f"--out {out} is an existing file, not a folder")
    if out.resolve() == run.resolve():
        raise AnisdfError("--out must not be the run folder itself")
    opts = BakeOptions(faces=faces, texture=texture, specular_texture=specular_texture, lobes=lobes,
                       directions=directions, resolution=resolution)
    opts.validate()
    if not 1 <= supersample <= 4:
        raise AnisdfError(f"--supersample must be between 1 and 4, got {supersample}")
    if not 0.0 <= pixel_filter <= 2.0:
        raise AnisdfError(f"--pixel-filter must be between 0 and 2 pixels, got {pixel_filter}")
    dev = pick_device(device or "auto")
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def tick(name: str) -> None:
        now = time.perf_counter()
        timings[name] = round(now - clock[0], 2)
        clock[0] = now

    cfg, model, ck = load_run(run, dev)
    if cfg.appearance.kind != "blend":
        log.info("export: appearance.kind=%s; the lobes are fitted to its colour all the same", cfg.appearance.kind)
    camera, up = _export_camera(run, cfg, ck)
    tick("load")
    mesh = mc(model.geometry.sdf, radius=model.radius, resolution=resolution, device=dev, progress=progress)
    tick("marching_cubes")
    baked = bake(model, mesh, opts, progress=progress, timer=tick)
    manifest: dict[str, Any] = {
        "format": fmt.FORMAT, "version": fmt.VERSION, "anisdf": __version__, "run": str(run.resolve()),
        "step": int(ck["state"]["step"]), "frame": "dataset",
        "faces": len(baked.faces), "vertices": len(baked.vertices), "marching_cubes_resolution": resolution,
        "faces_requested": faces, "texture": opts.texture, "specular_texture": opts.spec_size,
        "lobes": opts.lobes, "directions": opts.directions, "diffuse_directions": opts.diffuse_directions,
        "fit_iters": opts.fit_iters, "sharpness_range": list(SHARPNESS_RANGE), "supersample": supersample,
        "pixel_filter": pixel_filter,
        "diffuse": "view-independent part of the blended colour w c_view + (1 - w) c_ref: the per-texel fit's "
                   "constant term (hemisphere mean with K = 0)",
        "up": up, "camera": camera, "stats": baked.stats,
    }
    sizes = write_asset(out, baked, np.asarray(ck["to_world"]), manifest)
    tick("write")
    manifest.update(files=sizes, total_bytes=int(sum(sizes.values())), timings=timings,
                    seconds=round(sum(timings.values()), 2))
    write_text_atomic(out / fmt.MANIFEST, json.dumps(manifest, indent=2) + "\n")
    log.info("export: %d faces, %d px diffuse, %d px lobes x %d -> %s (%.1f MB: %s) in %.0f s", len(baked.faces),
             opts.texture, opts.spec_size, opts.lobes, out, manifest["total_bytes"] / 1e6,
             ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sizes.items()), manifest["seconds"])
    return manifest
