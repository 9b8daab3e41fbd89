"""Real captures: camera refinement (se(3) corrections of the training cameras) and per-image appearance codes."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scenes import look_at, write_test_scene
from scipy.linalg import expm
from scipy.spatial.transform import Rotation
from test_training import TINY

from anisdf.config import load_config
from anisdf.data.dataparsers import load_scene
from anisdf.data.scene import capture_switch
from anisdf.fields.radiance_field import RadianceField
from anisdf.models.per_image import (
    CameraRefinement,
    colour_affine,
    colour_gain,
    colour_transform,
    pose_changes,
    se3_exp,
    undo_colour_transform,
)
from anisdf.run_dir import RunDir
from anisdf.tasks.loading import load_run, scene_for_run
from anisdf.training.trainer import Trainer, build_model

AUTO = ["cameras.refine=auto", "appearance.embedding=auto"]
"""Both switches following the dataset's format (their defaults)."""


def _hat(xi: np.ndarray) -> np.ndarray:
    w, v = xi[:3], xi[3:]
    m = np.zeros((4, 4))
    m[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    m[:3, 3] = v
    return m


def test_se3_exp_matches_the_matrix_exponential_and_has_exact_gradients():
    gen = torch.Generator().manual_seed(0)
    xi = torch.randn(6, 6, generator=gen, dtype=torch.float64)
    xi[0, :3] *= 1e-5  # the Taylor branch
    xi[1, :3] = 0.0
    xi[2] *= 3.0  # beyond pi
    rot, t = se3_exp(xi)
    ref = np.stack([expm(_hat(x)) for x in xi.numpy()])
    np.testing.assert_allclose(rot.numpy(), ref[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(t.numpy(), ref[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(rot.numpy(), Rotation.from_rotvec(xi[:, :3].numpy()).as_matrix(), atol=1e-12)
    assert torch.autograd.gradcheck(se3_exp, (xi.clone().requires_grad_(),))
    assert torch.autograd.gradcheck(se3_exp, (torch.zeros(2, 6, dtype=torch.float64, requires_grad=True),))


def test_corrected_rays_are_the_rays_of_the_corrected_camera():
    """Rays moved by CameraRefinement equal the rays of the camera c2w exp(xi) built directly."""
    scene_c2w = torch.tensor(np.stack([expm(_hat(np.r_[0.3, -0.2, 0.5, 1.0, 2.0, -0.5]))[:3, :4],
                                       expm(_hat(np.r_[-0.1, 0.4, 0.2, 0.0, 1.0, 2.0]))[:3, :4]]), dtype=torch.float32)
    ref = CameraRefinement(scene_c2w, torch.tensor([True, False]))
    with torch.no_grad():
        ref.delta[:] = torch.tensor([[0.02, -0.01, 0.03, 0.05, -0.02, 0.01]] * 2)
    d_cam = torch.nn.functional.normalize(torch.tensor([[0.1, -0.2, 1.0], [0.0, 0.3, 1.0]]), dim=-1)
    cam = torch.tensor([0, 1])
    pose = scene_c2w[cam]
    with torch.no_grad():
        o, d = ref(pose[:, :, 3], (pose[:, :, :3] @ d_cam[..., None])[..., 0], cam)
    new = ref.refined_poses()
    np.testing.assert_allclose(o[0], new[0, :, 3], atol=1e-6)
    np.testing.assert_allclose(d[0], new[0, :, :3] @ d_cam[0], atol=1e-6)
    np.testing.assert_allclose(o[1], scene_c2w[1, :, 3], atol=1e-6)  # untrained: unchanged
    np.testing.assert_allclose(new[1], scene_c2w[1], atol=1e-6)


def _ring_cameras(n: int = 6) -> torch.Tensor:
    """[n,3,4] cameras on a tilted ring at distance 3, looking at the origin."""
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        poses.append(look_at([3 * np.cos(a), 3 * np.sin(a), 1.0 + 0.3 * np.sin(3 * a)])[:3])
    return torch.tensor(np.stack(poses), dtype=torch.float32)


def test_the_anchor_takes_out_the_motion_common_to_all_cameras_and_keeps_the_rest():
    """Corrections that only move the whole rig (a gauge: no training photo changes) vanish when anchored; one
    camera's own correction stays (less its share of the common motion)."""
    poses = _ring_cameras()
    rot, centre = poses[:, :, :3], poses[:, :, 3]
    w, v = torch.tensor([0.01, -0.02, 0.015]), torch.tensor([0.03, 0.01, -0.02])
    common = torch.cat([(rot.transpose(1, 2) @ w)[..., None].squeeze(-1).expand(6, 3),
                        (rot.transpose(1, 2) @ (torch.linalg.cross(w.expand(6, 3), centre) + v)[..., None])[..., 0]], 1)
    trained = torch.tensor([True] * 5 + [False])  # the last one is a test camera
    for anchor, expect_small in ((True, True), (False, False)):
        ref = CameraRefinement(poses, trained, anchor=anchor)
        with torch.no_grad():
            ref.delta[:] = common
            d_rot, d_t = ref.corrections()
        angle = torch.arccos(((d_rot.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))
        size = float(angle[:5].max() + d_t[:5].norm(dim=-1).max())
        assert (size < 2e-3) == expect_small, (anchor, size)
        assert float(angle[5]) == 0.0 and float(d_t[5].norm()) == 0.0  # test cameras are never corrected
    own = torch.zeros(6, 6)
    own[2] = torch.tensor([0.0, 0.02, 0.0, 0.05, 0.0, 0.0])
    ref = CameraRefinement(poses, trained)
    with torch.no_grad():
        ref.delta[:] = own
        d_rot, d_t = ref.corrections()
    assert float(d_t[2].norm()) > 0.6 * 0.05 and float(torch.arccos((d_rot[2].trace() - 1) / 2)) > 0.6 * 0.02


@pytest.mark.parametrize("fmt", ["nerf-synthetic", "neus", "llff", "colmap", "instant-ngp"])
def test_switches_are_off_for_rendered_scenes_and_on_for_photos(tmp_path, fmt):
    """auto follows the format; by default photos get camera refinement and a gain per image (both measured to
    help), and the paper's photo presets keep the dataset's cameras and learn nothing per image."""
    write_test_scene(tmp_path / fmt, fmt)
    scene = load_scene(tmp_path / fmt)
    photos = fmt != "nerf-synthetic"
    model = build_model(load_config("cpu-quick", [*TINY, *AUTO]), scene, torch.device("cpu"))
    assert (model.cameras is not None, model.image_codes is not None) == (photos, photos)
    default = build_model(load_config("cpu-quick", TINY), scene, torch.device("cpu"))
    assert (default.cameras is not None, default.image_codes is not None) == (photos, photos)
    if photos:
        assert default.colour_transform == "gain" and default.image_codes.codes.shape[1] == 3
    for paper in ("dtu", "mipnerf360"):
        assert (load_config(paper).cameras.refine, load_config(paper).appearance.embedding) == ("off", "off")
    off = build_model(load_config("cpu-quick", [*TINY, "cameras.refine=off", "appearance.embedding=false"]), scene,
                      torch.device("cpu"))
    assert off.cameras is None and off.image_codes is None
    assert capture_switch("on", "nerf-synthetic") and not capture_switch("off", fmt)
    if photos:
        assert model.cameras.trained.tolist() == [i in scene.splits["train"] for i in range(scene.n_images)]


def test_without_codes_the_radiance_field_is_the_plain_one():
    """appearance.embedding off: the same parameters from the same seed and the same colours."""
    cfg = load_config("cpu-quick", TINY).appearance
    torch.manual_seed(0)
    plain = RadianceField(cfg, 15)
    torch.manual_seed(0)
    again = RadianceField(cfg, 15, code_dim=0)
    x, f, n, d = (torch.randn(64, k) for k in (3, 15, 3, 3))
    n, d = torch.nn.functional.normalize(n, dim=-1), torch.nn.functional.normalize(d, dim=-1)
    assert all(torch.equal(a, b) for a, b in zip(plain.state_dict().values(), again.state_dict().values(),
                                                  strict=True))
    assert torch.equal(plain(x, f, n, d)["rgb"], again(x, f, n, d)["rgb"])
    codes = RadianceField(cfg, 15, code_dim=8)
    out = codes(x, f, n, d, torch.randn(64, 8))
    assert out["rgb"].shape == (64, 3) and torch.isfinite(out["rgb"]).all()


def test_colour_affine_is_the_identity_at_zero_and_leaves_empty_rays_empty():
    c = torch.rand(5, 3) * torch.tensor([1.0, 1.0, 1.0, 0.5, 0.0])[:, None]
    coverage = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.0])
    assert torch.equal(colour_affine(c, torch.zeros(5, 12), coverage), c)
    a = torch.zeros(5, 12)
    a[:, [0, 4, 8]] = torch.tensor([1.0, -0.5, 0.0])  # red doubled, green halved
    a[:, 11] = 0.2  # blue lifted where the ray sees the scene
    want = c * torch.tensor([2.0, 0.5, 1.0]) + torch.stack([0 * coverage, 0 * coverage, 0.2 * coverage], -1)
    torch.testing.assert_close(colour_affine(c, a, coverage), want)
    assert torch.equal(colour_affine(c, a, coverage)[4], torch.zeros(3))
    assert torch.equal(colour_gain(c, torch.zeros(5, 3)), c)
    torch.testing.assert_close(colour_gain(c, torch.tensor([0.6931472, -0.6931472, 0.0]).expand(5, 3)),
                               c * torch.tensor([2.0, 0.5, 1.0]))
    for kind, dim in (("affine", 12), ("gain", 3)):  # the scene's own colour back from a photo's (full coverage)
        t = torch.randn(dim, generator=torch.Generator().manual_seed(dim)) * 0.2
        photo = colour_transform(kind, c, t.expand(5, dim), torch.ones(5))
        torch.testing.assert_close(undo_colour_transform(kind, photo, t), c)


@pytest.mark.parametrize("kind", ["affine", "gain"])
def test_a_colour_transform_per_image_learns_each_photos_exposure(tmp_path, kind):
    """appearance.embedding_kind=affine|gain on photos re-exposed by known gains: the heads take no code, and the
    transform each training image learns brightens the dark photos and darkens the bright ones."""
    truth = write_test_scene(tmp_path / "s", "nerf-synthetic", n_images=9, width=24, height=16)
    scene = load_scene(tmp_path / "s")
    train = scene.splits["train"]
    gains = np.linspace(0.6, 1.4, len(train))
    for i, g in zip(train, gains, strict=True):  # each training photo exposed by its own gain (RGB, not alpha)
        img = iio.imread(truth.image_paths[i]).astype(np.float64)
        img[..., :3] = np.clip(img[..., :3] * g, 0, 255)
        iio.imwrite(truth.image_paths[i], np.round(img).astype(np.uint8))
    scene = load_scene(tmp_path / "s")
    cfg = load_config("cpu-quick", [*TINY, "appearance.embedding=on", f"appearance.embedding_kind={kind}"])
    tr = Trainer(cfg, scene, tmp_path / "r", torch.device("cpu"), progress=False)
    model = tr.model
    assert model.colour_transform == kind and model.image_codes.codes.shape == (9, {"affine": 12, "gain": 3}[kind])
    assert model.appearance.view_mlp[0].in_features == RadianceField(cfg.appearance, 15).view_mlp[0].in_features
    for _ in range(80):
        tr.train_step()
    # the mean diagonal of M, or the mean log gain
    learned = model.image_codes.codes.detach()[train][:, [0, 4, 8] if kind == "affine" else [0, 1, 2]].mean(1).numpy()
    # 80 steps learn the transforms part of the way, and the path depends on the thread count: their order and the
    # gap between the three darkest and three brightest photos, not the exact values (about 0.085 on 1 and 2 threads)
    assert np.corrcoef(learned, gains)[0, 1] > 0.7, (learned, gains)
    assert learned[-3:].mean() - learned[:3].mean() > 0.04, (learned, gains)


def _state(tr: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in tr.model.state_dict().items()}


def test_resume_is_exact_with_refinement_and_codes_and_the_poses_are_written_and_used(tmp_path, monkeypatch):
    """A colmap capture (both switches auto, so on): 4 steps straight equal 2 + resume + 2, bit for bit;
    refined_cameras.json holds the trained cameras in the dataset's frame, scene_for_run renders them from it, eval
    records the protocol."""
    from anisdf.tasks.evaluate import appearance, evaluate, view_cameras

    truth = write_test_scene(tmp_path / "s", "colmap", n_images=9, width=24, height=16)
    scene = load_scene(tmp_path / "s")
    cfg = load_config("cpu-quick", [*TINY, "cameras.start_step=1", "cameras.lr=1e-2", *AUTO])
    straight = Trainer(cfg, scene, tmp_path / "a", torch.device("cpu"), progress=False)
    assert straight.model.cameras is not None and straight.model.image_codes is not None
    for _ in range(4):
        straight.train_step()
    part = Trainer(cfg, scene, tmp_path / "b", torch.device("cpu"), progress=False)
    part.train_step()
    part.train_step()
    part.save()
    resumed = Trainer(cfg, load_scene(tmp_path / "s"), tmp_path / "b", torch.device("cpu"), progress=False)
    resumed.load_state_dict(torch.load(part.ckpt_path, weights_only=False))
    resumed.train_step()
    stats = resumed.train_step()
    a, b = _state(straight), _state(resumed)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert stats["camera"] > 0 and a["cameras.delta"].abs().max() > 0 and a["image_codes.codes"].abs().max() > 0

    resumed.write_run_files("done")
    resumed.save()
    record = json.loads(RunDir(tmp_path / "b").refined_cameras.read_text())
    train = scene.splits["train"]
    assert [c["index"] for c in record["cameras"]] == train
    names = {c["image"]: c for c in record["cameras"]}
    first = names[truth.image_paths[train[0]].relative_to(tmp_path / "s").as_posix()]
    np.testing.assert_allclose(first["original"], truth.c2w[train[0]], atol=1e-4)  # the dataset's own frame
    assert first["rotation_deg"] > 0
    cfg2, model, ck = load_run(tmp_path / "b")
    assert torch.equal(model.cameras.delta, b["cameras.delta"])
    used = scene_for_run(tmp_path / "b", cfg2, ck)
    refined = model.cameras.refined_poses()
    np.testing.assert_allclose(used.cameras.c2w[train], refined[train], atol=1e-5)
    test = scene.splits["test"]
    assert torch.equal(used.cameras.c2w[test], scene.cameras.c2w[test])  # no correction for test cameras
    monkeypatch.setattr(appearance, "FIT_STEPS", 4)
    monkeypatch.setattr(view_cameras, "FIT_ITERATIONS", 1)
    result = evaluate(tmp_path / "b", split="test", appearance="fit-left-half", progress=False)
    assert result["protocol"]["appearance"]["protocol"] == "fit-left-half"
    assert result["protocol"]["appearance"]["scored"].startswith("right half")
    assert "no learned correction" in result["protocol"]["cameras"]["poses"]
    assert np.isfinite(result["psnr"]) and model.image_codes.fixed is None
    assert appearance.appearance_record(model, "mean")["protocol"] == "mean"


def test_a_resumed_run_keeps_the_parts_its_checkpoint_has():
    """--resume of a run that trained without camera corrections or codes (a rendered scene, or a run from before
    the switches) turns an auto switch off, so the model it builds matches the checkpoint."""
    from anisdf.tasks.train import _settle_switches

    cfg = load_config("cpu-quick", AUTO)
    _settle_switches(cfg, ["geometry.branches.0.grid.table"])
    assert (cfg.cameras.refine, cfg.appearance.embedding) == ("off", "off")
    cfg = load_config("cpu-quick", AUTO)
    _settle_switches(cfg, ["cameras.delta", "image_codes.codes"])
    assert (cfg.cameras.refine, cfg.appearance.embedding) == ("auto", "auto")


def test_fit_left_half_scores_the_right_halves_of_a_run_without_codes_too(tmp_path):
    """Runs with and without codes compare under one protocol: fit-left-half scores right halves for both."""
    from anisdf.cli import main
    from anisdf.tasks.evaluate import evaluate

    write_test_scene(tmp_path / "s", "colmap", n_images=9, width=24, height=16)
    # the cameras as given: eval then scores from the given poses, with no pose fit (not the subject here)
    assert main(["train", str(tmp_path / "s"), "--out", str(tmp_path / "r"), "--preset", "cpu-quick",
                 "--max-steps", "4", "--no-progress", *TINY, "cameras.refine=off"]) == 0
    whole = evaluate(tmp_path / "r", split="test", progress=False)
    half = evaluate(tmp_path / "r", split="test", appearance="fit-left-half", progress=False)
    assert whole["protocol"]["appearance"]["scored"] == "whole image"
    assert half["protocol"]["appearance"]["scored"].startswith("right half")
    assert half["psnr"] != whole["psnr"]


def test_a_test_view_camera_fitted_to_its_image_comes_back_toward_the_true_pose(tmp_path, monkeypatch):
    """eval --cameras fit: a view whose pose is turned by 3 deg, with the model's own render from the true pose as its
    image, gets a fitted pose closer to the true one and a lower image error; the dataset's pose is put back after.
    eval.json names the protocol and each view's correction. The default (auto) fits only runs with refined
    cameras."""
    import dataclasses

    from anisdf.cli import main
    from anisdf.data.rays import RayDataset
    from anisdf.tasks.evaluate import evaluate, view_cameras

    write_test_scene(tmp_path / "s", "nerf-synthetic", n_images=9, width=32, height=24)
    assert main(["train", str(tmp_path / "s"), "--out", str(tmp_path / "r"), "--preset", "cpu-quick",
                 "--max-steps", "4", "--no-progress", *TINY]) == 0
    cfg, model, ck = load_run(tmp_path / "r")
    scene = scene_for_run(tmp_path / "r", cfg, ck, split="test")
    data = RayDataset(scene, "test", background="white")
    index = int(data.indices[0])
    true = data.cameras.c2w[index].clone()
    batch, (h, w) = data.image(0)
    with torch.no_grad():
        target = model.render_rays(batch.origins, batch.directions, batch.background).rgb.float()
    turned = true.clone()
    turned[:, :3] = true[:, :3] @ torch.tensor(Rotation.from_rotvec([np.radians(3.0), 0, 0]).as_matrix()).float()
    c2w = data.cameras.c2w.clone()
    c2w[index] = turned
    data.cameras = dataclasses.replace(data.cameras, c2w=c2w)
    plain_image = data.image

    def image(i):
        b, hw = plain_image(i)
        return dataclasses.replace(b, rgb=target), hw

    monkeypatch.setattr(data, "image", image)
    monkeypatch.setattr(view_cameras, "FIT_RAYS", 512)
    monkeypatch.setattr(view_cameras, "FIT_CHUNK", 200)  # the normal equations summed over chunks

    def error(pose):
        rays = data.cameras.rays(torch.full((h * w,), index), batch.pixels[:, 0], batch.pixels[:, 1])
        o, d = pose[:, 3].expand(h * w, 3), (pose[:, :3] @ true[:, :3].T @ rays[1][..., None])[..., 0]
        with torch.no_grad():
            return float(((model.render_rays(o, d, batch.background).rgb - target) ** 2).mean())

    fitted, kept = view_cameras.fit_camera(model, data, 0)
    assert kept
    def turn(pose):
        return float(pose_changes(true[None].numpy(), pose[None].numpy())[0][0])

    assert turn(fitted) < 0.6 * turn(turned)
    assert error(fitted) < 0.5 * error(turned)
    # a fit that runs away is not kept: the given pose stays
    monkeypatch.setattr(view_cameras, "solve_correction", lambda *a: torch.tensor([0.3, -0.2, 0.0, 0.0, 0.1, 0.0]))
    wild, kept = view_cameras.fit_camera(model, data, 0)
    assert not kept and torch.equal(wild, turned)
    monkeypatch.undo()
    monkeypatch.setattr(data, "image", image)
    assert all(p.requires_grad for p in model.parameters())
    monkeypatch.setattr(view_cameras, "FIT_ITERATIONS", 1)
    with view_cameras.view_camera(model, data, 0, "fit") as record:
        assert torch.equal(data.cameras.c2w[index], data.scene.cameras.c2w[index].to(data.cameras.c2w))
        assert not torch.equal(data.cameras.c2w[index], turned) and record["camera_fit_deg"] > 0
    assert torch.equal(data.cameras.c2w[index], turned)
    result = evaluate(tmp_path / "r", split="test", cameras="fit", max_views=1, progress=False)
    assert result["protocol"]["cameras"]["scored_views"]["protocol"] == "fit"
    assert "camera_fit_deg" in RunDir(tmp_path / "r").read_eval()["per_view"][0]
    # the default, auto: fit for runs that refined their cameras; this one did not, so its views keep their poses
    result = evaluate(tmp_path / "r", split="test", max_views=1, progress=False)
    assert result["protocol"]["cameras"]["scored_views"]["protocol"] == "given"
    assert result["protocol"]["cameras"]["scored_views"]["requested"].startswith("auto")
    assert "camera_fit_deg" not in RunDir(tmp_path / "r").read_eval()["per_view"][0]
    assert [view_cameras.resolve_protocol(p, True) for p in view_cameras.PROTOCOLS] == ["fit", "given", "fit"]
    assert [view_cameras.resolve_protocol(p, False) for p in view_cameras.PROTOCOLS] == ["given", "given", "fit"]
