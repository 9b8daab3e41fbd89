"""Training on a tiny analytic scene made by the test: quality rises, resume is exact, failures are clean."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from anisdf.cli import main
from anisdf.config import load_config
from anisdf.data.dataparsers import load_scene
from anisdf.data.synthetic import scene_sdf
from anisdf.errors import AnisdfError, TrainingDiverged
from anisdf.training import checkpoint
from anisdf.training.trainer import Trainer, lr_factor

TINY = [
    "geometry.n_levels=8", "geometry.coarse_levels=5", "geometry.coarse_start_levels=3",
    "geometry.level_start_step=40", "geometry.level_every=20",
    "geometry.log2_hashmap_size=14", "geometry.base_resolution=8", "geometry.max_resolution=128",
    "geometry.feature_dim=15", "geometry.hidden_dim=32",
    "appearance.asg_theta=4", "appearance.asg_phi=8", "appearance.par_hidden=32", "appearance.ref_hidden=32",
    "appearance.view_hidden=32", "appearance.weight_hidden=32",
    "renderer.grid_resolution=32", "renderer.march_steps=256", "renderer.samples_per_step=4096",
    "renderer.init_rays=256", "renderer.grid_warmup_steps=32", "renderer.cos_anneal_steps=100",
    "optim.warmup_steps=20", "optim.lr_variance=0.01", "loss.curvature_ramp_steps=50",
    "train.val_every=0", "train.ckpt_every=0", "train.log_every=10", "data.downscale=1", "train.max_minutes=0",
]


def _trainer(scene_dir: Path, out: Path, extra: list[str] | None = None, device: str = "cpu") -> Trainer:
    cfg = load_config("cpu-quick", TINY + (extra or []))
    scene = load_scene(scene_dir, downscale=cfg.data.downscale)
    return Trainer(cfg, scene, out, torch.device(device), progress=False)


def test_training_raises_psnr_and_finds_the_surface(toy_scene, tmp_path):
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=100"])
    first = tr.train_step()["psnr"]
    summary = tr.fit()
    assert summary["status"] == "done" and summary["step"] == 100
    psnr = tr.validate()
    print(f"toy scene: psnr {first:.2f} -> {psnr:.2f} dB in {summary['train_seconds']:.1f} s")
    assert psnr > first + 3.5 and psnr > 20.0, (first, psnr)  # seeds 0-2: +3.8 / +6.0 / +5.8 dB
    # the SDF's zero level lies near the true surface: points on the analytic surface have small |SDF|
    g = torch.Generator().manual_seed(0)
    p = (torch.rand(20000, 3, generator=g) * 2 - 1) * 0.8
    for _ in range(20):  # project onto the analytic surface
        p.requires_grad_(True)
        d = scene_sdf(p)
        (grad,) = torch.autograd.grad(d.sum(), p)
        p = (p - d[:, None] * grad).detach()
    on = p[scene_sdf(p).abs() < 1e-4]
    norm = torch.as_tensor(tr.scene.to_normalised_frame(on.numpy()), dtype=torch.float32)
    with torch.no_grad():
        err = tr.model.geometry.sdf(norm).abs() * tr.scene.scale
    print(f"median |sdf| on the true surface: {float(err.median()):.4f}")
    assert float(err.median()) < 0.03, float(err.median())
    assert (tmp_path / "run" / "checkpoints" / "last.pt").is_file()
    assert (tmp_path / "run" / "log.jsonl").read_text().count("\n") >= 10


def test_resume_continues_exactly(toy_scene, tmp_path):
    a = _trainer(toy_scene, tmp_path / "a", ["train.max_steps=8"])
    a.fit()
    b = _trainer(toy_scene, tmp_path / "b", ["train.max_steps=8"])
    b.fit(max_steps=4)
    c = _trainer(toy_scene, tmp_path / "b", ["train.max_steps=8"])
    c.load_state_dict(checkpoint.load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt"))
    assert c.state.step == 4
    c.fit()
    sa, sc = a.model.state_dict(), c.model.state_dict()
    assert sa.keys() == sc.keys()
    for k in sa:
        assert torch.equal(sa[k], sc[k]), k


class _FakeClock:
    """A machine of a chosen speed: each training step takes ``seconds_per_step`` of this clock's time."""

    def __init__(self, trainer: Trainer, seconds_per_step: float) -> None:
        self.now = 0.0
        step = trainer.train_step

        def timed_step() -> dict[str, float]:
            self.now += seconds_per_step
            return step()

        trainer.train_step = timed_step  # type: ignore[method-assign]
        trainer.clock = self

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize("seconds_per_step,steps", [(6.0, 10), (3.0, 20)])
def test_a_time_budget_lays_the_schedule_on_time(toy_scene, tmp_path, seconds_per_step, steps):
    """With ``--max-minutes`` the schedule advances with the budget spent: a slow and a fast machine both end at the
    deadline with every level on, the cos anneal done and the learning rate decayed; the fast one uses its time for
    more steps, not fewer minutes."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=1000", "train.max_minutes=1", "optim.warmup_steps=2"])
    _FakeClock(tr, seconds_per_step)
    lrs = []
    step = tr.train_step
    tr.train_step = lambda: (lambda st: (lrs.append(st["lr"]), st)[1])(step())  # type: ignore[method-assign]
    summary = tr.fit()
    assert summary["status"] == "done" and summary["step"] == steps
    assert summary["train_seconds"] == pytest.approx(60.0) and summary["schedule_step"] == 1000
    assert all(b.n_active == b.n_levels for b in tr.model.geometry.branches)
    assert tr.model.cos_anneal == 1.0
    base = tr.cfg.optim.lr
    # decayed towards final_lr_factor = 0.1 at the deadline (the first step is the warm-up's 1%)
    assert lrs[-1] < 0.2 * base and lrs[-1] == min(lrs[1:])
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["status"] == "done" and run["schedule"] == "time" and run["step"] == steps


def test_the_warm_up_lasts_its_optimiser_steps_under_a_time_budget(toy_scene, tmp_path):
    """A slow machine's budget runs many schedule steps an optimiser step; the learning-rate warm-up still spans
    ``optim.warmup_steps`` optimiser steps (and as many schedule steps), while the decay follows the schedule."""
    cfg = load_config("cpu-quick", ["optim.warmup_steps=100", "train.max_steps=1500"])
    for k in (10, 50, 99):  # 10 schedule steps an optimiser step: the schedule's decay, the optimiser's warm-up
        assert lr_factor(10 * k, cfg, k) == pytest.approx(lr_factor(10 * k, cfg) * (0.01 + 0.99 * k / 100))
    for k in (0, 5):  # both still warming up: the optimiser steps are the fewer
        assert lr_factor(10 * k, cfg, k) == pytest.approx(lr_factor(k, cfg))
    assert lr_factor(30, cfg, 200) == lr_factor(30, cfg)  # a fast machine: the schedule's warm-up is the longer
    assert lr_factor(1500, cfg, 150) == pytest.approx(cfg.optim.final_lr_factor)  # warm, and decayed to the end
    assert lr_factor(1500, cfg, 50) == pytest.approx(cfg.optim.final_lr_factor * (0.01 + 0.99 * 0.5))
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=1000", "train.max_minutes=1"])  # warm-up 20 steps
    _FakeClock(tr, 6.0)  # 100 schedule steps an optimiser step
    lrs = []
    step = tr.train_step
    tr.train_step = lambda: (lambda st: (lrs.append(st["lr"]), st)[1])(step())  # type: ignore[method-assign]
    tr.fit()
    base, decay = tr.cfg.optim.lr, tr.cfg.optim.final_lr_factor
    assert lrs[5] <= base * (0.01 + 0.99 * 5 / 20)  # the sixth step is a quarter into the warm-up, not past it
    assert lrs[-1] < base * decay**0.8 * (0.01 + 0.99 * 9 / 20)  # nine of its 20 steps: decayed, still warming


def test_short_budgets_probe_the_thread_count_sooner(toy_scene, tmp_path, monkeypatch):
    """The thread tuner's first probe waits out 20 steps of a 10-minute budget but only 4 of a 90-s one, where a busy
    core's first steps at the wrong count would eat a third of the budget; step budgets do not tune at all."""
    import anisdf.training.trainer as trainer_module
    from anisdf.training.cpu_threads import ThreadTuner

    warmups = []

    class Spy(ThreadTuner):
        def __init__(self, max_threads: int, **kwargs) -> None:
            warmups.append(kwargs.get("warmup"))
            super().__init__(max_threads, **kwargs)

    monkeypatch.setattr(trainer_module, "ThreadTuner", Spy)
    for minutes in (1.5, 10.0):
        _trainer(toy_scene, tmp_path / f"run{minutes}", [f"train.max_minutes={minutes}"]).fit(max_steps=1)
    _trainer(toy_scene, tmp_path / "steps", ["train.max_steps=1"]).fit()
    assert warmups == [4, 20]


def test_the_sharpness_learns_per_schedule_step_under_a_time_budget(toy_scene, tmp_path):
    """``optim.lr_variance`` is a rate per schedule step: under a budget the variance group's learning rate is
    multiplied by the schedule steps each optimiser step advances (6 s a step of a 60 s budget laid over 25
    schedule steps: 2.5; at most 4); without a budget it is the rate itself."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=25", "train.max_minutes=1"])
    _FakeClock(tr, 6.0)
    ratios = []
    step = tr.train_step

    def recorded() -> dict[str, float]:
        stats = step()
        model_lr, var_lr = (g["lr"] for g in tr.opt.param_groups[:2])
        ratios.append(var_lr / model_lr)
        return stats

    tr.train_step = recorded  # type: ignore[method-assign]
    assert tr.fit()["step"] == 10
    o = tr.cfg.optim
    assert ratios[0] == pytest.approx(o.lr_variance / o.lr)  # nothing spent yet: pace 1
    assert ratios[1:] == pytest.approx([2.5 * o.lr_variance / o.lr] * 9)
    fast = _trainer(toy_scene, tmp_path / "fast", ["train.max_steps=1000", "train.max_minutes=1"])
    _FakeClock(fast, 6.0)  # 100 schedule steps a step: held at 4
    fast.fit(max_steps=3)
    assert fast.opt.param_groups[1]["lr"] / fast.opt.param_groups[0]["lr"] == pytest.approx(4 * o.lr_variance / o.lr)
    plain = _trainer(toy_scene, tmp_path / "steps", ["train.max_steps=3"])
    plain.fit()
    assert plain.opt.param_groups[1]["lr"] / plain.opt.param_groups[0]["lr"] == pytest.approx(o.lr_variance / o.lr)


def test_a_first_kernel_build_is_not_spent_from_the_budget(toy_scene, tmp_path):
    """The lazily built hash-grid kernel loads before the budget's clock starts: a one-minute first build on a new
    machine leaves the schedule and the step count of a 1-minute budget as they are."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=1000", "train.max_minutes=1"])
    clock = _FakeClock(tr, 6.0)
    loaded = []
    sdf = tr.model.geometry.sdf

    def first_query_builds(x):  # the first SDF query of the process pays for the build
        if not loaded:
            loaded.append(clock.now)
            clock.now += 60.0
        return sdf(x)

    tr.model.geometry.sdf = first_query_builds  # type: ignore[method-assign]
    summary = tr.fit()
    assert loaded == [0.0]
    assert summary["status"] == "done" and summary["step"] == 10 and summary["train_seconds"] == pytest.approx(60.0)


def test_a_resumed_time_budget_continues_its_schedule(toy_scene, tmp_path):
    """Stopped half-way through its budget, a run resumes where its schedule stood (not from the start) and ends at
    the deadline."""
    a = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=1000", "train.max_minutes=1"])
    _FakeClock(a, 6.0)
    assert a.fit(max_steps=5)["status"] == "stopped"
    assert a.state.schedule_step == 400 and a.state.train_seconds == pytest.approx(30.0)  # read before step 5
    b = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=1000", "train.max_minutes=1"])
    b.load_state_dict(checkpoint.load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt"))
    _FakeClock(b, 6.0)
    seen = []
    step = b.train_step
    b.train_step = lambda: (lambda st: (seen.append(st["schedule_step"]), st)[1])(step())  # type: ignore[method-assign]
    summary = b.fit()
    assert seen == [500, 600, 700, 800, 900]
    assert summary["status"] == "done" and summary["step"] == 10 and summary["schedule_step"] == 1000


def test_steps_without_a_budget_stay_bit_exact(toy_scene, tmp_path):
    """No budget: the schedule is the step count (a stopped run's resume equals an uninterrupted run, above)."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=3"])
    summary = tr.fit()
    assert summary["status"] == "done" and summary["schedule_step"] == 2 and tr.state.step == 3
    assert json.loads((tmp_path / "run" / "run.json").read_text())["schedule"] == "steps"


def test_a_step_prunes_by_its_query_while_the_last_step_pruned_little(toy_scene, tmp_path, monkeypatch):
    """renderer.prune_after_query_below: a step skips the SDF-only pruning pass when the step before pruned less
    than that fraction of its samples (a new run starts with the pass); the fraction is part of the checkpoint."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=6"])
    seen, render = [], tr.model.render_rays
    monkeypatch.setattr(tr.model, "render_rays",
                        lambda *a, **k: (seen.append((k["prune_after_query"], tr.state.pruned)), render(*a, **k))[1])
    for _ in range(6):
        tr.train_step()
    assert seen[0] == (False, 1.0)
    assert all(after == (pruned < tr.cfg.renderer.prune_after_query_below) for after, pruned in seen)
    assert sum(after for after, _ in seen) >= 3  # the toy's first steps hide almost nothing
    resumed = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=6"])
    resumed.load_state_dict(tr.state_dict())
    assert resumed.state.pruned == tr.state.pruned < 1.0


def test_resume_of_a_checkpoint_from_another_device_kind_warns_and_goes_on(toy_scene, tmp_path, caplog):
    """A CUDA run's random stream (its generator lives on the GPU) does not fit a CPU generator: the run resumes
    from the seed with a warning instead of failing."""
    a = _trainer(toy_scene, tmp_path / "a", ["train.max_steps=2"])
    a.fit()
    ck = checkpoint.load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")
    ck["generator"] = torch.zeros(16, dtype=torch.uint8)  # the size of a CUDA (Philox) generator state
    b = _trainer(toy_scene, tmp_path / "a", ["train.max_steps=4"])
    with caplog.at_level("WARNING", logger="anisdf"):
        b.load_state_dict(ck)
    assert "another kind of device" in caplog.text
    assert b.state.step == 2 and b.model.step_int == 2
    assert b.fit()["step"] == 4


def test_a_step_reads_the_device_only_where_shapes_depend_on_data(toy_scene, tmp_path, monkeypatch):
    """On a GPU every read of a device value waits for the queue to drain, and the step is launch-bound there
    (benchmarks/RESULTS.md). Forward and backward may read only the sample selections (one ``nonzero`` per march
    chunk, the pruning and the visible set); the step's numbers come back in one ``tolist`` after backward, and
    the sample counts that set the next batch are known on the host. (The CPU optimiser reads its step counters;
    CUDA's fused one does not, and is left out.)"""
    import anisdf.models.anisdf as model_module
    from anisdf.benchmarks.opcount import count_step

    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=10", "renderer.early_stop_eps=1e-3"])
    tr.model.one_pass_pruning = ("cpu", "cuda")  # the GPU's pruning pass (CPU training prunes front to back)
    monkeypatch.setattr(model_module, "kernel_for", lambda t: None)  # the GPU's march (the CPU kernel reads nothing)
    for _ in range(3):
        tr.train_step()
    c = count_step(tr)
    reads = {k: n for k, n in c.host_reads.items() if k[0] != "optimizer"}
    # one march chunk, the pruned selection, the visible samples; then the step's numbers
    assert reads == {("forward", "nonzero"): 3, ("after backward", "tolist"): 1}, reads
    assert sum(n for (phase, _), n in c.kernels.items() if phase == "backward") > 100  # the counter saw backward


def test_same_seed_same_result(toy_scene, tmp_path):
    runs = []
    for name in ("x", "y"):
        t = _trainer(toy_scene, tmp_path / name, ["train.max_steps=3"])
        t.fit()
        runs.append(t.model.geometry.branches[0].grid.table.detach().clone())
    assert torch.equal(runs[0], runs[1])


def test_the_sharpness_stays_under_its_cap_and_can_come_back_down(toy_scene, tmp_path):
    """``renderer.inv_s_max`` bounds the NeuS sharpness by projecting its parameter after each step: at a learning
    rate that drives it up fast it sits at the cap instead of running past it, and the parameter, not only the
    clamped value, stays there, so that a gradient pointing down moves it at once."""
    cap = 25.0  # inv_s starts at exp(3) = 20.1
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=12", "optim.lr_variance=0.2",
                                                 f"renderer.inv_s_max={cap}"])
    v = tr.model.variance
    seen = []
    for _ in range(12):
        tr.train_step()
        seen.append(float(v()))
    assert max(seen) <= cap * (1 + 1e-5) and max(seen) > 0.9 * cap, seen  # it reached the cap and stayed under
    assert float(v.variance) * v.scale <= np.log(cap) + 1e-5  # the parameter itself is held at the cap
    with torch.enable_grad():
        (-v()).backward()  # d(-s)/dv < 0 at the cap: the gradient is not cut by the clamp
    assert float(v.variance.grad) < 0


def test_nan_loss_stops_with_clear_message_and_keeps_checkpoint(toy_scene, tmp_path):
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=2"])
    tr.fit()
    ck = tmp_path / "run" / "checkpoints" / "last.pt"
    before = ck.read_bytes()
    with torch.no_grad():
        tr.model.variance.variance.fill_(float("nan"))
    with pytest.raises(TrainingDiverged, match="last good checkpoint"):  # caught by the loss or the save guard
        tr.fit(max_steps=5)
    assert ck.read_bytes() == before
    assert checkpoint.load_checkpoint(ck)["state"]["step"] == 2


def test_a_vanished_surface_stops_with_a_clear_message(toy_scene, tmp_path):
    """An SDF positive everywhere leaves the occupancy grid empty and no ray a sample: the run stops, saying so,
    instead of training on nothing."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=5"])
    with torch.no_grad():
        for b in tr.model.geometry.branches:
            b.layers[-1].bias[0] += 10.0
    with pytest.raises(TrainingDiverged, match="surface vanished") as err:
        tr.train_step()
    assert "schedule steps an optimiser step" not in str(err.value)
    # under a time budget of few steps the schedule was compressed: the message says so, and what gives it more
    short = _trainer(toy_scene, tmp_path / "short", ["train.max_steps=1000", "train.max_minutes=1"])
    short.state.step, short.state.train_seconds = 16, 9.6  # 160 schedule steps in 16: 10 a step
    with torch.no_grad():
        for b in short.model.geometry.branches:
            b.layers[-1].bias[0] += 10.0
    with pytest.raises(TrainingDiverged, match=r"10 schedule steps an optimiser step.*longer --max-minutes"):
        short.train_step()


def test_checkpoint_write_failure_keeps_previous(tmp_path, monkeypatch):
    path = tmp_path / "ck.pt"
    checkpoint.atomic_save({"a": 1}, path)

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(AnisdfError, match="No space left.*previous one is kept"):
        checkpoint.atomic_save({"a": 2}, path)
    monkeypatch.undo()
    assert checkpoint.load_checkpoint(path) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["ck.pt"]


def test_cli_train_resume_and_errors(toy_scene, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", str(toy_scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "2",
            "--no-progress", *TINY]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["step"] == 2
    assert main(args) == 2  # refuses to overwrite a run
    assert "--resume" in capsys.readouterr().err
    assert main(["train", str(toy_scene), "--out", str(out), "--resume", "--max-steps", "3", "--no-progress"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 3
    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "r2"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]
    assert main(["train", str(toy_scene), "--out", str(tmp_path / "r3"), "geometry.bogus=1"]) == 2
    assert "unknown config key" in capsys.readouterr().err


def test_resume_accepts_the_runs_own_preset_and_refuses_a_changed_setting(toy_scene, tmp_path, capsys):
    out = tmp_path / "run"
    start = ["train", str(toy_scene), "--out", str(out), "--no-progress"]
    assert main([*start, "--preset", "cpu-quick", "--max-steps", "2", *TINY]) == 0
    capsys.readouterr()
    # The same preset and overrides again, plus a train.* change: accepted.
    assert main([*start, "--resume", "--max-steps", "3", "--preset", "cpu-quick", *TINY, "train.log_every=5"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 3
    assert yaml.safe_load((out / "config.yaml").read_text())["train"]["log_every"] == 5
    # An unchanged setting alone (no preset), spelled as the user would: accepted.
    assert main([*start, "--resume", "--max-steps", "4", "geometry.hidden_dim=32", "geometry.base_resolution=8.0"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 4
    for extra, key in [(["geometry.hidden_dim=64"], "geometry.hidden_dim"),
                       (["--preset", "cpu-quick", *TINY, "appearance.kind=pe"], "appearance.kind"),
                       # the preset without the run's overrides (its downscale, capped by data.min_size, agrees)
                       (["--preset", "cpu-quick"], "geometry.n_levels"),
                       (["--preset", "nerf-synthetic", *TINY], "preset")]:
        assert main([*start, "--resume", "--max-steps", "5", *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--resume: {key}" in err[0] and "config.yaml" in err[0], err
    assert json.loads((out / "run.json").read_text())["step"] == 4  # a refused resume trains nothing


def test_a_run_records_the_downscale_min_size_gave_and_resumes_with_its_preset(toy_scene, tmp_path, capsys):
    """cpu-quick halves images but keeps 256 px on the longer side (data.min_size): the 32 px toy scene trains at
    full size, config.yaml says so (eval and resume read it), and the same preset and overrides resume the run."""
    out = tmp_path / "run"
    start = ["train", str(toy_scene), "--out", str(out), "--no-progress", "--preset", "cpu-quick"]
    assert main([*start, "--max-steps", "1", *TINY, "data.downscale=2"]) == 0
    saved = yaml.safe_load((out / "config.yaml").read_text())["data"]
    assert saved["downscale"] == 1.0 and saved["min_size"] == 256
    capsys.readouterr()
    assert main([*start, "--resume", "--max-steps", "2", *TINY, "data.downscale=2"]) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 2
    assert main([*start, "--resume", "--max-steps", "3", *TINY, "data.downscale=2", "data.min_size=0"]) == 2
    assert "--resume: data.downscale is 1.0" in capsys.readouterr().err


def test_loss_dict_has_every_term(toy_scene, tmp_path):
    tr = _trainer(toy_scene, tmp_path / "run", ["loss.curvature_ramp_steps=0", "loss.mask=0.1"])
    stats = tr.train_step()
    for key in ("rgb", "eikonal", "curvature", "orientation", "entropy", "total"):
        assert key in stats and np.isfinite(stats[key]), key


def test_the_interior_prior_trains_and_resumes_exactly(toy_scene, tmp_path, monkeypatch):
    from anisdf.models import anisdf as model_module

    monkeypatch.setattr(model_module, "INTERIOR_EVERY", 2)  # depths at every 2nd grid update, from the start
    monkeypatch.setattr(model_module, "INTERIOR_STEPS", 1)  # the term at every step
    extra = ["train.max_steps=10", "loss.interior=0.1", "loss.interior_start=0", "renderer.grid_update_every=2"]
    a = _trainer(toy_scene, tmp_path / "a", extra)
    a.fit()
    b = _trainer(toy_scene, tmp_path / "b", extra)
    b.fit(max_steps=5)
    c = _trainer(toy_scene, tmp_path / "b", extra)
    c.load_state_dict(checkpoint.load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt"))
    c.fit()
    sa, sc = a.model.state_dict(), c.model.state_dict()
    assert "interior.depth" in sc and sa.keys() == sc.keys()
    for k in sa:
        assert torch.equal(sa[k], sc[k]), k
    assert float(a.model.interior.depth.max()) > 0 and np.isfinite(a.train_step()["interior"])


def test_fast_backend_without_a_kernel_stops_before_training(toy_scene, tmp_path, monkeypatch):
    """encoding_backend=fast where the device has no fast kernel: a clear error before any step or file."""
    monkeypatch.setenv("ANISDF_NO_KERNEL", "1")
    with pytest.raises(AnisdfError, match="encoding_backend=fast.*ANISDF_NO_KERNEL"):
        _trainer(toy_scene, tmp_path / "run", ["geometry.encoding_backend=fast"])
    assert not (tmp_path / "run").exists()


def test_mixed_precision_step_trains_and_keeps_the_sdf_in_float32(toy_scene, tmp_path):
    """bf16 autocast (train.amp=true on CUDA) run on CPU: the same code path, so dtype slips show up without a GPU."""
    tr = _trainer(toy_scene, tmp_path / "run", ["train.max_steps=60"])
    tr.use_amp = True
    first = tr.train_step()
    for _ in range(59):
        stats = tr.train_step()
    assert all(np.isfinite(v) for v in stats.values()), stats
    assert stats["psnr"] > first["psnr"] + 2, (first["psnr"], stats["psnr"])
    batch = tr.train_data.sample(64, torch.Generator().manual_seed(1))
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        sdf, feat = tr.model.geometry(torch.zeros(5, 3))
        out = tr.model.render_rays(batch.origins, batch.directions, batch.background)
    assert sdf.dtype == feat.dtype == torch.float32
    assert out.rgb.dtype == out.opacity.dtype == torch.float32


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_compiled_heads_give_the_eager_gradients(toy_scene, tmp_path, device):
    """train.compile=true: the compiled SDF MLPs, radiance field and opacity train the same as the eager code
    (on CUDA too, where inductor writes Triton kernels instead of C++)."""
    grads, stats = [], []
    for name, extra in (("eager", []), ("compiled", ["train.compile=true"])):
        tr = _trainer(toy_scene, tmp_path / name, ["train.max_steps=10", *extra], device=device)
        tr.opt.step = lambda: None  # keep the gradients of the first step, with the parameters unchanged
        stats.append(tr.train_step())
        stats.append(tr.train_step())  # a second sample count: the graphs are dynamic, not re-specialised
        grads.append({n: p.grad.clone() for n, p in tr.model.named_parameters() if p.grad is not None})
    for fn in (tr.model.color_fn, tr.model.alpha_fn):
        assert fn.compiled is not None and fn.compiled_calls == 2, f"{fn.name}: the compiled path did not run"
    sdf_fn = tr.model.geometry.mlp_fn  # 2 branches; normals in both steps, curvature from step 1 (its ramp starts at 0)
    assert sdf_fn.compiled is not None and sdf_fn.compiled_calls == 6, "the SDF MLPs: the compiled path did not run"
    assert stats[1]["n_samples"] != stats[0]["n_samples"] or stats[1]["n_rays"] != stats[0]["n_rays"]
    for a, b in zip(stats[:2], stats[2:], strict=True):
        assert a["total"] == pytest.approx(b["total"], rel=1e-4)
    assert grads[0].keys() == grads[1].keys()
    for n, g in grads[0].items():
        scale = float(g.abs().max()) + 1e-12
        assert float((g - grads[1][n]).abs().max()) <= 1e-3 * scale, n


def test_a_head_that_cannot_compile_runs_eagerly_with_one_warning(monkeypatch, caplog):
    from anisdf.model_components import compiled

    def broken_compile(fn, dynamic):  # noqa: ANN001, ANN202  (a machine without a working compiler)
        def run(*args):  # noqa: ANN002, ANN202
            raise RuntimeError("no C++ compiler found")
        return run

    monkeypatch.setattr(compiled.torch, "compile", broken_compile)
    head = compiled.Compiled(lambda x: x * 2.0, "the test head")
    with caplog.at_level("WARNING", logger="anisdf"):
        assert torch.equal(head(torch.ones(3)), torch.full((3,), 2.0))
        assert torch.equal(head(torch.ones(2)), torch.full((2,), 2.0))
    assert caplog.text.count("torch.compile of the test head failed") == 1
    assert "no C++ compiler found" in caplog.text
    # an error of the inputs is the caller's: it comes from the eager code, unchanged
    bad = compiled.Compiled(lambda x: x.view(7), "the test head")
    with pytest.raises(RuntimeError, match="shape"):
        bad(torch.ones(3))
