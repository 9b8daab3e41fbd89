"""The viewer pages of exported assets: a template of export/web/ (index.html for the baked asset,
pbr.html for the PBR asset) with the shared viewer script (web/viewer.js: glb reader, camera, resolve pass) and the
asset's files embedded (base64), so that the page opens from disk in any WebGL2 browser with no network and no
server."""

from __future__ import annotations

import base64
import json
from importlib import resources
from typing import Any

PLACEHOLDER = "__ANISDF_DATA__"
VIEWER = "__ANISDF_VIEWER__"


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def fill_template(template: str, data: dict[str, Any]) -> str:
    """The page ``template`` (a file of export/web/) with the viewer script and ``data`` (JSON) in place."""
    text = (resources.files("anisdf.export") / "web" / template).read_text(encoding="utf-8")
    viewer = (resources.files("anisdf.export") / "web" / "viewer.js").read_text(encoding="utf-8")
    for mark in (PLACEHOLDER, VIEWER):
        if text.count(mark) != 1:
            raise RuntimeError(f"the viewer template {template} must hold {mark} exactly once")
    # JSON inside <script>: "</" must not appear (it cannot in base64; the manifest's strings are escaped)
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return text.replace(VIEWER, viewer).replace(PLACEHOLDER, payload)


def page_html(manifest: dict[str, Any], glb: bytes, lobe_pngs: list[bytes], rgb_pngs: list[bytes]) -> str:
    """index.html showing ``glb`` (mesh and diffuse texture) with the lobe textures, as described by ``manifest``
    (export.json's content: lobes, sharpness_range, up, camera)."""
    return fill_template("index.html", {"manifest": manifest, "glb": b64(glb), "lobe": [b64(p) for p in lobe_pngs],
                                        "rgb": [b64(p) for p in rgb_pngs]})
