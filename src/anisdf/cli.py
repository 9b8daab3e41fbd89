"""Command line: ``anisdf <command> ...``.

User errors end with exit code 2 and one line (``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from anisdf import __version__
from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")


def _add_config_args(p: argparse.ArgumentParser) -> None:
    from anisdf.config import preset_names

    p.add_argument("--preset", default=None, help=f"preset name ({', '.join(preset_names())}) or a YAML file")
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="config overrides, e.g. geometry.kind=single appearance.kind=pe renderer.grid_resolution=64")


def cmd_inspect(args: argparse.Namespace) -> int:
    from anisdf.data.inspect import inspect_dataset

    print(json.dumps(inspect_dataset(Path(args.data)), indent=2))
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from anisdf.systems.commands import train

    summary = train(Path(args.data), Path(args.out), preset=args.preset, overrides=args.overrides,
                    max_steps=args.max_steps, max_minutes=args.max_minutes, device=args.device,
                    resume=args.resume, progress=not args.no_progress)
    print(json.dumps(summary, indent=2))
    return 0


def cmd_extract_mesh(args: argparse.Namespace) -> int:
    from anisdf.systems.commands import extract_mesh

    path = extract_mesh(Path(args.run), resolution=args.resolution, fmt=args.format, device=args.device,
                        keep_floaters=args.keep_floaters, keep_inner=args.keep_inner)
    print(path)
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from anisdf.systems.commands import render

    out = render(Path(args.run), split=args.split, video=args.video, max_views=args.max_views,
                 downscale=args.downscale, device=args.device)
    print(out)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from anisdf.systems.commands import evaluate

    metrics = evaluate(Path(args.run), split=args.split, max_views=args.max_views,
                       gt_mesh=Path(args.gt_mesh) if args.gt_mesh else None, device=args.device,
                       chamfer_points=args.chamfer_points, mesh_resolution=args.mesh_resolution)
    print(json.dumps(metrics, indent=2))
    return 0


def cmd_chamfer(args: argparse.Namespace) -> int:
    from anisdf.eval.metrics import chamfer_main

    value = chamfer_main(args.a, args.b, n_points=args.points, seed=args.seed)
    print(f"{value:.6f}")
    return 0


def cmd_dtu_chamfer(args: argparse.Namespace) -> int:
    from anisdf.eval.dtu import dtu_chamfer, mask_cull_inputs

    mask_cull = mask_cull_inputs(args.mask_cull) if args.mask_cull else None
    r = dtu_chamfer(args.mesh, args.dtu_root, args.scan, scale_mat=args.scale_mat, mask_cull=mask_cull,
                    density=args.density, max_dist=args.max_dist, seed=args.seed, thin_stl=not args.no_stl_thinning)
    for key, value in r.items():
        if key not in ("accuracy", "completeness", "chamfer"):
            print(f"{key}: {value}")
    print(f"accuracy {r['accuracy']:.3f} completeness {r['completeness']:.3f} chamfer {r['chamfer']:.3f}")
    return 0


def cmd_process_data(args: argparse.Namespace) -> int:
    from anisdf.data.process import process_data, summary_line

    summary = process_data(Path(args.input), Path(args.out), matcher=args.matcher, max_frames=args.max_frames,
                           downscale=args.downscale, camera_model=args.camera_model, vocab_tree=args.vocab_tree,
                           force_undistort=args.undistort, refine_principal_point=args.refine_principal_point,
                           progress=not args.no_progress)
    print(json.dumps(summary, indent=2))
    print(summary_line(summary))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from anisdf.systems.demo import run_demo

    run_demo(Path(args.out), minutes=args.minutes, device=args.device)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from anisdf.systems.bench import run_bench

    run_bench(as_json=args.json, quick=args.quick, data=Path(args.data) if args.data else None,
              minutes=args.minutes, device=args.device, preset=args.preset)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="anisdf", description="AniSDF: neural surfaces from posed photos.")
    p.add_argument("--version", action="version", version=f"anisdf {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("inspect", help="validate a dataset and print a JSON summary")
    s.add_argument("data", help="dataset folder (format detected automatically)")
    s.set_defaults(fn=cmd_inspect)

    s = sub.add_parser("train", help="reconstruct a scene")
    s.add_argument("data", help="dataset folder")
    s.add_argument("--out", required=True, help="run folder (checkpoints, logs, renders)")
    s.add_argument("--max-steps", type=int, default=None)
    s.add_argument("--max-minutes", type=float, default=None,
                   help="stop cleanly and save after this many minutes of training in all (0: no limit)")
    s.add_argument("--device", default=None, help="auto | cpu | cuda[:N]")
    s.add_argument("--resume", action="store_true", help="continue from RUN/checkpoints/last.pt")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_config_args(s)
    s.set_defaults(fn=cmd_train)

    s = sub.add_parser("extract-mesh", help="marching cubes on the SDF -> RUN/mesh.<ext>")
    s.add_argument("run")
    s.add_argument("--resolution", type=int, default=512)
    s.add_argument("--format", choices=["ply", "obj", "glb"], default="ply")
    s.add_argument("--keep-floaters", action="store_true", help="keep small disconnected pieces")
    s.add_argument("--keep-inner", action="store_true",
                   help="keep surfaces around pockets enclosed inside the object (no camera outside sees them)")
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_extract_mesh)

    s = sub.add_parser("render", help="render views and maps (normal, depth, c_view, c_ref, w, opacity)")
    s.add_argument("run")
    s.add_argument("--split", default="test")
    s.add_argument("--video", action="store_true", help="also write an orbit video (MP4)")
    s.add_argument("--max-views", type=int, default=0)
    s.add_argument("--downscale", type=int, default=1)
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_render)

    s = sub.add_parser("eval", help="PSNR, SSIM, normal MAE and Chamfer -> RUN/eval.json + report")
    s.add_argument("run")
    s.add_argument("--split", default="test")
    s.add_argument("--max-views", type=int, default=0)
    s.add_argument("--gt-mesh", default=None, help="reference mesh for the Chamfer distance")
    s.add_argument("--chamfer-points", type=int, default=1_000_000)
    s.add_argument("--mesh-resolution", type=int, default=512)
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_eval)

    s = sub.add_parser("chamfer", help="Chamfer distance between two meshes (last line)")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--points", type=int, default=1_000_000)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(fn=cmd_chamfer)

    s = sub.add_parser("dtu-chamfer", help="official DTU accuracy / completeness / Chamfer in mm (last line)")
    s.add_argument("mesh")
    s.add_argument("--dtu-root", required=True, help="folder with ObsMask/ and Points/stl/ of the DTU benchmark")
    s.add_argument("--scan", type=int, required=True, help="DTU scan number, e.g. 65")
    s.add_argument("--scale-mat", default=None, help="cameras_sphere.npz whose scale_mat_0 maps the mesh to mm")
    s.add_argument("--mask-cull", default=None, metavar="DATASET_DIR",
                   help="NeuS dataset folder (cameras npz, mask/): cull the mesh with the dilated masks first")
    s.add_argument("--density", type=float, default=0.2, help="sampling and thinning distance in mm")
    s.add_argument("--max-dist", type=float, default=20.0, help="distances of this many mm or more are outliers")
    s.add_argument("--seed", type=int, default=0, help="order of the point thinning")
    s.add_argument("--no-stl-thinning", action="store_true",
                   help="score against every STL point (DTUeval-python) instead of thinning them (MATLAB original)")
    s.set_defaults(fn=cmd_dtu_chamfer)

    s = sub.add_parser("process-data", help="camera poses for your own photos or video (pycolmap) -> SCENE")
    s.add_argument("input", help="folder of images, or a video file")
    s.add_argument("--out", required=True, help="scene folder to write (images/, colmap/, transforms.json)")
    s.add_argument("--matcher", choices=["exhaustive", "sequential", "vocab"], default=None,
                   help="image pairs to match (default: sequential for a video, exhaustive for photos)")
    s.add_argument("--max-frames", type=int, default=None,
                   help="keep this many evenly spread images (default: 150 for a video, every photo)")
    s.add_argument("--downscale", type=int, default=1, help="divide the image size by this integer first")
    s.add_argument("--camera-model", default="simple_radial",
                   help="COLMAP camera model: simple_radial, radial, opencv, pinhole, ... (others are undistorted)")
    s.add_argument("--vocab-tree", default=None, help="COLMAP vocabulary tree file for --matcher vocab")
    s.add_argument("--undistort", action="store_true", help="write undistorted pinhole images even when anisdf "
                   "could model the distortion")
    s.add_argument("--refine-principal-point", action="store_true",
                   help="free the principal point in a last bundle adjustment (lenses with an off-centre one)")
    s.add_argument("--no-progress", action="store_true", help="no progress bars")
    s.set_defaults(fn=cmd_process_data)

    s = sub.add_parser("demo", help="reconstruct the bundled scene on the CPU in a few minutes")
    s.add_argument("--out", default="runs/demo")
    s.add_argument("--minutes", type=float, default=4.0)
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_demo)

    s = sub.add_parser("bench", help="speed benchmark (encoding, training step, time to quality)")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--quick", action="store_true", help="skip the time-to-PSNR run")
    s.add_argument("--data", default=None, help="scene for time-to-PSNR (default ../shared/data/bunny_plastic)")
    s.add_argument("--minutes", type=float, default=10.0)
    s.add_argument("--device", default="auto", help="auto (CUDA if available) | cpu | cuda[:N]")
    s.add_argument("--preset", default="cpu-quick", help="configuration of the training-step and time-to-PSNR runs")
    s.set_defaults(fn=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # key=value overrides may come after options (argparse stops the positional list at them)
        bad = [e for e in extra if e.startswith("-") or "=" not in e]
        if bad or not hasattr(args, "overrides"):
            parser.error(f"unrecognized arguments: {' '.join(bad or extra)}")
        args.overrides = list(args.overrides or []) + extra
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.INFO, format="%(message)s")
    try:
        return int(args.fn(args) or 0)
    except AnisdfError as e:
        if args.debug:
            raise
        print(f"anisdf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("anisdf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
