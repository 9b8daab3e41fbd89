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


def _scene_for_run(run: Path, cfg, ck: dict[str, Any]):
    from anisdf.data.dataparsers import load_scene

    info_path = run / "run.json"
    data = json.loads(info_path.read_text())["data"] if info_path.is_file() else ck.get("data")
    if not data or not Path(data).exists():
        raise AnisdfError(f"{run}: the dataset this run was trained on ({data}) is no longer there")
    return load_scene(Path(data), downscale=cfg.data.downscale, max_images=cfg.data.max_images,
                      images_dir=cfg.data.images_dir)


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


def train(data: Path, out: Path, preset: str | None = None, overrides: list[str] | None = None,
          max_steps: int | None = None, max_minutes: float | None = None, device: str | None = None,
          resume: bool = False, progress: bool = True) -> dict[str, Any]:
    from anisdf.data.dataparsers import load_scene
    from anisdf.systems.checkpoint import load_checkpoint
    from anisdf.systems.trainer import Trainer, pick_device

    ckpt_path = out / "checkpoints" / "last.pt"
    ck = None
    if resume:
        ck = load_checkpoint(ckpt_path)
        cfg = _resume_config(out, config_from_dict(ck["config"]), preset, overrides or [])
    else:
        if ckpt_path.exists():
            raise AnisdfError(f"{out}: already holds a run; pass --resume to continue it or choose another --out")
        cfg = load_config(preset, overrides)
    if max_steps:
        cfg.train.max_steps = max_steps
        if max_minutes is None and not resume:  # `--max-steps N` alone asks for N steps, not the preset's budget
            cfg.train.max_minutes = 0.0
    if max_minutes is not None:
        cfg.train.max_minutes = max_minutes
    dev = pick_device(device or cfg.train.device)
    scene = load_scene(data, downscale=cfg.data.downscale, max_images=cfg.data.max_images,
                       images_dir=cfg.data.images_dir)
    for w in scene.warnings:
        log.warning("warning: %s", w)
    trainer = Trainer(cfg, scene, out, dev, progress=progress)
    if ck is not None:
        trainer.load_state_dict(ck)
        log.info("resuming %s at step %d", out, trainer.state.step)
    return trainer.fit()


def extract_mesh(run: Path, resolution: int = 512, fmt: str = "ply", device: str | None = None,
                 keep_floaters: bool = False, keep_inner: bool = False, progress: bool = True) -> Path:
    """Marching cubes on the SDF, vertex colours from the view branch, written in the dataset's frame."""
    from anisdf.export.mesh import color_vertices, remove_floaters, save_mesh, to_world
    from anisdf.export.mesh import extract_mesh as mc
    from anisdf.systems.trainer import load_run, pick_device

    dev = pick_device(device or "auto")
    cfg, model, ck = load_run(run, dev)
    mesh = mc(model.geometry.sdf, radius=model.radius, resolution=resolution, device=dev, progress=progress,
              keep_inner=keep_inner)
    if not keep_floaters:
        mesh = remove_floaters(mesh)
    mesh = color_vertices(mesh, model.diffuse_color, device=dev)
    mesh = to_world(mesh, np.asarray(ck["to_world"], dtype=np.float64))
    path = run / f"mesh.{fmt}"
    save_mesh(mesh, path, fmt)
    log.info("mesh: %d vertices, %d faces -> %s", len(mesh.vertices), len(mesh.faces), path)
    return path


def render(run: Path, split: str = "test", video: bool = False, max_views: int = 0, downscale: int = 1,
           device: str | None = None, n_video_frames: int = 60) -> Path:
    """Render every view of a split with its maps into RUN/renders/<split>/, and optionally an orbit video."""
    from tqdm import tqdm

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.export.visualize import depth_to_image, normal_to_image, save_image, scalar_to_image, to_uint8
    from anisdf.systems.rendering import render_view
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
        m = res["maps"]
        fg = m["opacity"][..., 0] > 0.5
        save_image(out_dir / f"{i:03d}_rgb.png", to_uint8(m["rgb"]))
        save_image(out_dir / f"{i:03d}_normal.png", normal_to_image(m["normal"] * fg[..., None]))
        save_image(out_dir / f"{i:03d}_depth.png", depth_to_image(m["depth"][..., 0], mask=fg))
        save_image(out_dir / f"{i:03d}_opacity.png", scalar_to_image(np.clip(m["opacity"][..., 0], 0, 1)))
        for key in ("c_view", "c_ref"):
            if key in m:
                save_image(out_dir / f"{i:03d}_{key}.png", to_uint8(m[key]))
        if "weight" in m:
            save_image(out_dir / f"{i:03d}_weight.png", scalar_to_image(np.clip(m["weight"][..., 0], 0, 1)))
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


def evaluate(run: Path, split: str = "test", max_views: int = 0, gt_mesh: Path | None = None,
             device: str | None = None, chamfer_points: int = 1_000_000, mesh_resolution: int = 512,
             progress: bool = True) -> dict[str, Any]:
    """PSNR / SSIM (and normal MAE where the dataset has normal maps) on a split, Chamfer against ``gt_mesh``;
    writes RUN/eval.json, RUN/eval/ images and a report (protocols: docs/evaluation.md)."""
    from tqdm import tqdm

    from anisdf.data.rays import RayDataset, eval_background
    from anisdf.eval.metrics import chamfer_distance, load_mesh, normal_mae_deg, psnr, ssim
    from anisdf.eval.report import write_report
    from anisdf.export.visualize import save_image
    from anisdf.systems.rendering import panel, render_view
    from anisdf.systems.trainer import load_run, pick_device

    dev = pick_device(device or "auto")
    if gt_mesh is not None:
        gt = load_mesh(gt_mesh)  # fail early on a bad reference mesh
    cfg, model, ck = load_run(run, dev)
    scene = _scene_for_run(run, cfg, ck)
    if not scene.splits.get(split):
        raise AnisdfError(f"split '{split}' is empty for {scene.root}; choose one of {sorted(scene.splits)}")
    data = RayDataset(scene, split, device=dev, background=eval_background(scene))
    ids = scene.splits[split]
    n = len(data) if max_views <= 0 else min(max_views, len(data))
    per_view: list[dict[str, Any]] = []
    images: list[Path] = []
    for i in tqdm(range(n), desc=f"eval {split}", unit="view", disable=not progress):
        res = render_view(model, data, i, scene, cfg.renderer.eval_chunk_rays)
        pred = np.clip(res["maps"]["rgb"], 0.0, 1.0)
        row: dict[str, Any] = {"view": i, "image": scene.image_paths[ids[i]].name,
                               "psnr": psnr(pred, res["gt"]), "ssim": ssim(pred, res["gt"])}
        ref = scene.normals.get(ids[i])
        if ref is not None:
            ref_np = ref.cpu().numpy() if isinstance(ref, torch.Tensor) else np.asarray(ref)
            row["normal_mae_deg"] = normal_mae_deg(res["maps"]["normal"], ref_np[..., :3], ref_np[..., 3] > 0.5)
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
    if gt_mesh is not None:
        mesh_path = extract_mesh(run, resolution=mesh_resolution, device=str(dev), progress=progress)
        cd = chamfer_distance(load_mesh(mesh_path), gt, n_points=chamfer_points, seed=0)
        metrics.update(chamfer=cd["chamfer"], chamfer_accuracy=cd["accuracy"],
                       chamfer_completeness=cd["completeness"], chamfer_points=chamfer_points,
                       gt_mesh=str(gt_mesh), mesh=str(mesh_path))
    metrics.update(steps=int(ck["state"]["step"]), train_seconds=float(ck["state"]["train_seconds"]),
                   preset=cfg.preset)
    (run / "eval.json").write_text(json.dumps({**metrics, "per_view": per_view}, indent=2))
    write_report(run, metrics, per_view, images)
    return metrics
