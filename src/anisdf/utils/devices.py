"""Picking the torch device a command runs on."""

from __future__ import annotations

import torch

from anisdf.errors import AnisdfError


def pick_device(name: str) -> torch.device:
    """``auto`` (CUDA if there is one), ``cpu`` or ``cuda[:N]``; an AnisdfError naming ``--device`` otherwise."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise AnisdfError(f"--device {name!r}: expected auto, cpu or cuda[:N]") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise AnisdfError(f"--device {name}: CUDA is not available in this torch build")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise AnisdfError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device
