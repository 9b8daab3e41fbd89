"""``anisdf batch``: two tiny jobs one by one here, then on a local Ray with 2 CPUs where one job's worker is killed
mid-run: both runs still finish, with the figures of the local runs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from test_training import TINY

import anisdf
from anisdf.cli import main
from anisdf.eval.paper_tables import METRICS
from anisdf.orchestration import cluster, reproduce

try:
    import ray
except ImportError:
    ray = None
needs_ray = pytest.mark.skipif(ray is None, reason="Ray is not installed (pip install 'anisdf[cluster]'); the batch "
                                                   "runner's Ray path is not tested")

STEPS = 16


def _jobs(scene: Path, folder: Path) -> Path:
    common = {"data": str(scene), "preset": "cpu-quick", "max_steps": STEPS, "max_views": 1, "mesh_resolution": 32,
              "chamfer_points": 2000, "cpus": 1}
    jobs = [{"name": "a", **common, "overrides": [*TINY, "train.ckpt_every=2"]},
            {"name": "b", **common, "overrides": [*TINY, "train.seed=1"]}]
    path = folder / "jobs.yaml"
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(jobs))
    return path


@pytest.fixture(scope="module")
def local_batch(toy_scene, tmp_path_factory) -> tuple[Path, dict]:
    """The two jobs run one by one in this process."""
    root = tmp_path_factory.mktemp("batch")
    jobs = _jobs(toy_scene, root)
    assert main(["batch", str(jobs), "--out", str(root / "local"), "--no-progress"]) == 0
    return jobs, json.loads((root / "local" / "batch.json").read_text())


def test_local_batch_trains_meshes_and_evaluates_each_job(local_batch, tmp_path, monkeypatch):
    jobs, result = local_batch
    out = Path(result["out"])
    assert [r["name"] for r in result["runs"]] == ["a", "b"] and result["ray"] is None
    for r in result["runs"]:
        assert r["status"] == "done" and r["steps"] == STEPS and r["attempts"] == 1
        assert r["psnr"] > 5 and 0 < r["ssim"] <= 1 and r["chamfer"] > 0 and r["normal_mae_deg"] >= 0
        assert (out / r["name"] / "mesh.ply").is_file()
        assert json.loads((out / r["name"] / "eval.json").read_text())["psnr"] == r["psnr"]
    assert result["runs"][0]["psnr"] != result["runs"][1]["psnr"]  # seeds 0 and 1
    # a rerun keeps the finished jobs
    monkeypatch.setattr(cluster, "attempt", lambda *a, **k: pytest.fail("a finished job ran again"))
    assert main(["batch", str(jobs), "--out", str(out), "--no-progress"]) == 0
    assert json.loads((out / "batch.json").read_text())["runs"] == result["runs"]


@pytest.mark.parametrize("content, message", [
    ("- {name: a}", "'data' is missing"),
    ("- {name: a, data: nowhere}", "does not exist"),
    ("- {name: a, data: ., minutes: -1}", "'minutes' must be >= 0"),
    ("- {name: a, data: ., overrides: [x]}", "not of the form key=value"),
    ("- {name: a, data: ., epochs: 3}", "unknown key 'epochs'"),
    ("- {name: a, data: .}\n- {name: a, data: .}", "used twice"),
    ("- {name: ../up, data: .}", "must be a folder name"),
    ("{name: a}", "expected a list of jobs"),
])
def test_bad_jobs_files_get_one_line(tmp_path, capsys, content, message):
    path = tmp_path / "jobs.yaml"
    path.write_text(content)
    assert main(["batch", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_ray_missing_is_a_clear_error(local_batch, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as if not installed
    assert main(["batch", str(local_batch[0]), "--out", str(tmp_path / "out"), "--ray"]) == 2
    assert "pip install 'anisdf[cluster]'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def local_ray():
    src = str(Path(anisdf.__file__).resolve().parents[1])  # the workers import this anisdf
    path = os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])])
    ray.init(num_cpus=2, object_store_memory=100 * 2**20, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})
    yield
    ray.shutdown()


@needs_ray
def test_ray_batch_survives_a_killed_worker(local_batch, local_ray, tmp_path, monkeypatch):
    jobs, local = local_batch
    out = tmp_path / "ray"
    killed: list[int] = []

    def kill_a_once() -> None:
        """Kill job a's worker as soon as it has a checkpoint (SIGKILL: no clean-up, as a lost node)."""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            info = cluster.read_attempt(out / "a")
            if info.get("attempt") == 1 and (out / "a" / "checkpoints" / "last.pt").is_file():
                os.kill(info["pid"], signal.SIGKILL)
                killed.append(info["pid"])
                return
            time.sleep(0.02)

    monkeypatch.setattr(cluster, "PROGRESS_SECONDS", 1.0)
    killer = threading.Thread(target=kill_a_once, daemon=True)
    killer.start()
    assert main(["batch", str(jobs), "--out", str(out), "--ray"]) == 0
    killer.join()
    assert killed, "job a ended before its worker could be killed"
    result = json.loads((out / "batch.json").read_text())
    assert result["ray"] == "local"
    runs = {r["name"]: r for r in result["runs"]}
    assert (runs["a"]["attempts"], runs["b"]["attempts"]) == (2, 1)
    assert cluster.read_attempt(out / "a")["pid"] != killed[0]
    for ours, theirs in zip(result["runs"], local["runs"], strict=True):
        assert ours["status"] == "done" and ours["steps"] == STEPS
        # resumed from its checkpoint, the killed run is the run that was never interrupted (1 thread each)
        for m in METRICS:
            assert ours[m] == pytest.approx(theirs[m], rel=1e-6), (ours["name"], m)


@needs_ray
def test_reproduce_on_ray_writes_the_rows_of_a_local_call(toy_scene, local_ray, tmp_path):
    root = tmp_path / "nerf_synthetic"
    shutil.copytree(toy_scene, root / "lego")
    opts = {"scale": "cpu", "minutes": 0.0, "max_steps": 2, "overrides": TINY, "max_views": 1,
            "mesh_resolution": 32, "chamfer_points": 2000, "progress": False, "seeds": [0, 1], "cpus_per_run": 1}
    here = reproduce.reproduce("nerf-synthetic", root, tmp_path / "here", **opts)
    there = reproduce.reproduce("nerf-synthetic", root, tmp_path / "there", ray="local", **opts)
    assert [(r["scene"], r["seed"]) for r in there["rows"]] == [("lego", 0), ("lego", 1)]  # the table's order
    for a, b in zip(here["rows"], there["rows"], strict=True):
        assert b["status"] == "done" and b["device"] == a["device"]  # on Ray: the worker's (the same CPU here)
        assert {m: b[m] for m in METRICS} == {m: a[m] for m in METRICS}
    assert json.loads((tmp_path / "there" / "reproduce.json").read_text())["rows"] == there["rows"]
