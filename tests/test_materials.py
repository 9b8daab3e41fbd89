"""Materials and light (anisdf.materials): the BRDF's split sum against its plain sum, light maps (rotation, files,
prefiltering), a fit that lowers its loss, and the commands (materials, relight, eval --relight, export --pbr) on a
tiny run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scenes import look_at

from anisdf.materials import environment as env_mod
from anisdf.materials.brdf import brdf
from anisdf.materials.shading import shade, shade_reference


def _points(m: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    n = F.normalize(torch.randn(m, 3, generator=g), dim=-1)
    v = F.normalize(torch.randn(m, 3, generator=g), dim=-1)
    v = F.normalize(v + n * (0.3 - (n * v).sum(-1, keepdim=True)).clamp_min(0) * 2, dim=-1)  # above the horizon
    return n, v


def test_split_sum_matches_the_plain_sum_in_a_white_furnace_and_conserves_energy():
    n, v = _points(8)
    base = torch.rand(8, 3, generator=torch.Generator().manual_seed(1))
    rough = torch.tensor([0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
    metal = torch.tensor([0.0, 1.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.2])
    white = torch.ones(32, 64, 3)
    fast = shade(env_mod.prefilter(white), n, v, base, rough, metal)
    ref = shade_reference(white, n, v, base, rough, metal)
    assert torch.allclose(fast, ref, atol=0.01), (fast - ref).abs().max()
    # a white, non-metallic surface under a white light reflects about what it receives (the glTF mix of (1 - F)
    # diffuse and F specular is not exactly energy conserving; the quadrature adds a little)
    ones = torch.ones(8, 3)
    out = shade_reference(white, n, v, ones, rough, torch.zeros(8))
    assert (out <= 1.02).all() and (out > 0.9).all()


def test_brdf_known_value_lambertian_limit():
    # roughness 1 dielectric seen and lit head-on: (1 - F) c / pi + F D V with F = 0.04, D = 1 / pi, V = 1 / 4
    n = torch.tensor([[0.0, 0.0, 1.0]])
    f = brdf(n, n, n, torch.full((1, 3), 0.5), torch.ones(1, 1), torch.zeros(1, 1))
    expected = 0.96 * 0.5 / math.pi + 0.04 / math.pi * 0.25
    assert torch.allclose(f, torch.full((1, 3), expected), rtol=1e-4)


def test_light_rotation_turns_about_up_and_round_trips():
    h = 16
    env = torch.rand(h, 2 * h, 3, generator=torch.Generator().manual_seed(0)) + 0.1
    turned = env_mod.rotate(env, 90.0)  # whole texels: a column shift
    d = env_mod.texel_directions(h, 2 * h)
    # what arrived from direction d now arrives from d turned by +90 deg about z
    rot = torch.stack([-d[..., 1], d[..., 0], d[..., 2]], -1)
    assert torch.allclose(env_mod.lookup(turned, rot), env_mod.lookup(env, d), atol=1e-4)
    smooth = env_mod.downsample(torch.rand(64, 128, 3, generator=torch.Generator().manual_seed(1)), 4)
    smooth = F.interpolate(smooth.permute(2, 0, 1)[None], size=(h, 2 * h), mode="bilinear")[0].permute(1, 2, 0)
    back = env_mod.rotate(env_mod.rotate(smooth, 37.0), -37.0)
    assert (back - smooth).abs().mean() < 0.01
    assert torch.equal(env_mod.rotate(env, 360.0), env)


def test_the_bundled_studio_light_is_a_dark_room_lit_by_its_key_light():
    import math

    env = env_mod.studio_light(32)
    assert env.shape == (32, 64, 3) and bool((env > 0).all())
    d = env_mod.texel_directions(32, 64).reshape(-1, 3)
    brightest = d[env.sum(-1).reshape(-1).argmax()]
    az, el, _, _ = env_mod.STUDIO[0]
    key = torch.tensor([math.cos(math.radians(el)) * math.cos(math.radians(az)),
                        math.cos(math.radians(el)) * math.sin(math.radians(az)), math.sin(math.radians(el))])
    assert float(brightest @ key) > math.cos(math.radians(6))
    assert float(env.median()) < 0.1  # a dark room


@pytest.mark.parametrize("suffix", [".hdr", ".npy", ".exr"])
def test_light_files_round_trip(tmp_path, suffix):
    if suffix == ".exr":
        pytest.importorskip("OpenEXR")
    img = (np.random.default_rng(0).random((8, 16, 3)) * 10.0).astype(np.float32)
    img[0, 0] = 0.0
    path = env_mod.write_env(tmp_path / f"light{suffix}", img)
    back = env_mod.read_env(path)
    assert back.shape == img.shape
    tol = 0.01 if suffix == ".hdr" else 1e-6  # RGBE keeps 8 bits of mantissa
    assert np.all(np.abs(back - img) <= tol * np.maximum(img.max(-1, keepdims=True), 1e-6))


def test_prefilter_keeps_a_constant_light_and_passes_gradients():
    c = torch.full((8, 16, 3), 0.7, requires_grad=True)
    pre = env_mod.Prefilter(8, levels=4, samples=16)(c)
    for level in pre.levels:
        assert torch.allclose(level, torch.full_like(level, 0.7), atol=1e-4)
    assert torch.allclose(pre.irradiance, torch.full_like(pre.irradiance, 0.7), atol=2e-3)
    (pre.levels[2].sum() + pre.irradiance.sum()).backward()
    assert c.grad is not None and torch.isfinite(c.grad).all() and c.grad.abs().sum() > 0


def _sphere_scene(n_views: int = 6, size: int = 24):
    """A unit sphere (Surface), cameras around it and photos of it rendered with a known material and light."""
    import trimesh

    from anisdf.export.reference_renderer import PinholeCamera
    from anisdf.materials.fit import MaterialGrid
    from anisdf.materials.render import prepare_light, render_view
    from anisdf.materials.surface import Surface

    mesh = trimesh.creation.icosphere(subdivisions=3)
    surface = Surface(torch.as_tensor(mesh.vertices, dtype=torch.float32),
                      F.normalize(torch.as_tensor(mesh.vertex_normals, dtype=torch.float32), dim=-1),
                      torch.as_tensor(mesh.faces, dtype=torch.long))
    truth = MaterialGrid(torch.full((3,), -1.1), torch.full((3,), 1.1), 2)
    with torch.no_grad():  # base colour (0.6, 0.15, 0.12), roughness 0.3, metallic ~0
        truth.mean.copy_(torch.tensor([*torch.logit(torch.tensor([0.6, 0.15, 0.12])).tolist(),
                                       math.log((0.3 - 0.02) / (1 - 0.3)), -8.0]))
    d = env_mod.texel_directions(8, 16)
    light = 0.4 + 1.5 * torch.relu(d @ torch.tensor([0.3, 0.2, 0.93]))[..., None] * torch.tensor([1.0, 0.9, 0.8])
    pre = prepare_light(light, samples=32, rows=8)
    views = []
    for k in range(n_views):
        a = 2 * math.pi * k / n_views
        eye = [3.5 * math.cos(a), 3.5 * math.sin(a), 1.0]
        cam = PinholeCamera(look_at(eye), size * 1.2, size * 1.2, size / 2, size / 2, size, size)
        img = render_view(surface, truth, pre, cam, supersample=1, pixel_filter=0.0)
        views.append((cam, (img[..., :3] * 255 + 0.5).astype(np.uint8), img[..., 3]))
    return surface, views, light


def test_a_few_fit_steps_lower_the_loss():
    from anisdf.materials.fit import Fit, FitSettings, gather_samples

    surface, views, _ = _sphere_scene()
    samples = gather_samples(surface, views)
    assert len(samples) > 500
    fit = Fit(surface, FitSettings(batch=512, light_rows=8, grid=4, filter_samples=16))
    idx = torch.arange(len(samples))
    with torch.no_grad():
        before = float(fit.loss(samples, idx)[1])
    fit.run(samples, 25, deadline=float("inf"), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        after = float(fit.loss(samples, idx)[1])
    assert fit.step == 25 and after < 0.5 * before, (before, after)


def test_the_uniform_prior_holds_unseen_roughness_at_the_shared_value():
    """--uniform-prior: where no photo constrains roughness (a grid corner no surface point reaches) its residual
    returns to the shared value; without the prior it stays where it was put."""
    from anisdf.materials.fit import Fit, FitSettings, gather_samples

    surface, views, _ = _sphere_scene(n_views=2)
    samples = gather_samples(surface, views)
    ends = []
    for prior in (0.0, 1.0):
        fit = Fit(surface, FitSettings(batch=512, light_rows=8, grid=8, filter_samples=16, uniform_prior=prior,
                                       tv_material=0.0))
        with torch.no_grad():
            fit.material.grid[0, 3, 0, 0, 0] = 2.0  # a corner node: its cells hold no point of the sphere
        fit.run(samples, 30, deadline=float("inf"), generator=torch.Generator().manual_seed(0))
        ends.append(float(fit.material.grid[0, 3, 0, 0, 0].detach()))
    assert ends[0] == 2.0 and ends[1] < 1.6, ends


TINY_FIT = ["--minutes", "2", "--steps", "15", "--resolution", "32", "--faces", "3000", "--light-rows", "8",
            "--grid", "4", "--batch", "512", "--no-progress"]


# ``fitted_run`` (conftest.py): a tiny trained run with a material fit of TINY_FIT.


def test_materials_writes_a_resumable_fit(fitted_run):
    from anisdf.cli import main
    from anisdf.run_dir import RunDir

    rd = RunDir(fitted_run)
    info = json.loads(rd.materials_info.read_text())
    assert info["step"] == 15 and info["pixels"] > 0 and set(info["material"]) == {"base_color", "roughness",
                                                                                   "metallic"}
    assert env_mod.read_env(rd.materials_light).shape == (8, 16, 3)
    assert main(["materials", str(fitted_run), *TINY_FIT[:2], "--steps", "20", *TINY_FIT[4:]]) == 0
    assert json.loads(rd.materials_info.read_text())["step"] == 20  # continued from 15


def test_relight_eval_relight_and_export_pbr(fitted_run, toy_scene, tmp_path):
    import pygltflib
    import trimesh
    from PIL import Image

    from anisdf.cli import main
    from anisdf.run_dir import RunDir

    light = env_mod.write_env(tmp_path / "sky.hdr", np.ones((8, 16, 3), np.float32) * 0.8)
    out = tmp_path / "relit"
    assert main(["relight", str(fitted_run), "--env", str(light), "--rotate", "45", "--out", str(out),
                 "--cameras", str(toy_scene / "transforms_test.json"), "--no-progress"]) == 0
    assert main(["relight", str(fitted_run), "--env", "studio", "--out", str(tmp_path / "studio"), "--max-views", "1",
                 "--cameras", str(toy_scene / "transforms_test.json"), "--no-progress"]) == 0
    assert json.loads((tmp_path / "studio" / "relight.json").read_text())["env"] == "studio"
    views = sorted(out.glob("*.png"))
    assert len(views) == 2 and Image.open(views[0]).mode == "RGBA"
    assert np.asarray(Image.open(views[0]))[..., 3].max() == 255  # the object is in the picture

    folder = tmp_path / "truth"  # the relight folder layout, its "truth" the renders just made
    (folder / "sky").mkdir(parents=True)
    for v in views:
        (folder / "sky" / v.name).write_bytes(v.read_bytes())
    (folder / "sky_world.hdr").write_bytes(light.read_bytes())
    (folder / "transforms_test.json").write_text((toy_scene / "transforms_test.json").read_text())
    (folder / "material.json").write_text(json.dumps({"base_color": [0.5, 0.5, 0.5], "roughness": 0.5}))
    assert main(["eval", str(fitted_run), "--relight", str(folder), "--max-views", "1"]) == 0
    scores = RunDir(fitted_run).read_eval()["relight"]
    assert scores["sky"]["psnr"] > 40 and scores["sky"]["views"] == 2
    assert {"base_color_error", "roughness_error"} <= set(scores["material"])
    assert "relight.sky.psnr" in RunDir(fitted_run).report_md.read_text()

    asset = tmp_path / "pbr"
    assert main(["export", str(fitted_run), "--pbr", "--out", str(asset), "--faces", "2000", "--texture", "64",
                 "--no-progress"]) == 0
    assert (asset / "light.hdr").is_file()
    page = (asset / "index.html").read_text()
    assert "__ANISDF" not in page and '"name":"studio"' in page and '"name":"estimated"' in page
    geom = next(iter(trimesh.load(asset / "model.glb").geometry.values()))
    assert geom.visual.material.baseColorTexture.size == (64, 64)
    assert geom.visual.material.metallicRoughnessTexture.size == (64, 64)
    pbr = pygltflib.GLTF2().load(str(asset / "model.glb")).materials[0].pbrMetallicRoughness
    assert pbr.baseColorTexture.index == 0 and pbr.metallicRoughnessTexture.index == 1


def test_materials_fits_a_photo_run_with_refined_cameras_and_takes_each_photos_gain_out(tmp_path):
    """A photo capture's run (camera corrections and a gain per image, as auto gives photos) loads for the fit, and
    the fit sees each training photo divided by its image's learned gain: the scene's own colour."""
    from scenes import write_test_scene
    from test_training import TINY

    from anisdf.cli import main
    from anisdf.tasks.materials import _load_model, _training_views

    write_test_scene(tmp_path / "s", "colmap", n_images=9, width=24, height=16)
    run = tmp_path / "run"
    assert main(["train", str(tmp_path / "s"), "--out", str(run), "--preset", "cpu-quick", "--max-steps", "6",
                 "--no-progress", *TINY, "cameras.refine=on", "appearance.embedding=on",
                 "appearance.embedding_kind=gain"]) == 0
    assert main(["materials", str(run), *TINY_FIT]) == 0
    cfg, model, ck = _load_model(run)
    assert model.cameras is not None and model.colour_transform == "gain"
    with torch.no_grad():
        model.image_codes.codes.zero_()
        photos = _training_views(run, cfg, ck, 0, model)  # gain 1: the photos as they are
        model.image_codes.codes.copy_(torch.log(torch.tensor([2.0, 1.0, 0.5])).expand_as(model.image_codes.codes))
    own = _training_views(run, cfg, ck, 0, model)
    assert len(own) == len(photos) == int(model.image_codes.trained.sum()) > 0
    for (_, photo, _), (_, seen, _) in zip(photos, own, strict=True):
        want = np.clip(photo * np.array([0.5, 1.0, 2.0]), 0, 255)  # divided by each channel's gain
        np.testing.assert_allclose(seen, want, atol=1e-3)
