"""Unit tests of the model's parts: hash grid, ASG, SH, SDF field, NeuS rendering, losses, config."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from anisdf.config import load_config
from anisdf.errors import AnisdfError
from anisdf.fields.asg import asg_encode, asg_frames
from anisdf.fields.encodings import sh_encoding
from anisdf.fields.hash_grid import cpu_kernel
from anisdf.fields.hash_grid.dispatch import HashGrid
from anisdf.fields.hash_grid.reference import GridSpec, corner_indices, hash_encode_reference, trilinear_weights
from anisdf.fields.sdf_field import SDFField
from anisdf.model_components import losses as L
from anisdf.model_components.neus_renderer import neus_alpha, packed_weights
from anisdf.model_components.occupancy_grid import OccupancyGrid
from anisdf.model_components.ray_marching import march, sphere_intersect

SMALL = GridSpec(n_levels=5, features_per_level=2, log2_hashmap_size=10, base_resolution=4, per_level_scale=1.8)


def test_small_spec_has_dense_and_hashed_levels():
    assert SMALL.hashed[0] is False and SMALL.hashed[-1] is True


def test_hash_encoding_matches_all_levels_formulation():
    torch.manual_seed(0)
    table = torch.randn(SMALL.n_params, 2, dtype=torch.float64)
    x = torch.rand(500, 3, dtype=torch.float64)
    x[:4] = torch.tensor([[0.0, 0, 0], [1, 1, 1], [0.5, 0.25, 1], [1, 0, 0.5]], dtype=torch.float64)
    idx, frac = corner_indices(x, SMALL)
    expected = (table[idx] * trilinear_weights(frac)[..., None]).sum(2).reshape(500, -1)
    torch.testing.assert_close(hash_encode_reference(x, table, SMALL), expected)


def test_hash_encoding_input_gradient_matches_finite_differences():
    torch.manual_seed(1)
    table = torch.randn(SMALL.n_params, 2, dtype=torch.float64)
    x = (torch.rand(64, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    proj = torch.randn(SMALL.output_dim, dtype=torch.float64)
    (g,) = torch.autograd.grad((hash_encode_reference(x, table, SMALL) @ proj).sum(), x)
    eps = 1e-7
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = eps
        with torch.no_grad():
            fd = (hash_encode_reference(x + e, table, SMALL) @ proj - hash_encode_reference(x - e, table, SMALL)
                  @ proj) / (2 * eps)
        torch.testing.assert_close(g[:, k], fd, atol=1e-5, rtol=1e-4)


def test_hash_encoding_table_gradient_is_the_trilinear_weights():
    table = torch.zeros(SMALL.n_params, 2, dtype=torch.float64, requires_grad=True)
    x = torch.rand(1, 3, dtype=torch.float64)
    hash_encode_reference(x, table, SMALL)[0, 0].backward()  # level 0, feature 0
    idx, frac = corner_indices(x, SMALL)
    w = trilinear_weights(frac)[0, 0]
    torch.testing.assert_close(table.grad[idx[0, 0], 0], w)
    assert math.isclose(float(table.grad.sum()), 1.0, rel_tol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_reference_encoding_cpu_equals_cuda():
    table = torch.randn(SMALL.n_params, 2)
    x = torch.rand(1000, 3)
    torch.testing.assert_close(hash_encode_reference(x.cuda(), table.cuda(), SMALL).cpu(),
                               hash_encode_reference(x, table, SMALL), atol=1e-5, rtol=1e-5)


def test_asg_lobe_peaks_on_its_axis_and_is_anisotropic():
    frames = asg_frames(8, 16)
    assert frames.shape == (128, 3, 3)
    torch.testing.assert_close(frames @ frames.transpose(1, 2), torch.eye(3).expand(128, 3, 3), atol=1e-5,
                               rtol=0)
    one = frames[37:38]
    x_ax, y_ax, z_ax = one[0]
    lam, mu, xi = torch.tensor([[20.0]]), torch.tensor([[2.0]]), torch.ones(1, 1, 1)
    on_axis = asg_encode(z_ax[None], one, lam, mu, xi)
    tilt = 0.3
    along_x = asg_encode(F.normalize(z_ax + tilt * x_ax, dim=0)[None], one, lam, mu, xi)
    along_y = asg_encode(F.normalize(z_ax + tilt * y_ax, dim=0)[None], one, lam, mu, xi)
    assert on_axis.item() == pytest.approx(1.0, abs=1e-5)
    assert along_x.item() < along_y.item() < on_axis.item()  # sharper along x since lambda > mu
    behind = asg_encode(-z_ax[None], one, lam, mu, xi)
    assert behind.item() == 0.0


def test_sh_encoding_is_orthonormal():
    torch.manual_seed(0)
    d = F.normalize(torch.randn(400_000, 3, dtype=torch.float64), dim=-1)
    y = sh_encoding(d, 4)
    gram = 4 * math.pi * (y.T @ y) / d.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def _sphere_field(kind: str, normals: str = "analytic") -> SDFField:
    cfg = load_config(None, [f"geometry.kind={kind}", "geometry.log2_hashmap_size=12", "geometry.n_levels=6",
                             "geometry.coarse_levels=4", "geometry.max_resolution=64", f"geometry.normals={normals}",
                             "geometry.encoding_backend=torch"])
    torch.manual_seed(0)
    return SDFField(cfg.geometry)


@pytest.mark.parametrize("kind", ["fused", "single"])
def test_geometric_init_is_a_sphere_of_radius_half(kind):
    field = _sphere_field(kind)
    x = F.normalize(torch.randn(256, 3), dim=-1) * 0.5
    with torch.no_grad():
        sdf = field.sdf(x)
        outside = field.sdf(x * 1.6)
    assert sdf.abs().mean() < 0.1  # SAL init is approximate at width 64
    assert (outside > 0).all() and (field.sdf(x * 0.2) < 0).all()


def test_fused_sdf_is_the_sum_of_branches():
    field = _sphere_field("fused")
    x = torch.rand(10, 3) - 0.5
    with torch.no_grad():
        a, b = (br(x) for br in field.branches)
        sdf, feat = field(x)
    torch.testing.assert_close(sdf, a[:, 0] + b[:, 0])
    torch.testing.assert_close(feat, a[:, 1:] + b[:, 1:])


@pytest.mark.parametrize(("kind", "fusion"), [("fused", "sum"), ("fused", "mean"), ("single", "sum")])
def test_distance_is_the_sdf_without_the_feature(kind, fusion):
    """SDFField.distance (the SDF row of each last layer only) is sdf() up to float rounding, after training has
    moved the weights away from the sphere."""
    cfg = load_config("default", [f"geometry.kind={kind}", f"geometry.fusion={fusion}", "geometry.n_levels=4",
                                  "geometry.coarse_levels=2", "geometry.log2_hashmap_size=10",
                                  "geometry.encoding_backend=torch"]).geometry
    torch.manual_seed(0)
    field = SDFField(cfg)
    field.set_step(10**6)
    with torch.no_grad():
        for p in field.parameters():
            p.add_(0.05 * torch.randn_like(p))
        x = torch.rand(500, 3) * 2 - 1
        torch.testing.assert_close(field.distance(x), field.sdf(x), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("kind", "fusion"), [("fused", "sum"), ("fused", "mean"), ("single", "sum")])
def test_closed_form_normals_and_their_training_gradients_match_autograd(kind, fusion):
    """with_gradient's closed-form MLP gradient equals autograd's d sdf / d x, and a loss on it (eikonal, as in
    training) gives every parameter the gradient that the double backward through forward() gives."""
    field = _sphere_field(kind)
    field.cfg.fusion = fusion
    field.double()
    torch.manual_seed(3)
    with torch.no_grad():  # away from the initial sphere, every level on: all paths carry weight
        for b in field.branches:
            b.grid.table.normal_(0.0, 0.1)
            b.set_step(10**6, field.cfg)
            for lay in b.layers:
                lay.parametrizations.weight.original1.normal_(0.0, 0.3)
    x = (torch.rand(300, 3, dtype=torch.float64) * 2.0 - 1.0) * 0.9

    def autograd_reference():
        xg = x.clone().requires_grad_(True)
        sdf, feat = field(xg)
        (g,) = torch.autograd.grad(sdf, xg, torch.ones_like(sdf), create_graph=True)
        return sdf, feat, g

    def lazy_features():  # the renderer's route: the feature rows asked for after the SDF and its gradient
        q = field.query(x * 1.0, create_graph=True)
        return q.sdf, q.feature(torch.arange(x.shape[0] - 1, -1, -1)).flip(0), q.grad

    results = []
    for fn in (autograd_reference, lambda: field.with_gradient(x * 1.0, create_graph=True), lazy_features):
        field.zero_grad()
        sdf, feat, g = fn()
        (L.eikonal_loss(g) + sdf.square().mean() + feat.sin().mean()).backward()
        results.append((sdf, feat, g, {n: p.grad.clone() for n, p in field.named_parameters()}))
    sdf_r, feat_r, g_r, grads_r = results[0]
    for sdf_c, feat_c, g_c, grads_c in results[1:]:
        torch.testing.assert_close(sdf_c, sdf_r)
        torch.testing.assert_close(feat_c, feat_r)
        torch.testing.assert_close(g_c, g_r, rtol=1e-7, atol=1e-9)
        for n, g in grads_r.items():
            assert float(g.abs().max()) > 0, n
            torch.testing.assert_close(grads_c[n], g, rtol=1e-6, atol=1e-9 * float(g.abs().max()), msg=n)
    rows = torch.tensor([5, 0, 77])
    torch.testing.assert_close(field.query(x, create_graph=False).feature(rows), feat_r.detach()[rows])
    # without create_graph: the same values, nothing left to differentiate
    sdf_e, _, g_e = field.with_gradient(x, create_graph=False)
    torch.testing.assert_close(g_e, g_r.detach(), rtol=1e-7, atol=1e-9)
    assert not (sdf_e.requires_grad or g_e.requires_grad)


@pytest.mark.parametrize(("kind", "all_levels"), [("fused", True), ("fused", False), ("single", True)])
def test_kernel_jacobian_route_matches_the_autograd_route(kind, all_levels, monkeypatch):
    """With the compiled CPU kernel the closed-form normal reads the grid's Jacobian
    (:meth:`HashGrid.encode_with_jacobian`) instead of a backward pass through the encoding: the SDF, its gradient,
    the features and every parameter's gradient of a training-like loss equal the autograd route's."""
    if cpu_kernel.kernel_module() is None:
        pytest.skip(f"compiled hash-grid kernel unavailable: {cpu_kernel.kernel_info()['error']}")
    cfg = load_config(None, [f"geometry.kind={kind}", "geometry.log2_hashmap_size=12", "geometry.n_levels=6",
                             "geometry.coarse_levels=4", "geometry.max_resolution=64"])
    torch.manual_seed(0)
    field = SDFField(cfg.geometry)
    with torch.no_grad():
        for b in field.branches:
            b.grid.table.normal_(0.0, 0.1)
            b.set_step(10**6 if all_levels else 0, field.cfg)
            for lay in b.layers:
                lay.parametrizations.weight.original1.normal_(0.0, 0.3)
    assert all_levels or field.branches[-1].n_active < field.branches[-1].n_levels
    x = (torch.rand(3000, 3) * 2.0 - 1.0) * 0.9
    rows = torch.arange(0, 3000, 7)

    def run():
        field.zero_grad()
        q = field.query(x, create_graph=True)
        feat = q.feature(rows)
        (L.eikonal_loss(q.grad) + q.sdf.square().mean() + feat.sin().mean()).backward()
        return [q.sdf.detach(), q.grad.detach(), feat.detach()], {n: p.grad.clone() for n, p in
                                                                  field.named_parameters()}

    taken = []
    route = HashGrid.encode_with_jacobian
    monkeypatch.setattr(HashGrid, "encode_with_jacobian", lambda *a: taken.append(route(*a)) or taken[-1])
    values, grads = run()
    assert taken and all(t is not None for t in taken)
    monkeypatch.setattr(HashGrid, "encode_with_jacobian", lambda *a: None)
    values_r, grads_r = run()
    for a, b in zip(values, values_r, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for n, g in grads_r.items():
        assert float(g.abs().max()) > 0, n
        torch.testing.assert_close(grads[n], g, rtol=1e-4, atol=1e-5 * float(g.abs().max()), msg=n)


def test_finite_difference_normals_match_analytic_gradient():
    fa = _sphere_field("fused", "analytic")
    ff = _sphere_field("fused", "finite_difference")
    ff.load_state_dict(fa.state_dict())
    x = F.normalize(torch.randn(128, 3), dim=-1) * 0.45
    _, _, ga = fa.with_gradient(x, create_graph=False)
    _, _, gf = ff.with_gradient(x, create_graph=False, fd_eps=1e-3)
    cos = F.cosine_similarity(ga, gf, dim=-1)
    assert cos.min() > 0.99


def test_level_masking_switches_levels_on_progressively():
    field = _sphere_field("fused")
    coarse, fine = field.branches
    assert int(coarse.active_levels) == 4 and int(fine.active_levels) == 4  # the fine set starts at level m = 4
    cfg = field.cfg
    field.set_step(0)
    assert int(coarse.active_levels) == 4
    field.set_step(cfg.level_start_step + 10 * cfg.level_every)
    assert int(coarse.active_levels) == coarse.n_levels


def test_level_schedule_is_the_releases():
    """NOTES.md: coarse 4 -> 10 and fine 10 -> 16 active levels, one more every 1000 steps after step 5000, all
    active by step 11000 (the first extra level at 6000, not at 5000)."""
    cfg = load_config(None, ["geometry.log2_hashmap_size=10", "geometry.encoding_backend=torch"])
    field = SDFField(cfg.geometry)
    active = {}
    for step in (0, 5000, 5999, 6000, 10999, 11000, 20000):
        field.set_step(step)
        active[step] = tuple(b.n_active for b in field.branches)
    assert active == {0: (4, 10), 5000: (4, 10), 5999: (4, 10), 6000: (5, 11), 10999: (9, 15), 11000: (10, 16),
                      20000: (10, 16)}


@pytest.mark.parametrize("m", [6, 8, 12])
def test_level_m_moves_the_split_between_the_grids(m):
    """The "level m" ablation: the coarse grid holds levels 1..m and the fine grid's active set starts at m (Eq. 5),
    whatever m is."""
    cfg = load_config(None, [f"geometry.coarse_levels={m}", "geometry.log2_hashmap_size=10",
                             "geometry.encoding_backend=torch"])
    coarse, fine = SDFField(cfg.geometry).branches
    assert coarse.n_levels == m and fine.n_levels == 16
    assert fine.start_levels == m == coarse.n_levels


def test_loaded_level_state_is_the_one_the_field_uses():
    """The branches keep their active level count as a Python int (no GPU read per query); loading a state dict
    must update it, or a resumed run would query the wrong levels."""
    cfg = load_config(None, ["geometry.log2_hashmap_size=12", "geometry.n_levels=8", "geometry.coarse_levels=6",
                             "geometry.coarse_start_levels=2",
                             "geometry.max_resolution=64", "geometry.encoding_backend=torch"])
    trained, fresh = SDFField(cfg.geometry), SDFField(cfg.geometry)
    for b in trained.branches:
        b.grid.table.data.normal_(0.0, 0.1)
    trained.set_step(trained.cfg.level_start_step + trained.cfg.level_every)  # one more level on each branch
    fresh.load_state_dict(trained.state_dict())
    assert any(b.n_active > b.start_levels for b in trained.branches)  # the test loads a state that differs
    for bt, bf in zip(trained.branches, fresh.branches, strict=True):
        assert bt.n_active == min(bt.start_levels + 1, bt.n_levels)
        assert bf.n_active == bt.n_active == int(bf.active_levels)
    x = torch.rand(64, 3) - 0.5
    for b in fresh.branches:  # the features of levels not yet switched on read zero, the others do not
        enc, k = b.encode(x), b.n_active * b.features
        assert enc.shape[1] == b.n_levels * b.features
        assert torch.all(enc[:, k:] == 0) and torch.all(enc[:, :k].abs().sum(0) > 0)
    assert torch.equal(trained(x)[0], fresh(x)[0])


def test_loaded_step_is_the_one_the_schedules_use():
    """The model's step is also a Python int (cos annealing, loss ramps); loading a state dict must set it."""
    from anisdf.models.anisdf import AniSDFModel

    cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12"])
    trained, fresh = AniSDFModel(cfg), AniSDFModel(cfg)
    trained.set_step(cfg.renderer.cos_anneal_steps // 2)
    fresh.load_state_dict(trained.state_dict())
    assert fresh.step_int == trained.step_int == cfg.renderer.cos_anneal_steps // 2
    assert fresh.cos_anneal == pytest.approx(0.5, abs=0.01)
    assert [b.n_active for b in fresh.geometry.branches] == [b.n_active for b in trained.geometry.branches]


def _sphere_sdf(x: torch.Tensor, r: float = 0.5) -> torch.Tensor:
    return x.norm(dim=-1) - r


def test_neus_weights_sum_to_one_on_a_ray_hitting_a_sphere():
    origins = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.3, -2.0], [0.0, 0.9, -2.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    s = march(origins, dirs, None, radius=1.0, step=0.004, max_samples=2000)
    x = s.positions(origins, dirs)
    sdf = _sphere_sdf(x)
    grad = F.normalize(x, dim=-1)
    alpha = neus_alpha(sdf, grad, dirs[s.ray_idx], s.dt, torch.tensor(500.0), cos_anneal=1.0)
    w, _ = packed_weights(alpha, s.ray_idx, 3)
    total = torch.zeros(3).index_add_(0, s.ray_idx, w)
    assert total[0] == pytest.approx(1.0, abs=1e-3) and total[1] == pytest.approx(1.0, abs=1e-3)
    assert total[2] < 5e-3  # misses the sphere (only the 1e-5 alpha floor per sample)
    depth = torch.zeros(3).index_add_(0, s.ray_idx, w * s.t)
    assert depth[0] == pytest.approx(1.5, abs=0.01)


def test_packed_weights_match_dense_cumprod():
    torch.manual_seed(0)
    counts = torch.tensor([3, 0, 5, 1])
    ray_idx = torch.repeat_interleave(torch.arange(4), counts)
    alpha = torch.rand(int(counts.sum()))
    w, trans = packed_weights(alpha, ray_idx, 4)
    k = 0
    for _r, c in enumerate(counts.tolist()):
        a = alpha[k : k + c]
        t = torch.cumprod(torch.cat([torch.ones(1), 1 - a[:-1]]), 0) if c else a
        torch.testing.assert_close(trans[k : k + c], t)
        torch.testing.assert_close(w[k : k + c], t * a)
        k += c


def test_occupancy_grid_keeps_the_shell_of_a_sphere():
    grid = OccupancyGrid(32, 1.0)
    frac = grid.update(_sphere_sdf, inv_s=1e4, generator=torch.Generator().manual_seed(0), full=True)
    assert 0.02 < frac < 0.3
    on = F.normalize(torch.randn(1000, 3), dim=-1) * 0.5
    assert grid.query(on).all()
    assert not grid.query(torch.zeros(1, 3)).any() and not grid.query(torch.full((1, 3), 0.9)).any()


def _sphere_and_rays(inv_s: float, n_rays: int, *overrides: str, trained: bool = False):
    """A new cpu-quick model (its SDF the initial sphere) of sharpness ``inv_s`` with its occupancy grid updated, and
    ``n_rays`` rays from one camera 3 units away towards it. ``trained``: past the opacity slope's annealing."""
    from anisdf.models.anisdf import AniSDFModel

    cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12",
                                    "renderer.grid_resolution=32", *overrides])
    model = AniSDFModel(cfg).eval()
    if trained:
        model.set_step(cfg.renderer.cos_anneal_steps)
    with torch.no_grad():
        model.variance.variance.fill_(math.log(inv_s) / cfg.renderer.variance_scale)
    model.update_grid(torch.Generator().manual_seed(0), full=True)
    gen = torch.Generator().manual_seed(1)
    o = F.normalize(torch.randn(1, 3, generator=gen), dim=-1).expand(n_rays, 3) * 3.0
    d = F.normalize(-o + 0.35 * torch.randn(n_rays, 3, generator=gen), dim=-1)
    return model, o, d


def test_images_on_the_refined_grid_match_the_training_grid_with_fewer_samples(monkeypatch):
    """renderer.image_grid_resolution: a fixed model's images march a finer grid (occupied cells split, the
    object's inside kept): the same picture within 8-bit rounding, from fewer SDF queries."""
    model, o, d = _sphere_and_rays(300.0, 4096, "renderer.image_grid_resolution=128")
    queries = []
    sdf = model.geometry.distance
    monkeypatch.setattr(model.geometry, "distance", lambda x: (queries.append(x.shape[0]), sdf(x))[1])
    coarse = model.render_image(o, d, torch.ones_like(d), 1024)
    n_coarse, _ = sum(queries), queries.clear()
    fine_grid = model.image_grid()
    assert fine_grid.resolution == 128 and model.image_grid() is fine_grid  # built once per model state
    queries.clear()
    fine = model.render_image(o, d, torch.ones_like(d), 1024, fine_grid=True)
    assert (coarse["opacity"] > 0.5).sum() > 500
    assert sum(queries) < 0.8 * n_coarse
    assert (fine["rgb"] - coarse["rgb"]).abs().max() < 2e-3
    assert (fine["opacity"] - coarse["opacity"]).abs().max() < 2e-3


def test_images_query_normals_only_near_the_surface(monkeypatch):
    """renderer.eval_normal_band: a fixed model's image queries the normal only at samples with ``|sdf| inv_s`` below
    it; the others' opacity comes from the prune pass's SDF values. On a soft surface (inv_s 30, a real capture's)
    the same picture within an 8-bit level as with a normal at every sample (band 0, the reference), from fewer
    normal queries."""
    torch.manual_seed(0)
    model, o, d = _sphere_and_rays(30.0, 2048, trained=True)
    rows = []
    query = model.geometry.query
    monkeypatch.setattr(model.geometry, "query", lambda x, *a, **k: (rows.append(x.shape[0]), query(x, *a, **k))[1])
    images = {}
    for band in (0.0, 6.0):
        model.cfg.renderer.eval_normal_band = band
        rows.clear()
        images[band] = (model.render_image(o, d, torch.ones_like(d), 1024, fine_grid=True), sum(rows))
    (every, n_every), (seen, n_seen) = images[0.0], images[6.0]
    assert (every["opacity"] > 0.5).sum() > 300
    assert n_seen < 0.85 * n_every
    for key in ("rgb", "opacity"):  # within one 8-bit level
        assert (seen[key] - every[key]).abs().max() < 1 / 255, key
    for key in ("depth", "normal"):  # depths of about 3; the normal map leaves out the unseen samples' normals
        assert (seen[key] - every[key]).abs().max() < 1e-2, key


def test_images_whose_rays_carry_gradients(monkeypatch):
    """A held-out view's camera fitted by ``anisdf eval --cameras fit`` renders rays that carry gradients through the
    normal band (renderer.eval_normal_band; it crashed there): the picture of rays without them, and the gradient
    reaches the rays."""
    torch.manual_seed(0)
    model, o, d = _sphere_and_rays(30.0, 512, trained=True)
    rows = []
    query = model.geometry.query
    monkeypatch.setattr(model.geometry, "query", lambda x, *a, **k: (rows.append(x.shape[0]), query(x, *a, **k))[1])
    o = o.clone().requires_grad_(True)
    out = model.render_rays(o, d, torch.ones_like(d), grid=model.image_grid())
    with torch.no_grad():
        plain = model.render_rays(o, d, torch.ones_like(d), grid=model.image_grid())
        model.cfg.renderer.eval_normal_band = 0.0
        model.render_rays(o, d, torch.ones_like(d), grid=model.image_grid())
    (out.rgb.sum() + out.opacity.sum()).backward()
    assert (out.opacity > 0.5).sum() > 50 and o.grad is not None and o.grad.abs().sum() > 0
    assert (out.rgb - plain.rgb).abs().max() < 1 / 255
    assert rows[0] == rows[1] < rows[2]  # the band applies with gradients too


def test_a_camera_fits_normal_equations_hold_the_gradient_of_its_error(monkeypatch):
    """eval --cameras fit solves for a camera's six numbers by Levenberg-Marquardt on every pixel's Jacobian, built
    from three backward passes (one a colour channel) and the camera's forward-mode Jacobian: ``J^T r`` is the
    gradient of half the summed squared error (autograd through the correction), summed alike over chunks."""
    from anisdf.data.rays import RayBatch
    from anisdf.models.per_image import CameraRefinement
    from anisdf.tasks.evaluate import view_cameras

    torch.manual_seed(0)
    model, o, d = _sphere_and_rays(30.0, 300, trained=True)
    for p in model.parameters():
        p.requires_grad_(False)
    pose = torch.cat([torch.eye(3), o[:1].T], 1)[None]
    cam = CameraRefinement(pose, torch.ones(1, dtype=torch.bool), anchor=False)
    zero = torch.zeros(len(o), dtype=torch.long)
    target = torch.rand(len(o), 3, generator=torch.Generator().manual_seed(2))
    rays = RayBatch(o, d, target, torch.ones_like(o), None, zero, torch.zeros(len(o), 2))
    xi = torch.tensor([0.01, -0.02, 0.005, 0.02, 0.01, -0.01])

    def render(o_, d_, background):
        return model.render_rays(o_, d_, background, grid=model.image_grid())

    monkeypatch.setattr(view_cameras, "FIT_CHUNK", 128)
    jtj, jtr, err = view_cameras.normal_equations(render, cam, rays, xi)
    with torch.no_grad():
        cam.delta.copy_(xi[None])
    residual = render(*cam(o, d, zero), torch.ones_like(o)).rgb - target
    (grad,) = torch.autograd.grad(0.5 * (residual**2).sum(), cam.delta)
    assert grad.abs().max() > 1e-2
    torch.testing.assert_close(jtr.float(), grad[0], rtol=1e-3, atol=1e-4)
    assert err == pytest.approx(float((residual**2).mean()), rel=1e-5)
    assert torch.linalg.eigvalsh(jtj).min() > -1e-6 and torch.allclose(jtj, jtj.T)


def test_training_rays_march_the_refined_grid_with_the_same_picture_and_fewer_samples():
    """renderer.grid_refine: training rays march a grid refined at each update; the samples it drops lie in front
    of the surface's density band, so a training render is the same within float noise, from fewer samples."""
    from anisdf.models.anisdf import AniSDFModel

    def model_for(refine: int) -> AniSDFModel:
        cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12",
                                        "renderer.grid_resolution=32", f"renderer.grid_refine={refine}"])
        torch.manual_seed(0)
        model = AniSDFModel(cfg)
        with torch.no_grad():
            model.variance.variance.fill_(math.log(300.0) / cfg.renderer.variance_scale)  # inv_s = 300
        return model

    plain, refined = model_for(1), model_for(2)
    assert refined.march_grid is not None and refined.march_grid.resolution == 64
    coarse_steps = load_config("cpu-quick", ["renderer.grid_resolution=32", "renderer.grid_refine=2",
                                             "renderer.march_steps=64"])
    assert AniSDFModel(coarse_steps).march_grid is None  # cells under two march steps wide: no refinement
    # before any update every cell is occupied: the refined grid is a plain copy at the finer resolution
    assert refined.march_grid.occupied.all()
    for m in (plain, refined):
        m.update_grid(torch.Generator().manual_seed(0), full=True)
    fine = refined.march_grid.occupied
    assert torch.equal(refined.grid.occupied, plain.grid.occupied)
    assert not (fine & ~refined.grid.upsampled(2)).any()  # only children of occupied cells
    assert fine.sum() < 0.8 * refined.grid.upsampled(2).sum()
    assert "march_grid.occupied" in refined.state_dict()  # saved with the model: resume marches the same grid
    later = model_for(2)  # a checkpoint of a run without refinement loads: its grid, copied at the finer resolution
    later.load_state_dict(plain.state_dict())
    assert later.march_grid is not None and torch.equal(later.march_grid.occupied, plain.grid.upsampled(2))
    model_for(1).load_state_dict(refined.state_dict())  # and the other way round: the march grid is left out
    gen = torch.Generator().manual_seed(1)
    o = F.normalize(torch.randn(1, 3, generator=gen), dim=-1).expand(2048, 3) * 3.0
    d = F.normalize(-o + 0.35 * torch.randn(2048, 3, generator=gen), dim=-1)
    outs = [m.render_rays(o, d, torch.ones_like(d), train=True, generator=torch.Generator().manual_seed(2))
            for m in (plain, refined)]
    assert (outs[0].opacity > 0.5).sum() > 300
    assert outs[1].n_samples < 0.8 * outs[0].n_samples
    assert (outs[1].rgb - outs[0].rgb).abs().max() < 2e-3
    assert (outs[1].opacity - outs[0].opacity).abs().max() < 2e-3


def test_refining_every_fourth_update_keeps_the_same_march_grid_for_fewer_queries(monkeypatch):
    """renderer.grid_refine_every: between refinements only the cells that filled are refined and the children of
    emptied ones dropped; for a field that does not change, every update leaves the same march grid as refining at
    each update, from fewer SDF queries."""
    from anisdf.models.anisdf import AniSDFModel

    models, queries = {}, {}
    for every in (1, 4):
        cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12",
                                        "renderer.grid_resolution=32", "renderer.grid_refine=2",
                                        f"renderer.grid_refine_every={every}"])
        torch.manual_seed(0)
        models[every] = m = AniSDFModel(cfg)
        with torch.no_grad():
            m.variance.variance.fill_(math.log(300.0) / cfg.renderer.variance_scale)  # inv_s = 300
        sdf, queries[every] = m.geometry.distance, []
        monkeypatch.setattr(m.geometry, "distance", lambda x, sdf=sdf, q=queries[every]: (q.append(len(x)), sdf(x))[1])
    gens = {every: torch.Generator().manual_seed(0) for every in models}
    refills = 0
    for i in range(9):
        before = models[1].grid.occupied.clone()
        for every, m in models.items():
            m.update_grid(gens[every], full=i == 0)
        assert torch.equal(models[4].grid.occupied, models[1].grid.occupied)
        assert torch.equal(models[4].march_grid.occupied, models[1].march_grid.occupied), f"update {i}"
        refills += int((models[1].grid.occupied & ~before).sum()) if i else 0
    assert refills > 0  # cells flicker in and out of the coarse grid (random points): the partial path ran
    assert sum(queries[4]) < 0.8 * sum(queries[1])


def test_march_grid_over_the_query_budget_is_refined_in_turns_not_copied():
    """refine_march_grid: before the first refinement an over-budget grid is copied at the finer resolution; after it,
    an update whose full refinement would cost more than the budget refines the cells that filled and a rotating
    share of the occupied ones (a quarter of the budget's queries with ``every`` 4), never the copy, whose samples
    reach the band refined rays no longer train; the shares add up to the full refinement."""
    from anisdf.model_components.occupancy_grid import refine_march_grid

    def sdf(x: torch.Tensor) -> torch.Tensor:
        return x.norm(dim=-1) - 0.5

    queries: list[int] = []

    def counted(x: torch.Tensor) -> torch.Tensor:
        queries.append(x.shape[0])
        return sdf(x)

    inv_s, gen = 300.0, torch.Generator().manual_seed(0)
    grid, fine = OccupancyGrid(32, 1.0, band=6.0), OccupancyGrid(64, 1.0, band=6.0)
    before = grid.occupied.clone()
    grid.update(sdf, inv_s, gen, full=True)
    refine_march_grid(grid, fine, before, sdf, inv_s, every=4, budget=1)  # never refined: the copy
    assert torch.equal(fine.occupied, grid.upsampled(2)) and int(fine.n_updates) == 0
    # refined within the budget, with a softer surface (a wider band): the children of a sharper one are fewer
    refine_march_grid(grid, fine, grid.occupied.clone(), sdf, 30.0, every=4, budget=10**9)
    assert int(fine.n_updates) == 1
    want = grid.refined(sdf, inv_s, 2).occupied
    assert (fine.occupied & ~want).any()
    # the same grid over a budget whose quarter is 1/4.5 of a full refinement: five turns, then the full refinement
    budget = int(grid.occupied.sum()) * 8 * 8 // 9
    for turn in range(5):
        assert not torch.equal(fine.occupied, want), turn
        grid.n_updates += 1
        queries.clear()
        refine_march_grid(grid, fine, grid.occupied.clone(), counted, inv_s, every=4, budget=budget)
        assert 0 < sum(queries) <= 1.1 * budget / 4
    assert torch.equal(fine.occupied, want) and int(fine.n_updates) == 1
    # updates that move cells in and out (random points in each cell): never the copy, only children of occupied cells
    for _ in range(6):
        before = grid.occupied.clone()
        grid.update(sdf, inv_s, gen)
        budget = int(grid.occupied.sum()) * 8 // 2
        queries.clear()
        refine_march_grid(grid, fine, before, counted, inv_s, every=4, budget=budget)
        assert sum(queries) <= 1.1 * budget / 4 + 8 * int((grid.occupied & ~before).sum())
        assert not (fine.occupied & ~grid.upsampled(2)).any()
        assert fine.occupied.sum() < 0.8 * grid.upsampled(2).sum()


@pytest.mark.parametrize("segment", [1, 3, 8, 1000])
def test_early_ray_termination_keeps_the_samples_of_the_one_pass_pruning(segment):
    """prune_occluded_progressive queries the SDF a few samples a ray at a time and stops a ray once it is opaque:
    the same samples are kept as by the one-pass estimate, from fewer SDF queries."""
    from anisdf.model_components.neus_renderer import prune_occluded, prune_occluded_progressive

    gen = torch.Generator().manual_seed(0)
    n_rays, step = 300, 0.01
    o = F.normalize(torch.randn(n_rays, 3, generator=gen), dim=-1) * 2.0
    d = F.normalize(-o + 0.4 * torch.randn(n_rays, 3, generator=gen), dim=-1)
    s = march(o, d, None, 1.0, step, 1024)
    x = o[s.ray_idx] + d[s.ray_idx] * s.t[:, None]
    sdf = _sphere_sdf(x)
    inv_s = torch.tensor(200.0)
    want = prune_occluded(sdf, s.t, s.ray_idx, n_rays, step, inv_s, 1e-3)
    asked = []
    got, seen = prune_occluded_progressive(lambda i: (asked.append(i), sdf[i])[1], s.t, s.ray_idx, n_rays, step,
                                           inv_s, 1e-3, segment=segment)
    assert torch.equal(got, want)
    queried = torch.cat(asked)
    assert queried.unique().numel() == queried.numel()  # no sample asked twice
    torch.testing.assert_close(seen[queried], sdf[queried])
    assert want.sum() < 0.7 * s.n  # the sphere hides samples behind it ...
    if segment < 1000:
        assert queried.numel() < 0.75 * s.n  # ... which early termination never queries


@pytest.mark.parametrize("inv_s", [20.0, 60.0, 300.0])
def test_opaque_after_is_the_fewest_sections_that_can_hide_a_sample(inv_s):
    """A ray entering the surface head-on (SDF ``-2 / inv_s - t``: slope -1, every section about as opaque as one
    can be): its first ``opaque_after + 1`` samples are kept (the bound holds) and at most two more (it is tight)."""
    from anisdf.model_components.neus_renderer import opaque_after, prune_occluded

    step, eps = 0.01, 1e-3
    k = opaque_after(step, inv_s, eps)
    t = torch.arange(3 * k + 10, dtype=torch.float32) * step
    keep = prune_occluded(-2.0 / inv_s - t, t, torch.zeros_like(t, dtype=torch.long), 1, step,
                          torch.tensor(inv_s), eps)
    assert bool(keep[: k + 1].all()) and int(keep.sum()) <= k + 3


@pytest.mark.parametrize("inv_s", [2.0, 20.0, 60.0, 200.0])
def test_rays_too_short_to_turn_opaque_are_kept_unqueried(inv_s):
    """Training needs only the keep mask: a ray with fewer samples than ``opaque_after`` sections is kept whole
    without querying its SDF (at ``inv_s`` 2 every ray, at 200 almost none), and the mask is still the one-pass
    estimate's."""
    from anisdf.model_components.neus_renderer import opaque_after, prune_occluded, prune_occluded_progressive

    gen = torch.Generator().manual_seed(1)
    n_rays, step = 400, 0.01
    o = F.normalize(torch.randn(n_rays, 3, generator=gen), dim=-1) * 2.0
    d = F.normalize(-o + 0.6 * torch.randn(n_rays, 3, generator=gen), dim=-1)
    s = march(o, d, None, 1.0, step, 1024)
    sdf = _sphere_sdf(o[s.ray_idx] + d[s.ray_idx] * s.t[:, None]) - 0.3  # the sphere of radius 0.7
    want = prune_occluded(sdf, s.t, s.ray_idx, n_rays, step, torch.tensor(inv_s), 1e-3)
    asked = []
    got, _ = prune_occluded_progressive(lambda i: (asked.append(i), sdf[i])[1], s.t, s.ray_idx, n_rays, step,
                                        torch.tensor(inv_s), 1e-3, need_sdf=False)
    assert torch.equal(got, want)
    counts = torch.bincount(s.ray_idx, minlength=n_rays)
    short = counts <= opaque_after(step, inv_s, 1e-3) + 1
    queried = torch.cat(asked) if asked else torch.zeros(0, dtype=torch.long)
    assert not short[s.ray_idx[queried]].any()  # no sample of a short ray is queried
    if inv_s == 2.0:
        assert short.all() and not asked and bool(want.all())
    if inv_s in (20.0, 60.0):  # both kinds of ray, and the long ones can turn opaque
        assert 0 < int(short[counts > 0].sum()) < int((counts > 0).sum()) and not bool(want.all())
    if inv_s == 200.0:
        assert want.sum() < 0.8 * s.n


def test_ray_occupancy_query_finds_the_cells_of_the_point_query():
    """The march's per-ray query (cell units, one axis at a time) picks the cells ``query`` picks for the same
    points; the two round differently only on cell faces (a few points in a million)."""
    g = OccupancyGrid(32, 1.3)
    gen = torch.Generator().manual_seed(0)
    g.occupied.copy_(torch.rand(32**3, generator=gen) < 0.3)
    o = F.normalize(torch.randn(2048, 3, generator=gen), dim=-1) * 4.0
    d = F.normalize(-o / 4.0 + 0.2 * torch.randn(2048, 3, generator=gen), dim=-1)
    near, far = sphere_intersect(o, d, 1.3)
    t = near[:, None] + (torch.arange(200)[None] + torch.rand(2048, 1, generator=gen)) * (2.6 / 200)
    inside = t < far[:, None]
    want = g.query(o[:, None] + d[:, None] * t[..., None]) & inside
    got = g.query_rays(o, d, t) & inside
    assert inside.sum() > 100_000 and want.sum() > 10_000
    assert (got != want).sum() <= 1e-4 * inside.sum()


def test_sphere_intersection_has_finite_gradients_for_rays_that_graze_or_miss():
    """Rays of refined cameras carry gradients through the background's sphere exit: a ray that grazes the sphere
    (discriminant exactly 0) or misses it gets finite gradients, and hits keep the closed-form distances."""
    o = torch.tensor([[1.0, 0.0, -3.0], [2.0, 0.0, -3.0], [0.2, 0.1, -3.0]], dtype=torch.float64, requires_grad=True)
    d = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float64, requires_grad=True)
    near, far = sphere_intersect(o, d, 1.0)
    (near.sum() + far.sum()).backward()
    assert torch.isfinite(o.grad).all() and torch.isfinite(d.grad).all()
    half = math.sqrt(1.0 - 0.05)
    assert far[0] == 0.0 and far[1] == 0.0  # tangent and miss: no crossing
    assert near[2].item() == pytest.approx(3.0 - half) and far[2].item() == pytest.approx(3.0 + half)


def test_losses_behave():
    n = F.normalize(torch.randn(100, 3), dim=-1)
    assert L.eikonal_loss(n * 2) == pytest.approx(1.0)
    assert L.eikonal_loss(n) < 1e-10
    assert L.curvature_loss(n, n) < 1e-10 and L.curvature_loss(n, -n) == pytest.approx(4.0)
    assert L.alpha_entropy_loss(torch.tensor([0.0, 1.0])) < 2e-3
    assert L.alpha_entropy_loss(torch.tensor([0.5])) == pytest.approx(math.log(2), rel=1e-3)
    d = torch.tensor([[0.0, 0, 1]])
    facing = L.orientation_loss(torch.ones(1), -d, d, torch.zeros(1, dtype=torch.long), 1)
    back = L.orientation_loss(torch.ones(1), d, d, torch.zeros(1, dtype=torch.long), 1)
    assert facing == 0 and back == pytest.approx(1.0)


def test_config_overrides_and_errors():
    cfg = load_config("cpu-quick", ["geometry.kind=single", "renderer.samples_per_step=2**14", "train.amp=false"])
    assert cfg.geometry.kind == "single" and cfg.train.samples_per_step == 16384 and cfg.train.amp is False
    assert cfg.data.downscale == 2
    with pytest.raises(AnisdfError, match="unknown config key"):
        load_config(None, ["geometry.nope=1"])
    with pytest.raises(AnisdfError, match="must be one of"):
        load_config(None, ["appearance.kind=asg2"])
    with pytest.raises(AnisdfError, match="cannot read"):
        load_config(None, ["geometry.n_levels=many"])
    with pytest.raises(AnisdfError, match="unknown preset"):
        load_config("nope")


@pytest.mark.parametrize("normals", ["analytic", "finite_difference"])
def test_empty_inputs_and_rays_that_miss_render_background(normals):
    from anisdf.models.anisdf import AniSDFModel

    cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", f"geometry.normals={normals}"])
    model = AniSDFModel(cfg)
    _, feat, grad = model.geometry.with_gradient(torch.zeros(0, 3), create_graph=False)
    assert feat.shape == (0, cfg.geometry.feature_dim) and grad.shape == (0, 3)
    out = model.render_image(torch.tensor([[0.0, 0, 5]]), torch.tensor([[0.0, 0, 1]]), torch.ones(1, 3), 8)
    torch.testing.assert_close(out["rgb"], torch.ones(1, 3))
    assert float(out["opacity"]) == 0.0


def test_colour_heads_read_the_position():
    """Eqs. 10-11: c_view = Psi_v(x, d, n, F) and w = sigmoid(Psi_w(x, n, F)) depend on the position itself, not
    only through the geometry feature."""
    from anisdf.fields.radiance_field import RadianceField

    cfg = load_config("cpu-quick", [])
    torch.manual_seed(0)
    rf = RadianceField(cfg.appearance, cfg.geometry.feature_dim)
    n = 16
    feat = torch.randn(1, cfg.geometry.feature_dim).expand(n, -1)
    normal = F.normalize(torch.randn(1, 3), dim=-1).expand(n, -1)
    dirs = F.normalize(torch.randn(1, 3), dim=-1).expand(n, -1)
    x = (torch.rand(n, 3) * 2 - 1).requires_grad_(True)
    out = rf(x, feat, normal, dirs)
    assert out["c_view"].std(0).max() > 1e-4 and out["weight"].std() > 1e-4
    (gx,) = torch.autograd.grad(out["c_view"].sum() + out["weight"].sum(), x)
    assert gx.abs().max() > 1e-4


def test_optimiser_weight_decay_is_the_releases():
    """The release builds AdamW without a weight decay argument, so PyTorch's default applies (NOTES.md)."""
    default = torch.optim.AdamW([torch.zeros(1, requires_grad=True)]).defaults["weight_decay"]
    assert load_config(None, []).optim.weight_decay == default == 0.01


def test_a_training_render_without_samples_backpropagates():
    """Rays that miss every occupied cell give a step with no samples: its loss backpropagates (nothing to learn,
    no error; a 0-d bias in ``addmv`` once gave a 0-d SDF for 0 rows, and its backward failed)."""
    from anisdf.models.anisdf import AniSDFModel

    cfg = load_config("cpu-quick", ["geometry.encoding_backend=torch", "geometry.log2_hashmap_size=12",
                                    "renderer.grid_resolution=32"])
    torch.manual_seed(0)
    model = AniSDFModel(cfg)
    o, d = torch.full((64, 3), 3.0), F.normalize(torch.ones(64, 3), dim=-1)  # outside the sphere, pointing away
    with model.cached_weights():
        out = model.render_rays(o, d, torch.ones(64, 3), train=True, generator=torch.Generator().manual_seed(0))
        terms = model.losses(out, torch.ones(64, 3), None, torch.Generator().manual_seed(0))
    assert out.n_samples == 0
    terms["total"].backward()
    assert all(p.grad is None or not p.grad.any() for p in model.parameters())


def test_pruning_by_the_querys_values_keeps_the_samples_and_gradients_of_the_pruning_pass(monkeypatch):
    """prune_after_query: the training render queries every marched sample with its gradient and prunes by those
    SDF values, without the SDF-only pass; the same samples are kept (here a sharp sphere hides a third of them),
    with the same picture and parameter gradients within float rounding."""
    model, o, d = _sphere_and_rays(300.0, 1024)
    model.train()
    calls = []
    distance = model.geometry.distance
    monkeypatch.setattr(model.geometry, "distance", lambda x: (calls.append(x.shape[0]), distance(x))[1])
    outs, grads = [], []
    for after in (False, True):
        calls.clear()
        out = model.render_rays(o, d, torch.ones_like(d), train=True, generator=torch.Generator().manual_seed(2),
                                prune_after_query=after)
        assert bool(calls) != after  # the SDF-only pass runs only without pruning after the query
        model.zero_grad()
        (out.rgb.square().sum() + out.samples.grad.square().sum()).backward()
        outs.append(out)
        grads.append({k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None})
    a, b = outs
    assert a.n_marched == b.n_marched and a.n_samples == b.n_samples < 0.8 * a.n_marched
    assert torch.equal(a.samples.ray_idx, b.samples.ray_idx)
    torch.testing.assert_close(b.rgb, a.rgb, rtol=0, atol=1e-5)
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 5
    for k, g in grads[0].items():  # the squared normals' gradients run to thousands: relative to each tensor
        assert float((grads[1][k] - g).norm()) <= 1e-5 * float(g.norm()), k
