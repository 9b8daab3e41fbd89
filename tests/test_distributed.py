"""Data-parallel training under torchrun with gloo on 2 CPU processes: one step of 2 ranks is one step of a single
process on the union of the two ranks' rays, and a 2-rank run checkpoints and resumes with 2 ranks (bit-exact) or
with one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import torch.distributed as td
from test_training import TINY

from anisdf.cli import main
from anisdf.config import config_from_dict
from anisdf.data.dataparsers import load_scene
from anisdf.data.rays import RayBatch
from anisdf.model_components.ray_marching import Samples, march
from anisdf.models import anisdf as model_module
from anisdf.training import checkpoint
from anisdf.training.distributed import rank_seed
from anisdf.training.trainer import Trainer

pytestmark = pytest.mark.skipif(not td.is_available() or not td.is_gloo_available(),
                                reason="this torch build has no torch.distributed with gloo")


def _train(scene: Path, out: Path, *extra: str) -> None:
    args = ["train", str(scene), "--out", str(out), "--no-progress", *extra]
    assert main(args) == 0, args


@pytest.fixture(scope="module")
def one_step_run(toy_scene, tmp_path_factory) -> Path:
    """A run of one step with 2 ranks (``anisdf train --nproc 2``, i.e. torchrun with gloo)."""
    run = tmp_path_factory.mktemp("dist") / "two"
    _train(toy_scene, run, "--preset", "cpu-quick", "--max-steps", "1", "--nproc", "2", *TINY)
    return run


def _cat(batches: list[RayBatch]) -> RayBatch:
    def cat(name: str):
        parts = [getattr(b, name) for b in batches]
        return None if parts[0] is None else torch.cat(parts)

    return RayBatch(**{name: cat(name) for name in RayBatch.__dataclass_fields__})


def test_a_two_rank_step_is_one_step_on_the_union_of_their_rays(one_step_run, toy_scene, tmp_path, monkeypatch):
    ck = checkpoint.load_checkpoint(one_step_run / "checkpoints" / "last.pt")
    info = json.loads((one_step_run / "run.json").read_text())
    assert (info["world_size"], info["step"], ck["world_size"], len(ck["rank_generators"])) == (2, 1, 2, 2)
    cfg = config_from_dict(ck["config"])
    scene = load_scene(toy_scene, downscale=cfg.data.downscale)
    one = Trainer(cfg, scene, tmp_path / "one", torch.device("cpu"), progress=False)
    before = {k: v.clone() for k, v in one.model.state_dict().items()}
    # the rays rank r drew (its own stream), then its marching jitter from the same stream, rank 0's rays first
    n = cfg.train.init_rays
    gens = [torch.Generator().manual_seed(rank_seed(cfg.train.seed, r)) for r in range(2)]
    union = _cat([one.train_data.sample(n, g) for g in gens])
    one.next_batch = lambda n_rays: union  # type: ignore[method-assign]

    def march_per_rank(origins, dirs, grid, radius, step, max_samples, generator=None, **kw) -> Samples:
        s = [march(origins[r * n : (r + 1) * n], dirs[r * n : (r + 1) * n], grid, radius, step, max_samples, g)
             for r, g in enumerate(gens)]
        return Samples(torch.cat([s[0].ray_idx, s[1].ray_idx + n]), torch.cat([s[0].t, s[1].t]),
                       torch.cat([s[0].dt, s[1].dt]), 2 * n)

    monkeypatch.setattr(model_module, "march", march_per_rank)
    stats = one.train_step()
    got, want = ck["model"], one.model.state_dict()
    assert got.keys() == want.keys()
    moved = 0
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-5, atol=1e-6, msg=lambda m, k=k: f"{k}: {m}")
        moved += int(not torch.equal(want[k], before[k]))
    assert moved > 10  # the step changed the model
    lines = (one_step_run / "log.jsonl").read_text().splitlines()
    assert len(lines) == 1  # rank 0 alone writes the run folder
    logged = json.loads(lines[0])
    assert logged["n_rays"] == 2 * n and logged["n_samples"] == stats["n_samples"]
    assert logged["total"] == pytest.approx(stats["total"], rel=1e-4)
    assert logged["psnr"] == pytest.approx(stats["psnr"], rel=1e-4)


def test_a_two_rank_run_resumes_exactly_and_with_one_rank(one_step_run, toy_scene, tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    _train(toy_scene, straight, "--preset", "cpu-quick", "--max-steps", "3", "--nproc", "2", *TINY)
    shutil.copytree(one_step_run, resumed)
    _train(toy_scene, resumed, "--resume", "--max-steps", "3", "--nproc", "2")
    a = checkpoint.load_checkpoint(straight / "checkpoints" / "last.pt")
    b = checkpoint.load_checkpoint(resumed / "checkpoints" / "last.pt")
    assert a["state"]["step"] == b["state"]["step"] == 3
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert all(torch.equal(x, y) for x, y in zip(a["rank_generators"], b["rank_generators"], strict=True))
    # the same run goes on in one process: rank 0's grid stream, its rays from that stream
    _train(toy_scene, resumed, "--resume", "--max-steps", "5")
    info = json.loads((resumed / "run.json").read_text())
    assert (info["world_size"], info["step"], info["status"]) == (1, 5, "done")
    c = checkpoint.load_checkpoint(resumed / "checkpoints" / "last.pt")
    assert c["world_size"] == 1 and "rank_generators" not in c


def test_nproc_inside_torchrun_is_refused(toy_scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main(["train", str(toy_scene), "--out", str(tmp_path / "r"), "--nproc", "2"]) == 2
    assert "already one rank of a torchrun job" in capsys.readouterr().err
