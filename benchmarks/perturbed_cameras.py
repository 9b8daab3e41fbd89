"""Camera refinement on a NeuS/DTU capture whose cameras were perturbed on purpose.

    python benchmarks/perturbed_cameras.py /work/shared/data/dtu_scan65 [--work DIR] [--steps 1500]

Writes a copy of the dataset (images and masks linked, ``cameras_sphere.npz`` rewritten) in which every training
camera (the held-out test cameras keep their true pose: they score every run) is
rotated by ``--rot-deg`` about a random axis through its centre and moved by ``--move`` times its distance from the
``scale_mat`` centre in a random direction (a fixed ``--seed``), then trains three cpu-quick runs of ``--steps``
steps: the clean cameras, the perturbed ones as given (``cameras.refine=off``) and the perturbed ones refined
(``cameras.refine=on``); scores each on the test split under both camera protocols of ``anisdf eval --cameras``
(``given``: the true test poses; ``fit``: each test pose fitted to its image with the scene frozen, which takes out
the small rigid motion of the whole rig that the training photos cannot fix) and prints a table: test PSNR / SSIM
under each, and the training cameras' errors against the clean cameras, as given and as refined
(RUN/refined_cameras.json): rotation (deg), centre (% of the camera distance), and the reprojection error (px at the
dataset's resolution: the mean image displacement of points in the object's sphere, which is what a render sees; a
turn about the camera centre and a sideways move shift a distant object's image alike, so the first two can stay
large while the image fits). Runs already done in ``--work`` are reused.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from cpu_quick_runs import train_and_score
from scipy.spatial.transform import Rotation

from anisdf.data.dataparsers import parse_dataset
from anisdf.data.dataparsers.neus import decompose_projection, find_npz
from anisdf.run_dir import RunDir


def perturb(data: Path, out: Path, rot_deg: float, move: float, seed: int, which: set[int]) -> None:
    """``out``: ``data`` with the cameras ``which`` of its ``cameras_sphere.npz`` rotated and moved (see the module
    doc); the others (the held-out test views) keep their true pose, so that every run is scored by the same
    cameras."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("image", "mask"):
        if (data / name).is_dir() and not (out / name).exists():
            (out / name).symlink_to((data / name).resolve())
    npz = find_npz(data)
    if npz is None:
        raise SystemExit(f"{data}: not a NeuS dataset (no cameras_sphere.npz)")
    rng = np.random.default_rng(seed)
    with np.load(npz) as z:
        cams = {k: np.asarray(z[k]) for k in z.files}
    i = 0
    while f"world_mat_{i}" in cams:
        world = cams[f"world_mat_{i}"].astype(np.float64)
        if i not in which:
            i += 1
            continue
        K, c2w = decompose_projection(world)
        center = cams[f"scale_mat_{i}"][:3, 3]
        axis = rng.normal(size=3)
        rot = Rotation.from_rotvec(np.radians(rot_deg) * axis / np.linalg.norm(axis)).as_matrix()
        step = rng.normal(size=3)
        dist = np.linalg.norm(c2w[:3, 3] - center)
        c2w[:3, :3] = c2w[:3, :3] @ rot
        c2w[:3, 3] += move * dist * step / np.linalg.norm(step)
        P = np.eye(4)
        P[:3, :4] = K @ np.linalg.inv(c2w)[:3, :4]
        cams[f"world_mat_{i}"] = P.astype(world.dtype)
        i += 1
    tmp = out / f".{npz.stem}.{os.getpid()}.npz"  # atomic: several runs may share the copy
    np.savez(tmp, **cams)
    os.replace(tmp, out / npz.name)


def rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[N] angles (deg) between rotations ``a`` and ``b`` ([N,3,3])."""
    cos = (np.einsum("nij,nij->n", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_errors(c2w: np.ndarray, clean: np.ndarray, center: np.ndarray, idx: list[int]) -> tuple[float, float]:
    """Mean rotation error (deg) and mean centre error (% of the camera distance) over the cameras ``idx``."""
    rot = rotation_deg(c2w[idx, :3, :3], clean[idx, :3, :3])
    dist = np.linalg.norm(clean[idx, :3, 3] - center, axis=-1)
    move = np.linalg.norm(c2w[idx, :3, 3] - clean[idx, :3, 3], axis=-1) / dist
    return float(rot.mean()), float(100.0 * move.mean())


def reprojection_px(c2w: np.ndarray, clean: np.ndarray, intrinsics: np.ndarray, to_world: np.ndarray,
                    idx: list[int], n: int = 4000) -> float:
    """Mean displacement (px) of ``n`` points drawn uniformly in the object's sphere (the unit sphere of the
    normalised frame, mapped by ``to_world``) between their images in ``c2w`` and in ``clean`` (dataset-frame 4x4
    camera-to-world, OpenCV axes) through ``intrinsics`` ([N,4] fx, fy, cx, cy), over the cameras ``idx``."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, 3))
    x *= rng.uniform(size=(n, 1)) ** (1 / 3) / np.linalg.norm(x, axis=1, keepdims=True)
    x = x @ np.asarray(to_world)[:3, :3].T + np.asarray(to_world)[:3, 3]

    def image(pose: np.ndarray, k: np.ndarray) -> np.ndarray:
        cam = (x - pose[:3, 3]) @ pose[:3, :3]
        return k[:2] * cam[:, :2] / cam[:, 2:] + k[2:]

    return float(np.mean([np.linalg.norm(image(c2w[i], intrinsics[i]) - image(clean[i], intrinsics[i]), axis=1).mean()
                          for i in idx]))


def run_one(data: Path, out: Path, steps: int, refine: str, eval_downscale: float,
            overrides: list[str]) -> dict[str, dict]:
    """Train (unless done) and score a run under each camera protocol; returns ``{protocol: eval.json}`` (kept as
    ``RUN/eval_cameras_<protocol>.json``)."""
    evals = {f"cameras_{p}": {"cameras": p, "eval_downscale": eval_downscale} for p in ("given", "fit")}
    scores = train_and_score(data, out, steps, [*overrides, f"cameras.refine={refine}"], evals)
    return {p: scores[f"cameras_{p}"] for p in ("given", "fit")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--work", type=Path, default=None, help="folder of the perturbed copy and the runs (default: "
                    "a new temporary folder, kept)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--rot-deg", type=float, default=1.0)
    ap.add_argument("--move", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-downscale", type=float, default=2.0)
    ap.add_argument("--runs", default="clean,perturbed,refined", help="which of clean,perturbed,refined to run")
    ap.add_argument("--set", nargs="*", default=[], metavar="key=value", help="config overrides of every run")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="perturbed_cameras_"))
    noisy = work / "data_perturbed"
    clean_parsed = parse_dataset(a.data)
    perturb(a.data, noisy, a.rot_deg, a.move, a.seed, set(clean_parsed.splits["train"]))
    noisy_parsed = parse_dataset(noisy)
    clean = clean_parsed.c2w
    center = np.asarray(clean_parsed.to_world)[:3, 3]
    train_idx = list(clean_parsed.splits["train"])
    plan = {"clean": (a.data, "off"), "perturbed": (noisy, "off"), "refined": (noisy, "on")}
    rows = []
    for name in a.runs.split(","):
        data, refine = plan[name]
        scores = run_one(data, work / f"run_{name}", a.steps, refine, a.eval_downscale, a.set)
        ev, fit = scores["given"], scores["fit"]
        row = {"run": name, "cameras": "clean" if data == a.data else "perturbed", "refine": refine,
               "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "psnr_fit": fit.get("psnr"),
               "ssim_fit": fit.get("ssim"), "steps": ev.get("steps"), "train_seconds": ev.get("train_seconds")}
        poses = noisy_parsed.c2w if name != "clean" else clean
        refined = RunDir(work / f"run_{name}").refined_cameras
        if refine == "on" and refined.is_file():
            by_name = {c["image"]: c["refined"] for c in json.loads(refined.read_text())["cameras"]}
            poses = poses.copy()
            for i, path in enumerate(noisy_parsed.image_paths):
                poses[i] = by_name.get(path.relative_to(noisy).as_posix(), poses[i])
        row["rot_err_deg"], row["move_err_pct"] = pose_errors(poses, clean, center, train_idx)
        row["reproj_px"] = reprojection_px(poses, clean, clean_parsed.intrinsics, clean_parsed.to_world, train_idx)
        rows.append(row)
    print(f"work folder: {work}")
    print(f"{'run':10s} {'cameras':9s} {'refine':6s} {'PSNR':>7s} {'SSIM':>6s} {'PSNR fit':>8s} {'SSIM fit':>8s} "
          f"{'rot deg':>8s} {'move %':>7s} {'px':>6s} {'steps':>5s} {'minutes':>7s}")
    for r in rows:
        print(f"{r['run']:10s} {r['cameras']:9s} {r['refine']:6s} {r['psnr']:7.2f} {r['ssim']:6.3f} "
              f"{r['psnr_fit']:8.2f} {r['ssim_fit']:8.3f} {r['rot_err_deg']:8.3f} {r['move_err_pct']:7.3f} "
              f"{r['reproj_px']:6.2f} {r['steps']:5d} {r['train_seconds'] / 60:7.1f}")
    (work / "table.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
