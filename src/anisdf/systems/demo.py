"""``anisdf demo``: reconstruct the bundled analytic scene on the CPU, then mesh, render and evaluate it."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("anisdf")

# cpu-quick on the bundled 96 px scene, with the schedule compressed to what ~4 minutes on 2 cores reach.
DEMO_OVERRIDES = [
    "data.downscale=1", "train.max_steps=400", "geometry.level_start_step=100", "geometry.level_every=50",
    "renderer.cos_anneal_steps=200", "loss.curvature_ramp_steps=200", "optim.warmup_steps=50",
    "train.val_every=100", "train.ckpt_every=100",
]


def run_demo(out: Path, minutes: float = 4.0, device: str | None = None) -> dict:
    from anisdf.data.synthetic import make_synthetic_scene
    from anisdf.systems.commands import evaluate, render, train

    out = Path(out)
    data = out / "data"
    if not (data / "transforms_test.json").is_file():
        log.info("demo: rendering the bundled analytic scene into %s", data)
        make_synthetic_scene(data)
    run = out / "run"
    resume = (run / "checkpoints" / "last.pt").is_file()
    log.info("demo: training for up to %.1f minutes (preset cpu-quick) -> %s", minutes, run)
    train(data, run, preset=None if resume else "cpu-quick",
          overrides=None if resume else DEMO_OVERRIDES,
          max_minutes=minutes, device=device, resume=resume)
    metrics = evaluate(run, gt_mesh=data / "gt_mesh.ply", chamfer_points=200_000, mesh_resolution=256,
                       device=device)
    renders = render(run, split="test", video=True, max_views=4, device=device, n_video_frames=36)
    print("\nanisdf demo finished")
    print(f"  test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.3f}, normal MAE "
          f"{metrics.get('normal_mae_deg', float('nan')):.2f} deg, Chamfer {metrics.get('chamfer', float('nan')):.4f}")
    print(f"  mesh:    {run / 'mesh.ply'}")
    print(f"  renders: {renders} and {run / 'renders' / 'orbit.mp4'}")
    print(f"  report:  {run / 'report.html'}")
    return metrics
