"""No dead configuration: every key of the config is read by the code somewhere (as an attribute: the field
definitions themselves are annotations, and the generic set/merge code names no field)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from anisdf.config import Config

SRC = Path(__file__).resolve().parents[1] / "src" / "anisdf"


def _attributes_read() -> set[str]:
    names: set[str] = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                names.add(node.attr)
    return names


def test_every_config_key_is_read_somewhere():
    read = _attributes_read()
    dead = []
    for section in dataclasses.fields(Config):
        if section.name == "preset":
            continue
        for f in dataclasses.fields(getattr(Config(), section.name)):
            if f.name not in read:
                dead.append(f"{section.name}.{f.name}")
    assert not dead, f"config keys that no code reads: {dead}"
