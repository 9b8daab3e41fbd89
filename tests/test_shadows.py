"""The light's visibility from the fixed surface (materials --shadows): shadow maps, and shading with them."""

from __future__ import annotations

import json
import shutil

import numpy as np
import torch
import torch.nn.functional as F

from anisdf.materials import environment as env_mod
from anisdf.materials.render import prepare_light
from anisdf.materials.shading import shade
from anisdf.materials.surface import Surface
from anisdf.materials.visibility import fibonacci_directions, shadowing, vertex_visibility


def _sphere_under_a_roof(roof: bool) -> Surface:
    """A unit sphere and, optionally, a wide flat slab 0.6 above it."""
    import trimesh

    parts = [trimesh.creation.icosphere(subdivisions=3, radius=1.0)]
    if roof:
        slab = trimesh.creation.box(extents=(6.0, 6.0, 0.1))
        slab.apply_translation([0.0, 0.0, 1.65])
        parts.append(slab)
    mesh = trimesh.util.concatenate(parts)
    v = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    n = F.normalize(torch.as_tensor(np.asarray(mesh.vertex_normals), dtype=torch.float32), dim=-1)
    return Surface(v, n, torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long))


def test_directions_cover_the_sphere_evenly():
    d = fibonacci_directions(64)
    assert torch.allclose(d.norm(dim=-1), torch.ones(64), atol=1e-6)
    assert float(d.mean(0).norm()) < 0.02  # no side favoured
    nearest = (d @ d.T - 2 * torch.eye(64)).max(1).values  # cos of each one's nearest neighbour
    assert float(torch.rad2deg(torch.arccos(nearest)).max()) < 30


def test_a_roof_hides_the_sky_from_the_top_of_a_sphere_but_not_the_side():
    d = fibonacci_directions(32)
    up, side = int(d[:, 2].argmax()), int(d[:, 0].argmax())
    for roof in (False, True):
        s = _sphere_under_a_roof(roof)
        vis = vertex_visibility(s, d, size=128)
        top = int(s.positions[:, 2].argmax()) if not roof else int((s.positions[:642, 2]).argmax())
        east = int(s.positions[:642, 0].argmax())
        assert bool(vis[top, up]) is (not roof)
        assert bool(vis[east, side])
        assert not bool(vis[east, int((-d[:, 0]).argmax())])  # the sphere hides its own far side


def test_shading_with_full_visibility_is_shading_without_it_and_shadows_darken():
    light = prepare_light(env_mod.studio_light(16), samples=32, rows=16)
    g = torch.Generator().manual_seed(0)
    n = F.normalize(torch.randn(50, 3, generator=g), dim=-1)
    v = F.normalize(n + 0.5 * torch.randn(50, 3, generator=g), dim=-1)
    base, rough, metal = torch.rand(50, 3, generator=g), torch.rand(50, generator=g), torch.zeros(50)
    d = fibonacci_directions(32)
    plain = shade(light, n, v, base, rough, metal)
    full = shade(light, n, v, base, rough, metal, torch.ones(50, 32), d)
    none = shade(light, n, v, base, rough, metal, torch.zeros(50, 32), d)
    half = shade(light, n, v, base, rough, metal, (d[:, 2] < 0).float().expand(50, 32), d)
    assert torch.allclose(full, plain, atol=1e-6)
    convex = shade(light, n, v, base, rough, metal, (n @ d.T > 0).float(), d)  # sees all above, nothing below
    assert torch.allclose(convex, plain, atol=1e-6)
    assert float(none.abs().max()) < 1e-6
    assert bool((half <= plain + 1e-6).all()) and float((plain - half).mean()) > 0.01
    diff, spec = shadowing(light, d, torch.ones(50, 32), n, v)
    assert torch.allclose(diff, torch.ones_like(diff)) and torch.allclose(spec, torch.ones_like(spec))


def test_materials_with_shadows_keeps_the_visibility_and_relight_uses_it(fitted_run, toy_scene, tmp_path):
    from test_materials import TINY_FIT

    from anisdf.cli import main
    from anisdf.run_dir import RunDir

    run = tmp_path / "run"
    shutil.copytree(fitted_run, run)
    assert main(["materials", str(run), *TINY_FIT, "--shadows", "8", "--restart"]) == 0
    rd = RunDir(run)
    vis = torch.load(rd.materials_visibility, weights_only=False)
    assert vis["visibility"].shape[1] == 8 and vis["visibility"].any() and not vis["visibility"].all()
    assert json.loads(rd.materials_info.read_text())["settings"]["shadows"] == 8
    light = env_mod.write_env(tmp_path / "sky.hdr", np.ones((8, 16, 3), np.float32))
    assert main(["relight", str(run), "--env", str(light), "--out", str(tmp_path / "relit"), "--max-views", "1",
                 "--cameras", str(toy_scene / "transforms_test.json"), "--no-progress"]) == 0
    assert json.loads((tmp_path / "relit" / "relight.json").read_text())["shadows"] == 8
    assert main(["materials", str(run), *TINY_FIT[:2], "--steps", "20", *TINY_FIT[4:], "--shadows", "8"]) == 0
    assert json.loads(rd.materials_info.read_text())["step"] == 20  # continued, the visibility kept
