"""Command line: ``anisdf <command> ...``.

User errors end with exit code 2 and one line (``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from anisdf import __version__
from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's one-line errors (exit code 2): ``anisdf <command>: error: argument --x: ...``."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def int_at_least(low: int) -> Callable[[str], int]:
    """An argparse ``type=``: an integer >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, not {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, not {text!r}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


def float_at_least(low: float, strict: bool = False) -> Callable[[str], float]:
    """An argparse ``type=``: a finite number >= ``low`` (> ``low`` when ``strict``)."""
    bound = f"{'>' if strict else '>='} {low:g}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number {bound}, not {text!r}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"must be a finite number {bound}, not {text!r}")
        return value

    parse.__name__ = f"number {bound}"
    return parse


def count_at_least(low: int) -> Callable[[str], int]:
    """An argparse ``type=``: a count >= ``low``, written as digits or with a k / M suffix (``300k``, ``1.5M``)."""

    def parse(text: str) -> int:
        t = text.strip()
        scale = {"k": 1_000, "m": 1_000_000}.get(t[-1:].lower(), 1)
        try:
            number = float(t[:-1] if scale > 1 else t)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a count >= {low} such as 300000 or 300k, not {text!r}") from None
        value = number * scale
        if not math.isfinite(value) or value != int(value) or value < low:
            raise argparse.ArgumentTypeError(f"must be a whole count >= {low} such as 300000 or 300k, not {text!r}")
        return int(value)

    parse.__name__ = f"count >= {low}"
    return parse


def out_folder(text: str) -> str:
    """An argparse ``type=`` for ``--out``: a folder that may not exist yet, but not an existing file."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is an existing file, not a folder")
    return text


def port_number(text: str) -> int:
    """An argparse ``type=`` for ``--port``: 1 to 65535."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number from 1 to 65535, not {text!r}")
    return value


port_number.__name__ = "port number"


def _add_viewer_args(p: argparse.ArgumentParser, default_port: int | None) -> None:
    p.add_argument("--port", type=port_number, default=default_port,
                   help="viewer port (default 7007; when taken, the next free one, said at start)")
    p.add_argument("--host", default="127.0.0.1", help="viewer address to listen on (0.0.0.0: every interface)")


def _add_config_args(p: argparse.ArgumentParser) -> None:
    from anisdf.config import preset_names

    p.add_argument("--preset", default="auto",
                   help=f"preset name ({', '.join(preset_names())}) or a YAML file; auto (default): nerf-synthetic "
                   "for objects (alpha or masks), mipnerf360 for opaque photos without masks")
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="config overrides, e.g. geometry.kind=single appearance.kind=pe renderer.grid_resolution=64")


def cmd_inspect(args: argparse.Namespace) -> int:
    from anisdf.data.inspect import inspect_dataset

    print(json.dumps(inspect_dataset(Path(args.data)), indent=2))
    return 0


def _without_option(argv: list[str], name: str) -> list[str]:
    """``argv`` without ``name VALUE`` / ``name=VALUE``."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out


def _torchrun(nproc: int, argv: list[str]) -> int:
    """``anisdf train --nproc N``: the same command under ``torchrun --standalone --nproc-per-node N`` (one node)."""
    import shlex
    import subprocess

    if "WORLD_SIZE" in os.environ:
        raise AnisdfError("--nproc: this process is already one rank of a torchrun job; drop --nproc")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}",
           "-m", "anisdf", *_without_option(argv, "--nproc")]
    log.info("launching %s", shlex.join(cmd))
    return subprocess.call(cmd)


def cmd_train(args: argparse.Namespace) -> int:
    from anisdf.tasks.train import train

    if not args.viewer and (args.port is not None or args.host != "127.0.0.1"):
        raise AnisdfError("--port and --host are the viewer's: add --viewer")
    if args.nproc > 1:
        return _torchrun(args.nproc, args.argv)
    rank = int(os.environ.get("RANK", "0"))
    if rank > 0:  # under torchrun rank 0 speaks for the job
        logging.getLogger("anisdf").setLevel(logging.WARNING)
    summary = train(Path(args.data), Path(args.out), preset=args.preset, overrides=args.overrides,
                    max_steps=args.max_steps, max_minutes=args.max_minutes, device=args.device,
                    resume=args.resume, progress=not args.no_progress,
                    viewer_port=(args.port or 7007) if args.viewer else None, viewer_host=args.host)
    if rank == 0:
        print(json.dumps(summary, indent=2))
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from anisdf.viewer.run import view

    view(Path(args.run), port=args.port, host=args.host, device=args.device, max_resolution=args.max_resolution)
    return 0


def cmd_extract_mesh(args: argparse.Namespace) -> int:
    from anisdf.tasks.mesh import extract_mesh

    path = extract_mesh(Path(args.run), resolution=args.resolution, fmt=args.format, device=args.device,
                        remove_floaters=args.remove_floaters, remove_inner=args.remove_inner)
    print(path)
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from anisdf.tasks.render import render

    out = render(Path(args.run), split=args.split, video=args.video, max_views=args.max_views,
                 downscale=args.downscale, device=args.device)
    print(out)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from anisdf.tasks.evaluate import evaluate

    metrics = evaluate(Path(args.run), split=args.split, max_views=args.max_views,
                       gt_mesh=Path(args.gt_mesh) if args.gt_mesh else None, device=args.device,
                       chamfer_points=args.chamfer_points, mesh_resolution=args.mesh_resolution,
                       remove_floaters=args.remove_floaters, remove_inner=args.remove_inner,
                       re_extract=args.re_extract, eval_downscale=args.eval_downscale,
                       normal_mask=args.normal_mask, chamfer_seed=args.chamfer_seed,
                       baked=Path(args.baked) if args.baked else None)
    print(json.dumps(metrics, indent=2))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from anisdf.tasks.export import export

    manifest = export(Path(args.run), Path(args.out), faces=args.faces, texture=args.texture,
                      specular_texture=args.specular_texture, lobes=args.lobes, directions=args.directions,
                      resolution=args.resolution, supersample=args.supersample,
                      pixel_filter=args.pixel_filter, device=args.device,
                      progress=not args.no_progress)
    summary = {k: manifest[k] for k in ("faces", "vertices", "texture", "specular_texture", "lobes", "files",
                                        "total_bytes", "seconds")}
    print(json.dumps(summary, indent=2))
    print(Path(args.out) / "index.html")
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
    from anisdf.tasks.demo import run_demo

    run_demo(Path(args.out), minutes=args.minutes, device=args.device)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from anisdf.benchmarks.speed import run_bench

    run_bench(as_json=args.json, quick=args.quick, data=Path(args.data) if args.data else None,
              minutes=args.minutes, device=args.device, preset=args.preset)
    return 0


def _reproduce_command(args: argparse.Namespace) -> str:
    """The command line of ``anisdf reproduce`` as parsed (for reproduce.md)."""
    import shlex

    parts = ["anisdf", "reproduce", args.table, "--data", args.data, "--out", args.out, "--scale", args.scale]
    for opt in ("scenes", "minutes", "seeds", "max_steps", "max_views", "mesh_resolution", "chamfer_points",
                "dtu_eval", "device", "ray", "cpus_per_run"):
        value = getattr(args, opt)
        if value is not None and value != _REPRODUCE_DEFAULTS.get(opt):
            parts += [f"--{opt.replace('_', '-')}", str(value)]
    return shlex.join(parts + list(args.overrides or []))


_REPRODUCE_DEFAULTS = {"max_views": 0, "mesh_resolution": 512, "chamfer_points": 1_000_000}


def cmd_reproduce(args: argparse.Namespace) -> int:
    from anisdf.errors import AnisdfError
    from anisdf.orchestration.reproduce import reproduce

    try:
        seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else None
    except ValueError:
        raise AnisdfError(f"--seeds must be comma-separated integers, not '{args.seeds}'") from None
    reproduce(args.table, Path(args.data), Path(args.out), scale=args.scale,
              scenes=args.scenes.split(",") if args.scenes else None, minutes=args.minutes, seeds=seeds,
              device=args.device, overrides=args.overrides, max_steps=args.max_steps, max_views=args.max_views,
              mesh_resolution=args.mesh_resolution, chamfer_points=args.chamfer_points,
              dtu_eval=Path(args.dtu_eval) if args.dtu_eval else None, command=_reproduce_command(args),
              progress=not args.no_progress, ray=args.ray, cpus_per_run=args.cpus_per_run)
    print(Path(args.out) / "reproduce.md")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    from anisdf.orchestration.batch import run_batch

    result = run_batch(Path(args.jobs), Path(args.out), ray=args.ray, device=args.device,
                       progress=not args.no_progress)
    failed = [r["name"] for r in result["runs"] if r["status"] != "done"]
    print(Path(args.out) / "batch.json")
    if failed:
        print(f"anisdf: error: {len(failed)} of {len(result['runs'])} jobs did not finish: {', '.join(failed)} "
              "(see batch.json; rerun to retry them)", file=sys.stderr)
        return 1
    return 0


def ray_address(text: str) -> str:
    """An argparse ``type=`` for ``--ray``: local, auto, or a cluster address (not a key=value override)."""
    if "=" in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not a Ray address; put key=value overrides before --ray, or "
                                         "write --ray local")
    return text


def _add_ray_args(s: argparse.ArgumentParser, what: str) -> None:
    s.add_argument("--ray", nargs="?", const="local", default=None, type=ray_address, metavar="auto|ADDRESS",
                   help=f"run the {what} as tasks on Ray: alone (or 'local') starts Ray on this machine, 'auto' joins "
                        "the cluster this machine belongs to, else ray://HOST:10001 or HOST:6379 (anisdf[cluster])")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="anisdf", description="AniSDF: neural surfaces from posed photos.")
    p.add_argument("--version", action="version", version=f"anisdf {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("inspect", help="validate a dataset and print a JSON summary")
    s.add_argument("data", help="dataset folder (format detected automatically)")
    s.set_defaults(fn=cmd_inspect)

    s = sub.add_parser("train", help="reconstruct a scene")
    s.add_argument("data", help="dataset folder")
    s.add_argument("--out", required=True, type=out_folder, help="run folder (checkpoints, logs, renders)")
    s.add_argument("--max-steps", type=int_at_least(1), default=None)
    s.add_argument("--max-minutes", type=float_at_least(0.0), default=None,
                   help="stop cleanly and save after this many minutes of training in all (0: no limit)")
    s.add_argument("--device", default=None, help="auto | cpu | cuda[:N]")
    s.add_argument("--resume", action="store_true", help="continue from RUN/checkpoints/last.pt")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--nproc", type=int_at_least(1), default=1,
                   help="data-parallel ranks on this machine (torchrun --standalone; one per GPU, gloo on CPUs); "
                        "for several machines run torchrun yourself (docs/distributed.md)")
    s.add_argument("--viewer", action="store_true",
                   help="watch it learn in the browser (viser; rendering between steps, not counted as training time)")
    _add_viewer_args(s, default_port=None)
    _add_config_args(s)
    s.set_defaults(fn=cmd_train)

    s = sub.add_parser("view", help="interactive web viewer of a run (finished or training): maps, cameras, mesh")
    s.add_argument("run")
    _add_viewer_args(s, default_port=7007)
    s.add_argument("--max-resolution", type=int_at_least(64), default=512,
                   help="long side in pixels of a resting view (a slider in the page changes it)")
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_view)

    s = sub.add_parser("extract-mesh", help="marching cubes on the SDF -> RUN/mesh.<ext>")
    s.add_argument("run")
    s.add_argument("--resolution", type=int_at_least(2), default=512, help="marching-cubes grid cells per axis")
    s.add_argument("--format", choices=["ply", "obj", "glb"], default="ply")
    s.add_argument("--remove-floaters", action="store_true",
                   help="drop pieces under 1%% of the largest one's faces (default: the mesh is not cleaned)")
    s.add_argument("--remove-inner", action="store_true",
                   help="drop surfaces around pockets enclosed inside the object (no camera outside sees them)")
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_extract_mesh)

    s = sub.add_parser("render", help="render views and maps (normal, depth, c_view, c_ref, w, opacity)")
    s.add_argument("run")
    s.add_argument("--split", default="test")
    s.add_argument("--video", action="store_true", help="also write an orbit video (MP4)")
    s.add_argument("--max-views", type=int_at_least(0), default=0, help="at most this many views (0: all)")
    s.add_argument("--downscale", type=int_at_least(1), default=1)
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_render)

    s = sub.add_parser("eval", help="PSNR, SSIM, normal MAE and Chamfer -> RUN/eval.json + report")
    s.add_argument("run")
    s.add_argument("--split", default="test")
    s.add_argument("--max-views", type=int_at_least(0), default=0, help="at most this many views (0: all)")
    s.add_argument("--eval-downscale", type=float_at_least(0.0, strict=True), default=1.0,
                   help="render and score at the dataset's resolution divided by this (default 1, whatever "
                        "data.downscale training used)")
    s.add_argument("--normal-mask", choices=["refnerf", "alpha"], default="refnerf",
                   help="normal MAE weights: rendered opacity x ground-truth alpha (Ref-NeRF), or the alpha alone")
    s.add_argument("--gt-mesh", default=None, help="reference mesh for the Chamfer distance")
    s.add_argument("--chamfer-points", type=int_at_least(1), default=1_000_000)
    s.add_argument("--chamfer-seed", type=int_at_least(0), default=0,
                   help="seed of the prediction's points (reference: +1)")
    mesh_note = "; the mesh extract-mesh wrote is scored as it is, this must match it (or pass --re-extract)"
    s.add_argument("--mesh-resolution", type=int_at_least(2), default=None,
                   help="marching cubes resolution when eval extracts the mesh (default 512)" + mesh_note)
    s.add_argument("--remove-floaters", action="store_true", default=None,
                   help="clean small pieces when eval extracts the mesh (default: not cleaned)" + mesh_note)
    s.add_argument("--remove-inner", action="store_true", default=None,
                   help="drop enclosed inner shells when eval extracts the mesh (default: kept)" + mesh_note)
    s.add_argument("--re-extract", action="store_true",
                   help="extract a new RUN/mesh.ply (and mesh.json) even when extract-mesh wrote one")
    s.add_argument("--baked", default=None, metavar="DIR",
                   help="also score the asset anisdf export wrote to DIR, rendered as its viewer page draws it "
                        "(baked_psnr, baked_ssim)")
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_eval)

    s = sub.add_parser("export", help="bake a run into a real-time asset: model.glb, specular_*.png, index.html")
    s.add_argument("run")
    s.add_argument("--out", required=True, type=out_folder, help="folder of the asset")
    s.add_argument("--faces", type=count_at_least(4), default=200_000,
                   help="triangle budget of the decimated mesh, e.g. 300k (default 200k)")
    s.add_argument("--texture", type=int_at_least(16), default=1024, help="diffuse texture size in texels (1024)")
    s.add_argument("--specular-texture", type=int_at_least(0), default=0,
                   help="lobe texture size in texels; 0: half of --texture")
    s.add_argument("--lobes", type=int_at_least(0), default=3,
                   help="spherical Gaussian lobes per texel (0: diffuse only; at most 8)")
    s.add_argument("--directions", type=int_at_least(4), default=64,
                   help="reflected directions each texel's lobes are fitted to")
    s.add_argument("--resolution", type=int_at_least(16), default=512, help="marching cubes resolution")
    s.add_argument("--supersample", type=int_at_least(1), default=2,
                   help="the page's default antialiasing: s x s samples per pixel (1-4; eval --baked uses it too)")
    s.add_argument("--pixel-filter", type=float_at_least(0.0), default=0.6,
                   help="sigma in pixels of the Gaussian that filters those samples into pixels (0: each pixel's own "
                        "s x s box); 0.6 matches the path-traced training images best (benchmarks/RESULTS.md)")
    s.add_argument("--device", default=None)
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(fn=cmd_export)

    s = sub.add_parser("chamfer", help="Chamfer distance between two meshes (last line)")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--points", type=int_at_least(1), default=1_000_000)
    s.add_argument("--seed", type=int_at_least(0), default=0)
    s.set_defaults(fn=cmd_chamfer)

    s = sub.add_parser("dtu-chamfer", help="official DTU accuracy / completeness / Chamfer in mm (last line)")
    s.add_argument("mesh")
    s.add_argument("--dtu-root", required=True, help="folder with ObsMask/ and Points/stl/ of the DTU benchmark")
    s.add_argument("--scan", type=int_at_least(0), required=True, help="DTU scan number, e.g. 65")
    s.add_argument("--scale-mat", default=None, help="cameras_sphere.npz whose scale_mat_0 maps the mesh to mm")
    s.add_argument("--mask-cull", default=None, metavar="DATASET_DIR",
                   help="NeuS dataset folder (cameras npz, mask/): cull the mesh with the dilated masks first")
    s.add_argument("--density", type=float_at_least(0.0, strict=True), default=0.2,
                   help="sampling and thinning distance in mm")
    s.add_argument("--max-dist", type=float_at_least(0.0, strict=True), default=20.0,
                   help="distances of this many mm or more are outliers")
    s.add_argument("--seed", type=int_at_least(0), default=0, help="order of the point thinning")
    s.add_argument("--no-stl-thinning", action="store_true",
                   help="score against every STL point (DTUeval-python) instead of thinning them (MATLAB original)")
    s.set_defaults(fn=cmd_dtu_chamfer)

    s = sub.add_parser("process-data", help="camera poses for your own photos or video (pycolmap) -> SCENE")
    s.add_argument("input", help="folder of images, or a video file")
    s.add_argument("--out", required=True, help="scene folder to write (images/, colmap/, transforms.json)")
    s.add_argument("--matcher", choices=["exhaustive", "sequential", "vocab"], default=None,
                   help="image pairs to match (default: sequential for a video, exhaustive for photos)")
    s.add_argument("--max-frames", type=int_at_least(1), default=None,
                   help="keep this many evenly spread images (default: 150 for a video, every photo)")
    s.add_argument("--downscale", type=int_at_least(1), default=1, help="divide the image size by this integer first")
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
    s.add_argument("--out", default="runs/demo", type=out_folder)
    s.add_argument("--minutes", type=float_at_least(0.0, strict=True), default=4.0)
    s.add_argument("--device", default=None)
    s.set_defaults(fn=cmd_demo)

    s = sub.add_parser("bench", help="speed benchmark (encoding, training step, time to quality)")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--quick", action="store_true", help="skip the time-to-PSNR run")
    s.add_argument("--data", default=None, help="scene for time-to-PSNR (default ../shared/data/bunny_plastic)")
    s.add_argument("--minutes", type=float_at_least(0.0, strict=True), default=10.0)
    s.add_argument("--device", default="auto", help="auto (CUDA if available) | cpu | cuda[:N]")
    s.add_argument("--preset", default="cpu-quick", help="configuration of the training-step and time-to-PSNR runs")
    s.set_defaults(fn=cmd_bench)

    from anisdf.eval.paper_tables import TABLES

    s = sub.add_parser("reproduce", help="train and evaluate a table of the paper -> OUT/reproduce.json, .md")
    s.add_argument("table", choices=list(TABLES))
    s.add_argument("--data", required=True, help="dataset root holding the table's scenes, or one scene folder")
    s.add_argument("--out", required=True, type=out_folder,
                   help="folder of the runs and the results (a rerun resumes)")
    s.add_argument("--scale", choices=["paper", "cpu"], default="paper",
                   help="paper: the table's preset; cpu: cpu-quick with the table's data settings, --minutes per run")
    s.add_argument("--scenes", default=None, help="comma-separated scene folder names (default: the paper's)")
    s.add_argument("--minutes", type=float_at_least(0.0), default=None,
                   help="time budget per run (0: none; cpu scale: 10 unless --max-steps is given)")
    s.add_argument("--seeds", default=None, help="comma-separated seeds (train.seed), e.g. 0,1 (default 0)")
    s.add_argument("--max-steps", type=int_at_least(1), default=None,
                   help="steps per run instead of the preset's (step-based: no time budget unless --minutes)")
    s.add_argument("--max-views", type=int_at_least(0), default=0,
                   help="evaluate on at most this many test views (0: all)")
    s.add_argument("--mesh-resolution", type=int_at_least(2), default=512,
                   help="marching cubes resolution for the Chamfer")
    s.add_argument("--chamfer-points", type=int_at_least(1), default=1_000_000)
    s.add_argument("--dtu-eval", default=None,
                   help="folder with DTU's official ObsMask/ and Points/stl/ (default: beside the scenes)")
    s.add_argument("--device", default=None)
    s.add_argument("--no-progress", action="store_true")
    _add_ray_args(s, "runs")
    s.add_argument("--cpus-per-run", type=int_at_least(1), default=None,
                   help="torch threads of each run, and the CPUs each asks of Ray (default: all here, 1 on Ray)")
    s.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for every run")
    s.set_defaults(fn=cmd_reproduce)

    s = sub.add_parser("batch", help="train, mesh and evaluate a list of jobs (JOBS.yaml) -> OUT/NAME, OUT/batch.json")
    s.add_argument("jobs", help="YAML list of {name, data, preset, overrides: [key=value], minutes} (see "
                               "docs/distributed.md)")
    s.add_argument("--out", required=True, type=out_folder, help="folder of the runs and batch.json (a rerun resumes)")
    s.add_argument("--device", default=None)
    s.add_argument("--no-progress", action="store_true")
    _add_ray_args(s, "jobs")
    s.set_defaults(fn=cmd_batch)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
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
