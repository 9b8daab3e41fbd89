"""A command's argparse parser built from its options dataclass, and the dataclass filled back from the parse.

A command's options are the fields of a dataclass made with :func:`anisdf.utils.options.option` and
:func:`~anisdf.utils.options.positional` (the task's ``XOptions``, extended in the command's file by options only the
command line has). Each field becomes one argument:

- ``option``: ``--name`` (``flag`` overrides it); a field without a default is required; a ``bool`` field (default
  False, or ``bool | None`` with default None) is a switch; ``cli=False`` fields are the library's only;
- ``positional``: by position; variable-length ones (``nargs`` ``*``/``+``/``?``) after the fixed ones;
- the value reader (``parse``) checks the text; its ``ValueError`` becomes argparse's one-line error, and its
  ``__name__`` names the kind of value. Without a reader an ``int``, ``float`` or ``Path`` annotation reads the text.

Settings only argparse has (a bare ``--ray`` meaning ``local``, a positional's choices) are added to a field's
metadata with :func:`with_argparse` / :func:`field_from`.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NoReturn, TypeVar

T = TypeVar("T")
_VARIABLE = ("*", "+", "?")


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's one-line errors (exit code 2): ``anisdf <command>: error: argument --x: ...``."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def with_argparse(f: dataclasses.Field, **settings: Any) -> Any:
    """A copy of the dataclass field ``f`` (made with ``option`` / ``positional``) with more ``add_argument``
    settings, e.g. ``nargs="?", const="local"`` or a positional's ``choices``."""
    meta = {**f.metadata, "argparse": {**f.metadata.get("argparse", {}), **settings}}
    if f.default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=f.default_factory, metadata=meta)
    return dataclasses.field(default=f.default, metadata=meta)


def field_from(cls: type, name: str, **settings: Any) -> Any:
    """A copy of the field ``name`` of the dataclass ``cls`` (with more ``add_argument`` settings), to declare the
    same option in another command's options or to redeclare it in a subclass."""
    return with_argparse({f.name: f for f in dataclasses.fields(cls)}[name], **settings)


def cli_fields(cls: type) -> list[dataclasses.Field]:
    """The fields of ``cls`` that are command-line arguments."""
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata and f.metadata.get("cli", True)]


def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # an annotation that names something imported for type checking only
        return {}


def _plain(hint: Any) -> Any:
    """``X`` for ``X``, ``X | None`` and ``Optional[X]``; None for anything else."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0] if len(args) == 1 else None
    return hint


def _reader(read: Callable[[str], Any]) -> Callable[[str], Any]:
    """``read`` with its ValueError as argparse's one-line error (the message finishes "argument --x: ...")."""

    def parse(text: str) -> Any:
        try:
            return read(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    parse.__name__ = getattr(read, "__name__", "value")  # argparse names the reader in "invalid X value"
    return parse


def _argument(f: dataclasses.Field, hint: Any) -> tuple[list[str], dict[str, Any]]:
    """``add_argument``'s names and settings for the field ``f``."""
    meta = f.metadata
    kw: dict[str, Any] = {"help": meta["help"].replace("%", "%%")}
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    if meta.get("positional"):
        names = [f.name]
        if meta.get("nargs"):
            kw["nargs"] = meta["nargs"]
        if default is not dataclasses.MISSING:
            kw["default"] = default
    else:
        names = [meta.get("flag") or "--" + f.name.replace("_", "-")]
        kw["dest"] = f.name
        if default is dataclasses.MISSING:
            kw["required"] = True
        else:
            kw["default"] = default
        if default is False or (default is None and _plain(hint) is bool):
            kw["action"] = "store_true"
            return names, kw
        if default is True:
            raise TypeError(f"{f.name}: a switch is declared with default False (or None), not True")
    if meta.get("metavar"):
        kw["metavar"] = meta["metavar"]
    if meta.get("choices"):
        kw["choices"] = list(meta["choices"])
    if meta.get("parse") is not None:
        kw["type"] = _reader(meta["parse"])
    elif _plain(hint) in (int, float, Path):
        kw["type"] = _plain(hint)
    kw.update(meta.get("argparse", {}))
    return names, kw


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """One argument of ``parser`` for each command-line field of the options dataclass ``cls``."""
    hints = _hints(cls)
    fields = cli_fields(cls)
    positionals = [f for f in fields if f.metadata.get("positional")]
    # a variable-length positional takes what is left: after the fixed ones, whichever class declared them
    positionals.sort(key=lambda f: f.metadata.get("nargs") in _VARIABLE)
    for f in positionals + [f for f in fields if not f.metadata.get("positional")]:
        names, kw = _argument(f, hints.get(f.name))
        parser.add_argument(*names, **kw)


def read_options(cls: type[T], ns: argparse.Namespace, **fixed: Any) -> T:
    """The options dataclass ``cls`` filled from the parsed ``ns``; ``fixed`` sets fields the command line does not
    (``cli=False``) and that ``cls`` has."""
    names = {f.name for f in dataclasses.fields(cls)}
    values = {f.name: getattr(ns, f.name) for f in cli_fields(cls)}
    return cls(**values, **{k: v for k, v in fixed.items() if k in names})


def base_options(opts: Any, cls: type[T]) -> T:
    """The task's own options (dataclass ``cls``) out of a command's options, which extend them."""
    return cls(**{f.name: getattr(opts, f.name) for f in dataclasses.fields(cls) if f.init})


def changed_flags(opts: Any, cls: type, skip: Iterable[str] = ()) -> list[str]:
    """The options of ``cls`` that ``opts`` sets to another value than the default, as command-line words (to
    record how a result was made)."""
    words: list[str] = []
    for f in cli_fields(cls):
        if f.name in skip or f.metadata.get("positional"):
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        value = getattr(opts, f.name)
        if value is None or value == default:
            continue
        flag = f.metadata.get("flag") or "--" + f.name.replace("_", "-")
        if value is True:
            words.append(flag)
        elif isinstance(value, list | tuple):
            words += [flag, ",".join(map(str, value))]
        else:
            words += [flag, str(value)]
    return words

