"""Options of a task, declared once as dataclass fields: default, help, and how a command line's text is read.

A task (``anisdf.tasks.*``) declares its options as a dataclass whose fields are made with :func:`option` (or
:func:`positional`); the command line (``anisdf.cli``) builds its parser from those fields, and a Python user fills
the same dataclass. The default and the help text therefore live in one place.

The value readers (:func:`int_at_least` ...) turn the text of a command-line value into a checked value, raising
``ValueError`` with a message that finishes the sentence "--name: ..." (argparse shows it as one line).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

Reader = Callable[[str], Any]


def option(default: Any, help: str, parse: Reader | None = None, *, choices: Sequence[str] | None = None,
           metavar: str | None = None, flag: str | None = None, cli: bool = True) -> Any:
    """A dataclass field with a command-line option ``--name`` (``flag`` overrides the name). A ``bool`` default
    False makes a switch. ``cli=False``: the field is the library's only (a callback, a progress flag set by the
    command itself)."""
    meta = {"help": help, "parse": parse, "choices": tuple(choices) if choices else None, "metavar": metavar,
            "flag": flag, "cli": cli}
    if isinstance(default, list | dict | set):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def positional(help: str, parse: Reader | None = None, *, metavar: str | None = None, nargs: str | None = None,
               default: Any = dataclasses.MISSING) -> Any:
    """A dataclass field given on the command line by position (``anisdf eval RUN``)."""
    meta = {"help": help, "parse": parse, "positional": True, "metavar": metavar, "nargs": nargs, "cli": True}
    if isinstance(default, list):
        return dataclasses.field(default_factory=list, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _named(name: str, fn: Reader) -> Reader:
    fn.__name__ = name  # argparse names the reader in its messages
    return fn


def int_at_least(low: int) -> Reader:
    """An integer >= ``low``."""

    def read(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise ValueError(f"must be an integer >= {low}, not {text!r}") from None
        if value < low:
            raise ValueError(f"must be an integer >= {low}, not {text!r}")
        return value

    return _named(f"integer >= {low}", read)


def float_at_least(low: float, strict: bool = False) -> Reader:
    """A finite number >= ``low`` (> ``low`` when ``strict``)."""
    bound = f"{'>' if strict else '>='} {low:g}"

    def read(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"must be a number {bound}, not {text!r}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise ValueError(f"must be a finite number {bound}, not {text!r}")
        return value

    return _named(f"number {bound}", read)


def count_at_least(low: int) -> Reader:
    """A count >= ``low``, as digits or with a k / M suffix (``300k``, ``1.5M``)."""

    def read(text: str) -> int:
        t = text.strip()
        scale = {"k": 1_000, "m": 1_000_000}.get(t[-1:].lower(), 1)
        try:
            number = float(t[:-1] if scale > 1 else t)
        except ValueError:
            raise ValueError(f"must be a count >= {low} such as 300000 or 300k, not {text!r}") from None
        value = number * scale
        if not math.isfinite(value) or value != int(value) or value < low:
            raise ValueError(f"must be a whole count >= {low} such as 300000 or 300k, not {text!r}")
        return int(value)

    return _named(f"count >= {low}", read)


def out_folder(text: str) -> Path:
    """A folder that may not exist yet, but not an existing file."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{text} is an existing file, not a folder")
    return path


def port_number(text: str) -> int:
    """A TCP port, 1 to 65535."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 1 <= value <= 65535:
        raise ValueError(f"must be a port number from 1 to 65535, not {text!r}")
    return value


def comma_list(item: Reader = str) -> Reader:
    """Comma-separated values, each read by ``item`` (``0,1,2``)."""

    def read(text: str) -> list[Any]:
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts:
            raise ValueError(f"must be a comma-separated list, not {text!r}")
        try:
            return [item(p) for p in parts]
        except ValueError:
            raise ValueError(f"must be comma-separated {getattr(item, '__name__', 'values')}s, not {text!r}") from None

    return _named("comma-separated list", read)


port_number.__name__ = "port number"
out_folder.__name__ = "folder"
