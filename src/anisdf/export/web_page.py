"""The viewer page of a baked asset: export/web/index.html with the asset's files embedded (base64), so that it
opens from disk in any WebGL2 browser with no network and no server."""

from __future__ import annotations

import base64
import json
from importlib import resources
from typing import Any

PLACEHOLDER = "__ANISDF_DATA__"


def page_html(manifest: dict[str, Any], glb: bytes, lobe_pngs: list[bytes], rgb_pngs: list[bytes]) -> str:
    """index.html showing ``glb`` (mesh and diffuse texture) with the lobe textures, as described by ``manifest``
    (export.json's content: lobes, sharpness_range, up, camera)."""
    template = (resources.files("anisdf.export") / "web" / "index.html").read_text(encoding="utf-8")
    if template.count(PLACEHOLDER) != 1:
        raise RuntimeError("the viewer template must hold the data placeholder exactly once")

    def b64(data: bytes) -> str:
        return base64.b64encode(data).decode("ascii")

    data = {"manifest": manifest, "glb": b64(glb), "lobe": [b64(p) for p in lobe_pngs],
            "rgb": [b64(p) for p in rgb_pngs]}
    # JSON inside <script>: "</" must not appear (it cannot in base64; the manifest's strings are escaped)
    text = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return template.replace(PLACEHOLDER, text)
