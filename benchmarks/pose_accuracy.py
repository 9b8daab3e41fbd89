"""Camera poses of ``anisdf process-data`` against a dataset's given cameras.

    python benchmarks/pose_accuracy.py path/to/dtu_scan65 [--out /tmp/dtu65_sfm] [--matcher exhaustive]

Runs process-data on the dataset's images alone (``image/`` or ``images/``), reads the given cameras with
anisdf's own parser (NeuS ``cameras_sphere.npz``, LLFF ``poses_bounds.npy``, ...), aligns the estimated camera
centres to the given ones with a similarity (Umeyama, ``pycolmap.estimate_sim3d``) and prints a table: images
registered, rotation error (deg), camera-centre error in % of the cameras' spread (mean distance of the given
centres from their centroid), focal length error, and, for NeuS data, how the sparse-point bounding sphere
compares with the dataset's ``scale_mat`` sphere. ``--reuse`` compares an existing output without running SfM;
``--video`` first encodes the images as a video (one frame each) and processes that with the sequential matcher.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from anisdf.data.dataparsers import parse_dataset
from anisdf.data.dataparsers._common import image_size
from anisdf.data.process import process_data


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0))))


def make_video(images: Path, video: Path, fps: int = 10) -> int:
    """Encode the sorted images of ``images`` as an H.264 video, one frame each; returns the frame count."""
    import imageio_ffmpeg
    from PIL import Image

    paths = sorted(p for p in images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    size = Image.open(paths[0]).size
    writer = imageio_ffmpeg.write_frames(str(video), size, fps=fps, quality=8, macro_block_size=1)
    writer.send(None)
    for p in paths:
        writer.send(np.ascontiguousarray(np.asarray(Image.open(p).convert("RGB"))))
    writer.close()
    return len(paths)


def compare(data: Path, scene: Path, from_video: bool = False) -> dict[str, float | int | str]:
    """Errors of the process-data cameras in ``scene`` against the given cameras of ``data``; with
    ``from_video`` the k-th frame (``frame_0000k``) is the k-th image by name."""
    import pycolmap

    truth = parse_dataset(data)
    est = parse_dataset(scene)
    by_name = {p.name: i for i, p in enumerate(truth.image_paths)}
    if from_video:
        order = sorted(range(len(truth.image_paths)), key=lambda i: truth.image_paths[i].name)
        by_name = {f"frame_{k + 1:05d}.png": i for k, i in enumerate(order)}
    pairs = [(i, by_name[p.name]) for i, p in enumerate(est.image_paths) if p.name in by_name]
    ie, it = (np.array(v) for v in zip(*pairs, strict=True))
    sim = pycolmap.estimate_sim3d(est.c2w[ie, :3, 3], truth.c2w[it, :3, 3])
    if sim is None:
        raise RuntimeError("similarity alignment failed")
    rot = sim.rotation.matrix()
    rot_err = np.array([rotation_deg(rot @ est.c2w[a, :3, :3], truth.c2w[b, :3, :3]) for a, b in pairs])
    centres = truth.c2w[it, :3, 3]
    aligned = sim.scale * est.c2w[ie, :3, 3] @ rot.T + sim.translation
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean())
    centre_err = np.linalg.norm(aligned - centres, axis=1) / spread * 100.0
    # focal lengths in the pixels of the given images
    w_truth = truth.size[0] if truth.size else image_size(truth.image_paths[0])[0]
    w_est = est.size[0] if est.size else image_size(est.image_paths[0])[0]
    f_est = est.intrinsics[ie, 0] * w_truth / w_est
    focal_err = np.abs(f_est / truth.intrinsics[it, 0] - 1.0) * 100.0
    out: dict[str, float | int | str] = {
        "registered": f"{len(pairs)}/{len(truth.image_paths)}",
        "rotation_median_deg": float(np.median(rot_err)),
        "rotation_max_deg": float(rot_err.max()),
        "centre_median_pct": float(np.median(centre_err)),
        "centre_max_pct": float(centre_err.max()),
        "focal_median_pct": float(np.median(focal_err)),
    }
    if truth.to_world is not None and est.to_world is not None:  # NeuS scale_mat sphere vs the sparse-point one
        c_est = sim.scale * rot @ est.to_world[:3, 3] + sim.translation
        r_est = sim.scale * est.to_world[0, 0]
        r_true = float(truth.to_world[0, 0])
        out["sphere_centre_offset_pct_of_radius"] = float(np.linalg.norm(c_est - truth.to_world[:3, 3]) / r_true
                                                           * 100.0)
        out["sphere_radius_ratio"] = float(r_est / r_true)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="dataset with given cameras and an image/ or images/ folder")
    p.add_argument("--out", type=Path, default=None, help="scene folder for process-data (default /tmp/...)")
    p.add_argument("--matcher", default="exhaustive")
    p.add_argument("--camera-model", default="simple_radial")
    p.add_argument("--refine-principal-point", action="store_true")
    p.add_argument("--reuse", action="store_true", help="compare an existing --out without running process-data")
    p.add_argument("--json", action="store_true")
    p.add_argument("--video", action="store_true",
                   help="encode the images as a video first (one frame each) and process that (sequential matcher)")
    args = p.parse_args(argv)
    images = next((args.data / d for d in ("image", "images") if (args.data / d).is_dir()), None)
    if images is None:
        print(f"{args.data}: no image/ or images/ folder", file=sys.stderr)
        return 2
    out = args.out or Path("/tmp") / f"process_data_{args.data.name}"
    summary = None
    t0 = time.perf_counter()
    if not args.reuse and args.video:
        out.mkdir(parents=True, exist_ok=True)
        n = make_video(images, out / "input.mp4")
        summary = process_data(out / "input.mp4", out, matcher="sequential", max_frames=n,
                               camera_model=args.camera_model, refine_principal_point=args.refine_principal_point)
    elif not args.reuse:
        summary = process_data(images, out, matcher=args.matcher, camera_model=args.camera_model,
                               refine_principal_point=args.refine_principal_point)
    elif (out / "process_data.json").is_file():
        summary = json.loads((out / "process_data.json").read_text())
    result = compare(args.data, out, from_video=args.video)
    if summary is not None:
        result["mean_reprojection_error_px"] = summary["mean_reprojection_error_px"]
        result["points"] = summary["n_points"]
        result["process_data_s"] = summary["seconds"]["total"]
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    how = "video, sequential" if args.video else args.matcher
    print(f"\n{args.data.name}: process-data ({how}, {args.camera_model}) vs given cameras "
          f"({time.perf_counter() - t0:.0f} s)\n")
    print("| metric | value |\n|---|---|")
    for k, v in result.items():
        print(f"| {k} | {v:.3f} |" if isinstance(v, float) else f"| {k} | {v} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
