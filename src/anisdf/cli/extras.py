"""The optional extras of anisdf (``pip install 'anisdf[NAME]'``) and the modules each brings: a command checks its
extra before any work and stops with one line naming the pip command."""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence

from anisdf.errors import AnisdfError

EXTRAS: dict[str, tuple[str, ...]] = {
    "viewer": ("viser",),
    "colmap": ("pycolmap", "imageio_ffmpeg"),
    "video": ("imageio_ffmpeg",),
    "cluster": ("ray",),
    "export": ("fast_simplification", "xatlas", "pygltflib"),
    "masks": ("cv2",),
}
"""Extra -> the modules it installs that anisdf imports (pyproject.toml's optional dependencies)."""


def missing(extra: str, modules: Sequence[str] | None = None) -> list[str]:
    """The modules of ``extra`` (or those of ``modules``) that cannot be imported here."""
    return [m for m in (EXTRAS[extra] if modules is None else modules) if importlib.util.find_spec(m) is None]


def install_line(command: str, extra: str, absent: Sequence[str]) -> str:
    return (f"anisdf {command} needs the {extra} extra: pip install 'anisdf[{extra}]' "
            f"(missing: {', '.join(absent)})")


def require(command: str, extra: str, modules: Sequence[str] | None = None) -> None:
    """An AnisdfError naming the pip command unless the modules of ``extra`` (or only ``modules`` of them) are
    installed."""
    absent = missing(extra, modules)
    if absent:
        raise AnisdfError(install_line(command, extra, absent))
