"""``anisdf bench``'s time-to-PSNR run trains as ``anisdf train --max-minutes M`` does."""

from __future__ import annotations

from pathlib import Path

from anisdf.benchmarks.speed import time_to_psnr
from anisdf.data.dataparsers import load_scene
from anisdf.data.synthetic import make_synthetic_scene


def test_time_to_psnr_lays_the_schedule_on_its_minutes(tmp_path: Path) -> None:
    """cpu-quick's schedule is laid on time: within the bench's minutes it must run to its end (levels, annealing,
    learning-rate decay), not stay at its first position because the bench drives the steps itself. The position is
    the one the last step started at: one step of a loaded 2-core machine can take a fifth of these 4.8 s (a fresh
    clone's suite read 1197 of 1500 once), hence half the schedule as the bound, which a stuck schedule (0) misses."""
    scene = load_scene(make_synthetic_scene(tmp_path / "s", n_train=6, n_test=2, size=24, mesh_resolution=32))
    res = time_to_psnr(scene, minutes=0.08, n_views=1, eval_every_s=2.0)
    assert res["schedule_step"] >= 0.5 * res["schedule_steps"]
    assert res["curve"] and res["curve"][-1][0] >= 0.08 * 60 - 1e-6
