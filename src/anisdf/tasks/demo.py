"""``anisdf demo``: reconstruct the bundled glossy bunny on the CPU in about five minutes, then mesh, evaluate and
render it, and print the report."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from anisdf.utils.options import float_at_least, option

log = logging.getLogger("anisdf")

# cpu-quick on the bundled 128 px images (below its data.min_size, so not halved), its schedule laid on the demo's
# time budget.
DEMO_OVERRIDES = ["train.val_every=250", "train.ckpt_every=250"]


@dataclass(kw_only=True)
class DemoOptions:
    """``anisdf demo``'s training time and device."""

    minutes: float = option(4.0, "training time budget in minutes", float_at_least(0.0, strict=True))
    device: str | None = option(None, "auto | cpu | cuda[:N]")


def demo_scene() -> Path:
    """The bundled scene's folder (NeRF-synthetic format, see demo/bunny_plastic/SOURCES.md)."""
    return Path(str(resources.files("anisdf").joinpath("demo", "bunny_plastic")))


def run_demo(out: Path, options: DemoOptions | None = None, **changes: Any) -> dict:
    """Train the bundled bunny into OUT/run (resuming a run there), evaluate, render and print the report; returns
    the evaluation's figures. ``changes`` replace fields of ``options``."""
    from anisdf.run_dir import RunDir
    from anisdf.tasks.evaluate import evaluate
    from anisdf.tasks.render import render
    from anisdf.tasks.train import train

    o = dataclasses.replace(options or DemoOptions(), **changes)
    minutes, device = o.minutes, o.device
    out = Path(out)
    data = demo_scene()
    run = out / "run"
    rd = RunDir(run)
    resume = rd.has_checkpoint()
    log.info("demo: training on the bundled glossy bunny (%s) for %.1f minutes, preset cpu-quick -> %s",
             data, minutes, run)
    train(data, run, preset=None if resume else "cpu-quick", overrides=[] if resume else DEMO_OVERRIDES,
          max_minutes=minutes, device=device, resume=resume)
    metrics = evaluate(run, gt_mesh=data / "gt_mesh.ply", chamfer_points=200_000, mesh_resolution=256,
                       re_extract=True, device=device)  # a mesh of this run's last step, written beside it
    renders = render(run, split="test", video=True, max_views=4, device=device, n_video_frames=36)
    report = rd.report_md
    print("\n" + report.read_text().split("## Per view")[0].strip())
    print("\nanisdf demo finished")
    print(f"  test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.3f}, normal MAE "
          f"{metrics.get('normal_mae_deg', float('nan')):.2f} deg, Chamfer {metrics.get('chamfer', float('nan')):.4f}")
    print(f"  mesh:    {rd.mesh('ply')}")
    print(f"  renders: {renders} (rgb, normal, c_view, c_ref, weight w) and {rd.orbit_video}")
    print(f"  report:  {rd.report_html}")
    return metrics
