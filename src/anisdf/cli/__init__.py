"""Command line: ``anisdf <command> ...``, one module per command (:data:`COMMANDS`).

A command's module ``anisdf.cli.<name>`` holds its name (``NAME``), its options (``Options``: the task's options
dataclass, extended by what only the command line has; the parser is built from its fields by
:mod:`anisdf.cli.options`) and ``run(opts) -> int``, which makes one library call and prints its result.
Only the module of the command given is imported. User errors end with exit code 2 and one line (``--debug`` shows
the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from types import ModuleType
from typing import Any

from anisdf import __version__
from anisdf.cli.options import _Parser, add_options, cli_fields, read_options
from anisdf.errors import AnisdfError
from anisdf.utils.allocator import tune_malloc

COMMANDS = {
    "inspect": "validate a dataset and print a JSON summary",
    "train": "reconstruct a scene",
    "view": "interactive web viewer of a run (finished or training): maps, cameras, mesh",
    "extract-mesh": "marching cubes on the SDF -> RUN/mesh.<ext>",
    "render": "render views and maps (normal, depth, c_view, c_ref, w, opacity)",
    "eval": "PSNR, SSIM, normal MAE and Chamfer -> RUN/eval.json + report",
    "export": "bake a run into a real-time asset: model.glb, specular_*.png, index.html",
    "materials": "fit a light and a PBR material (base colour, roughness, metallic) -> RUN/materials/",
    "relight": "render the PBR asset under another light -> OUT/",
    "chamfer": "Chamfer distance between two meshes (last line)",
    "dtu-chamfer": "official DTU accuracy / completeness / Chamfer in mm (last line)",
    "process-data": "camera poses for your own photos or video (pycolmap) -> SCENE",
    "demo": "reconstruct the bundled scene on the CPU in a few minutes",
    "bench": "speed benchmark (encoding, training step, time to quality)",
    "reproduce": "train and evaluate a table of the paper -> OUT/reproduce.json, .md",
    "batch": "train, mesh and evaluate a list of jobs (JOBS.yaml) -> OUT/NAME, OUT/batch.json",
}
"""Each command and its line of help, in the order ``anisdf --help`` lists them; command ``x-y`` is the module
``anisdf.cli.x_y`` (imported only when it is the command given, so that ``anisdf --help`` starts no torch)."""

_GLOBAL_HELP = ("-h", "--help")


def command_module(name: str) -> ModuleType:
    """The module of the command ``name``."""
    return importlib.import_module(f"anisdf.cli.{name.replace('-', '_')}")


def _command_in(argv: list[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), or None when the listing of every command
    may be shown (no command, an unknown one, or ``--help`` before it)."""
    for word in argv:
        if word in _GLOBAL_HELP:
            return None
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``anisdf``: every command with its help line, and the arguments of ``command`` (None: of
    none)."""
    p = _Parser(prog="anisdf", description="AniSDF: neural surfaces from posed photos.")
    p.add_argument("--version", action="version", version=f"anisdf {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, help_line in COMMANDS.items():
        parser = sub.add_parser(name, help=help_line)
        if name == command:  # the other commands' arguments are read only when one of them is given
            add_options(parser, command_module(name).Options)
    return p


def parse(argv: list[str]) -> tuple[ModuleType, Any, argparse.Namespace]:
    """The command ``argv`` names, its options, and the parse (``--debug``); argparse's errors exit with code 2."""
    parser = build_parser(_command_in(argv))
    ns, extra = parser.parse_known_args(argv)
    mod = command_module(ns.command)
    if extra:  # key=value overrides may come after options (argparse stops the positional list at them)
        bad = [e for e in extra if e.startswith("-") or "=" not in e]
        if bad or "overrides" not in {f.name for f in cli_fields(mod.Options)}:
            parser.error(f"unrecognized arguments: {' '.join(bad or extra)}")
        ns.overrides = list(ns.overrides or []) + extra
    return mod, read_options(mod.Options, ns, argv=argv), ns


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    mod, opts, ns = parse(argv)
    logging.basicConfig(level=logging.DEBUG if ns.debug else logging.INFO, format="%(message)s")
    tune_malloc()  # before the command's first tensors: later steps reuse the heap instead of fresh pages
    try:
        return int(mod.run(opts) or 0)
    except AnisdfError as e:
        if ns.debug:
            raise
        print(f"anisdf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("anisdf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
