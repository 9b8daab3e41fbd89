"""The PBR asset's page (export --pbr's index.html) against its Python reference renderer, under each of its
lights: the fitted one, the bundled studio light turned by the slider, and a user's own .hdr file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("xatlas", reason="export --pbr needs the export extra (pip install 'anisdf[export]')")
pytest.importorskip("pygltflib", reason="export --pbr needs the export extra")

from scenes import look_at  # noqa: E402

from anisdf.export.reference_renderer import PinholeCamera  # noqa: E402
from anisdf.materials import environment as env_mod  # noqa: E402
from anisdf.materials.asset import Fitted  # noqa: E402
from anisdf.materials.fit import MaterialGrid  # noqa: E402
from anisdf.materials.pbr_asset import GLB, MANIFEST, bake_pbr  # noqa: E402
from anisdf.materials.pbr_viewer import PAGE, PbrAsset, pbr_page_html, render_asset, turn_z  # noqa: E402
from anisdf.materials.render import prepare_light  # noqa: E402
from anisdf.materials.surface import Surface  # noqa: E402


def sky(rows: int = 32) -> torch.Tensor:
    """A light with a sun, a blue sky and a brown ground, nothing symmetric about z."""
    d = env_mod.texel_directions(rows, 2 * rows)
    sun = torch.tensor([0.6, -0.3, 0.74])
    sun = sun / sun.norm()
    up = d[..., 2:].clamp_min(0)
    env = up * torch.tensor([0.3, 0.5, 0.9]) + (1 - up) * torch.tensor([0.25, 0.18, 0.1])
    return env + 25.0 * torch.exp(40.0 * ((d @ sun) - 1.0))[..., None] * torch.tensor([1.0, 0.9, 0.8])


@pytest.fixture(scope="module")
def asset(tmp_path_factory):
    """A sphere with a base colour, roughness and metallic that vary over it, exported as export --pbr does."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    v = torch.as_tensor(np.asarray(sphere.vertices), dtype=torch.float32)
    surface = Surface(v, v / v.norm(dim=-1, keepdim=True), torch.as_tensor(np.asarray(sphere.faces)))
    material = MaterialGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), res=4)
    with torch.no_grad():
        material.mean.copy_(torch.tensor([0.8, 0.0, -0.8, -0.5, -2.0]))
        g = torch.linspace(-1.5, 1.5, 4)
        material.grid[0, 3] = g[:, None, None]        # roughness from about 0.2 to 0.8 along x
        material.grid[0, 4] = 3.0 * g[None, None, :]  # metal on one side (z)
        material.grid[0, 1] = g[None, :, None]
    folder = tmp_path_factory.mktemp("pbr")
    glb, stats = bake_pbr(Fitted(surface, material.eval(), sky()), faces=3000, texture=128)
    cam = PinholeCamera(look_at([2.2, -1.4, 1.2]), 110.0, 110.0, 48.0, 48.0, 96, 96)
    manifest = {"format": "anisdf-pbr", "supersample": 2, "pixel_filter": 0.6, "camera": cam.to_json(),
                "up": [0.0, 0.0, 1.0], **stats}
    (folder / GLB).write_bytes(glb)
    (folder / MANIFEST).write_text(json.dumps(manifest))
    lights = {"estimated": sky().numpy(), "studio": env_mod.studio_light().numpy()}
    (folder / PAGE).write_text(pbr_page_html(manifest, glb, lights))
    return folder, cam, lights


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return -10 * math.log10(max(float(np.mean((a - b) ** 2)), 1e-10))


def test_the_reference_turns_the_light_as_relight_does(asset):
    """Turning the lookups by -a equals turning the map by +a (relight --rotate) for a whole-texel turn."""
    folder, cam, lights = asset
    pbr = PbrAsset.load(folder)
    env = torch.from_numpy(lights["estimated"])
    turned, _ = render_asset(pbr, prepare_light(env), cam, rotate=90.0)
    rolled, cover = render_asset(pbr, prepare_light(env_mod.rotate(env, 90.0)), cam)
    still, _ = render_asset(pbr, prepare_light(env), cam)
    assert cover.mean() > 0.2
    assert psnr(turned, rolled) > 40 > psnr(turned, still) + 5
    d = torch.tensor([[1.0, 0.0, 0.3]])
    assert torch.allclose(turn_z(d, 90.0), torch.tensor([[0.0, 1.0, 0.3]]), atol=1e-6)


def test_the_page_draws_what_the_reference_draws_under_each_light(asset, tmp_path):
    from test_export_baked import _browser

    sync_playwright, exe = _browser()
    folder, cam, lights = asset
    user = env_mod.write_env(tmp_path / "user.hdr", np.roll(sky(16).numpy(), 5, axis=1)[::-1].copy())
    pbr = PbrAsset.load(folder)
    cases = [("estimated", 0.0, torch.from_numpy(lights["estimated"])),
             ("studio", 90.0, torch.from_numpy(lights["studio"])),
             ("file: user.hdr", 200.0, torch.from_numpy(env_mod.read_env(user)))]
    shots = {}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True,
                                    args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                          "--ignore-gpu-blocklist", "--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": cam.width, "height": cam.height}, device_scale_factor=1)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto((folder / PAGE).resolve().as_uri())
            page.wait_for_function("window.anisdf && (window.anisdf.ready || window.anisdf.error)", timeout=120000)
            assert page.evaluate("window.anisdf.error") is None, page.evaluate("window.anisdf.error")
            page.evaluate("(c) => window.anisdf.setCamera(c)", cam.to_json())
            page.evaluate("document.getElementById('hud').style.display = 'none'")
            page.set_input_files("#hdr", str(user))
            page.wait_for_function("window.anisdf.light === 'file: user.hdr' || window.anisdf.error", timeout=120000)
            assert page.evaluate("window.anisdf.error") is None, page.evaluate("window.anisdf.error")
            for name, deg, _ in cases:
                page.evaluate("([n, d]) => { window.anisdf.setLight(n); window.anisdf.setRotation(d); }", [name, deg])
                start = page.evaluate("window.anisdf.frames")
                page.wait_for_function(f"window.anisdf.frames >= {start + 2}", timeout=60000)
                shots[name] = page.locator("canvas").screenshot()
            assert not errors, errors
        finally:
            browser.close()
    import io

    from PIL import Image

    for name, deg, env in cases:
        shot = np.asarray(Image.open(io.BytesIO(shots[name])).convert("RGB")) / 255.0
        ref, cover = render_asset(pbr, prepare_light(env), cam, rotate=deg)
        assert cover.mean() > 0.2
        print(f"{name} turned {deg:g} deg: page against reference {psnr(shot, ref):.1f} dB")
        assert psnr(shot, ref) >= 30, (name, psnr(shot, ref))
