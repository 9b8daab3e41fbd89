"""Compiled hash-grid kernel loader. Falls back to the PyTorch reference while no kernel is available."""

from __future__ import annotations

from anisdf.errors import AnisdfError


def load_fast_encoder(required: bool = False):
    if required:
        raise AnisdfError("geometry.encoding_backend=fast: no compiled hash-grid kernel is available")
    return None
