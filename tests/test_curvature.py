"""The curvature term (Eq. 15) in its forms: the normal at the tangent-shifted point (fused or the coarse branch's),
the squared or angle penalty, the tangent step (finest cell or the mean of the grids' cells), the weight's decay."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch.nn.utils import parametrize

from anisdf.config import Config, config_from_dict, load_config
from anisdf.model_components import losses as L
from anisdf.models.anisdf import AniSDFModel

SMALL = ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12"]


def _model(*overrides: str, preset: str = "cpu-quick") -> AniSDFModel:
    torch.manual_seed(0)
    return AniSDFModel(load_config(preset, [*SMALL, *overrides]))


def _make_planar(model: AniSDFModel, normal: torch.Tensor) -> None:
    """Every branch's SDF becomes exactly ``normal . x`` (softplus is the identity on the shifted unit it passes)."""
    for b in model.geometry.branches:
        first, middle, last = b.layers
        for layer in b.layers:
            parametrize.remove_parametrizations(layer, "weight", leave_parametrized=True)
        with torch.no_grad():
            for layer in b.layers:
                layer.weight.zero_()
                layer.bias.zero_()
            first.weight[0, :3] = normal
            first.bias[0] = 2.0
            middle.weight[0, 0] = 1.0
            last.weight[0, 0] = 1.0
            last.bias[0] = -2.0


def _on_sphere(n: int, radius: float) -> torch.Tensor:
    gen = torch.Generator().manual_seed(1)
    return F.normalize(torch.randn(n, 3, generator=gen), dim=-1) * radius


def _term(model: AniSDFModel, x: torch.Tensor, detach_normal: bool = False) -> torch.Tensor:
    _, _, grad = model.geometry.with_gradient(x, create_graph=True)
    n = F.normalize(grad, dim=-1)
    return model.curvature_term(x, n.detach() if detach_normal else n, torch.Generator().manual_seed(2))


@pytest.mark.parametrize("eps", ["finest", "mean_cells"])
def test_coarse_target_is_zero_on_a_plane_and_positive_on_a_small_sphere(eps):
    plane = _model("loss.curvature_target=coarse", f"loss.curvature_eps={eps}")
    _make_planar(plane, F.normalize(torch.tensor([0.3, -0.5, 0.8]), dim=0))
    x = torch.rand(256, 3) - 0.5
    assert _term(plane, x).item() < 1e-10
    sphere = _model("loss.curvature_target=coarse", f"loss.curvature_eps={eps}", "geometry.init_radius=0.2")
    assert _term(sphere, _on_sphere(256, 0.2)).item() > 1e-7


def test_angle_form_on_a_plane_is_the_clamp_floor():
    plane = _model("loss.curvature_target=coarse", "loss.curvature_form=angle")
    _make_planar(plane, torch.tensor([0.0, 0.0, 1.0]))
    floor = math.acos(1.0 - L.ANGLE_CLAMP) / math.pi
    assert _term(plane, torch.rand(64, 3) - 0.5).item() == pytest.approx(floor, rel=1e-2)


@pytest.mark.parametrize(("target", "detach_normal", "coarse", "fine"), [
    ("coarse", False, True, True),   # the fused normal at x trains both; the coarse target trains the coarse branch
    ("coarse", True, True, False),   # the target alone: only the coarse branch (not detached, as in the release)
    ("fused", True, True, True),     # today's form: the fused target trains both branches
])
def test_gradient_reaches_the_branches(target, detach_normal, coarse, fine):
    model = _model(f"loss.curvature_target={target}", "geometry.init_radius=0.2")
    loss = _term(model, _on_sphere(256, 0.2), detach_normal)
    for branch, expected in zip(model.geometry.branches, (coarse, fine), strict=True):
        params = list(branch.layers.parameters())
        grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
        reached = any(g is not None and float(g.abs().max()) > 0 for g in grads)
        assert reached is expected


def test_branch_gradient_finite_differences_match_the_closed_form():
    analytic = _model()
    fd = _model("geometry.normals=finite_difference")
    fd.load_state_dict(analytic.state_dict())
    x = _on_sphere(128, 0.45)
    for branch in (0, 1):
        ga = analytic.geometry.branch_gradient(x, branch, create_graph=False)
        gf = fd.geometry.branch_gradient(x, branch, create_graph=False, fd_eps=1e-3)
        assert F.cosine_similarity(ga, gf, dim=-1).min() > 0.99
    # the two branches' gradients, fused, are the field's
    _, _, g = analytic.geometry.with_gradient(x, create_graph=False)
    g0, g1 = (analytic.geometry.branch_gradient(x, i, create_graph=False) for i in (0, 1))
    torch.testing.assert_close(g, g0 + g1)


def test_single_grid_coarse_target_reads_the_one_grid():
    model = _model("geometry.kind=single", "loss.curvature_target=coarse", "geometry.init_radius=0.2")
    fused = _model("geometry.kind=single", "geometry.init_radius=0.2")
    x = _on_sphere(256, 0.2)
    torch.testing.assert_close(_term(model, x), _term(fused, x))


def test_angle_form_is_the_arccos_over_pi():
    gen = torch.Generator().manual_seed(3)
    n = F.normalize(torch.randn(500, 3, generator=gen), dim=-1)
    m = F.normalize(n + 0.7 * torch.randn(500, 3, generator=gen), dim=-1)
    m[:3] = n[:3]  # dot products of 1 (clamped)
    m[3] = -n[3]
    expected = torch.acos((n * m).sum(-1).clamp(-1 + 1e-6, 1 - 1e-6)).mean() / math.pi
    torch.testing.assert_close(L.curvature_loss(n, m, "angle"), expected)
    torch.testing.assert_close(L.curvature_loss(n, m), (((n * m).sum(-1) - 1) ** 2).mean())


@pytest.mark.parametrize("step", [0, 250, 450, 10_000])
def test_mean_cells_eps_is_the_mean_of_the_grids_finest_active_cells(step):
    cfg = load_config("cpu-quick", SMALL)
    g = cfg.geometry
    model = AniSDFModel(load_config("cpu-quick", [*SMALL, "loss.curvature_eps=mean_cells"]))
    model.set_step(step)
    extra = max(0, (step - g.level_start_step) // g.level_every)
    scale = (g.max_resolution / g.base_resolution) ** (1 / (g.n_levels - 1))
    active = (min(g.coarse_start_levels + extra, g.coarse_levels), min(g.coarse_levels + extra, g.n_levels))
    cells = [2.0 / math.floor(g.base_resolution * scale ** (n - 1) + 1e-6) for n in active]
    assert model.curvature_eps() == pytest.approx(sum(cells) / 2, rel=1e-12)
    assert model.finest_cell() == pytest.approx(cells[1], rel=1e-12)
    finest = AniSDFModel(cfg)
    finest.set_step(step)
    assert finest.curvature_eps() == pytest.approx(cells[1], rel=1e-12)


def test_exponential_decay_is_the_release_formula_on_dtu():
    model = _model(preset="dtu")
    assert model.cfg.loss.curvature_decay == "exponential"
    lam, scale = 5e-4, 1.3195079107728942
    for step, want in [(0, 0.0), (2500, lam / 2), (5000, lam), (6000, lam / scale), (11_000, lam / scale ** 6),
                       (40_000, lam * math.exp(-35_000 * math.log(scale) / 1000)),
                       (80_000, lam * math.exp(-75_000 * math.log(scale) / 1000))]:
        model.set_step(step)
        assert model.curvature_weight() == pytest.approx(want, rel=1e-6, abs=1e-30), step


def test_levels_decay_stops_once_the_last_level_is_on():
    model = _model("loss.curvature_decay=levels", preset="dtu")
    scale = model.cfg.geometry.per_level_scale()
    for step, levels_on in [(5000, 0), (7000, 2), (11_000, 6), (40_000, 6)]:
        model.set_step(step)
        assert model.curvature_weight() == pytest.approx(5e-4 / scale ** levels_on, rel=1e-9), step


def test_old_boolean_decay_still_loads(tmp_path):
    d = Config().to_dict()
    for old, new in [(True, "levels"), (False, "off")]:
        d["loss"]["curvature_decay"] = old
        assert config_from_dict(d).loss.curvature_decay == new
    path = tmp_path / "old.yaml"
    path.write_text("loss:\n  curvature_decay: true\n")
    assert load_config(str(path)).loss.curvature_decay == "levels"
    assert load_config(None, ["loss.curvature_decay=false"]).loss.curvature_decay == "off"
    assert load_config(None, ["loss.curvature_decay=exponential"]).loss.curvature_decay == "exponential"
