"""Meshes and baked real-time assets: marching cubes and mesh operations (:mod:`~anisdf.export.mesh`), the UV atlas
(:mod:`~anisdf.export.uv_atlas`), texels (:mod:`~anisdf.export.texels`), texel baking (:mod:`~anisdf.export.bake`)
with the lobe fit (:mod:`~anisdf.export.sg_fit`), the asset's files (:mod:`~anisdf.export.asset_files`,
:mod:`~anisdf.export.baked_format`, :mod:`~anisdf.export.web_page`) and their reference renderer
(:mod:`~anisdf.export.reference_renderer`)."""

from __future__ import annotations

import importlib.util

from anisdf.errors import AnisdfError

BAKE_MODULES = ("fast_simplification", "xatlas", "pygltflib")
"""The modules a bake needs beyond anisdf's own dependencies (the ``export`` extra)."""


def require_bake_modules() -> None:
    """Raise an :class:`AnisdfError` naming the modules of :data:`BAKE_MODULES` that are not installed, if any."""
    missing = [name for name in BAKE_MODULES if importlib.util.find_spec(name) is None]
    if missing:
        raise AnisdfError(f"anisdf export needs {', '.join(missing)}, not installed here: "
                          "pip install 'anisdf[export]'")
