"""Atomic checkpoints: write to a temporary file in the same folder, fsync, then rename over the old one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from anisdf.errors import AnisdfError


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` that never leaves a half-written file; on failure the previous file is intact."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise AnisdfError(f"{path}: cannot write checkpoint ({e.strerror or e}); the previous one is kept") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    if not path.is_file():
        raise AnisdfError(f"{path}: no checkpoint found (train first, or check the run folder)")
    try:
        return torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling/zip error means a damaged file
        raise AnisdfError(f"{path}: checkpoint is unreadable ({type(e).__name__}: {e})") from None
