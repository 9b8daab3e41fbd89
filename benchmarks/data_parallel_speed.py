"""Training speed at 1 and 2 data-parallel ranks on this machine (CPU, gloo), on a small synthetic scene.

    python benchmarks/data_parallel_speed.py [--steps 60] [--preset cpu-quick] [--size 64] [--out DIR] [key=value ...]

Runs ``python -m anisdf train SCENE --max-steps N`` as one process with 2 threads, one process with 1 thread, and
``--nproc 2`` (two ranks of 1 thread each: torchrun's default), and reports for each the steps per second and samples
per second of the training loop (run.json's ``train_seconds``, which leaves out start-up; ``n_samples`` of log.jsonl,
counted over all ranks). Each rank has the per-step sample budget of one process, so 2 ranks do twice the work of a
step. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def run(scene: Path, out: Path, steps: int, preset: str, overrides: list[str], threads: int, nproc: int) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    cmd = [sys.executable, "-m", "anisdf", "train", str(scene), "--out", str(out), "--preset", preset,
           "--max-steps", str(steps), "--no-progress", "--nproc", str(nproc), *overrides, "train.log_every=1",
           "train.val_every=0", "train.ckpt_every=0"]
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    info = json.loads((out / "run.json").read_text())
    logs = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    samples = sum(r["n_samples"] for r in logs[10:])  # past the first steps (grid warm-up, thread start)
    seconds = info["train_seconds"] - logs[9]["time"] if len(logs) > 10 else info["train_seconds"]
    return {"ranks": nproc, "threads_per_rank": threads, "steps": info["step"], "world_size": info["world_size"],
            "train_seconds": round(info["train_seconds"], 2),
            "steps_per_s": round((info["step"] - 10) / seconds, 3),
            "samples_per_s": round(samples / seconds), "samples_per_step": round(samples / max(len(logs) - 10, 1))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--preset", default="cpu-quick")
    p.add_argument("--size", type=int, default=64, help="image size of the synthetic scene")
    p.add_argument("--out", default=None, help="folder for the scene and the runs (default: a temporary one)")
    p.add_argument("overrides", nargs="*")
    args = p.parse_args()
    from anisdf.data.synthetic import make_synthetic_scene

    root = Path(args.out or tempfile.mkdtemp(prefix="bench_dist_"))
    scene = make_synthetic_scene(root / "scene", n_train=16, n_test=2, size=args.size, mesh_resolution=48)
    overrides = ["data.downscale=1", *args.overrides]
    rows = [run(scene, root / name, args.steps, args.preset, overrides, threads, nproc)
            for name, threads, nproc in (("one_2t", 2, 1), ("one_1t", 1, 1), ("two_ranks", 1, 2))]
    print(json.dumps({"preset": args.preset, "overrides": overrides, "size": args.size, "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
