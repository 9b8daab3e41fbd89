"""The web viewer (viser): the browser's camera rendered by the project's renderer, low resolution first then
refined, a step hook that costs nothing without a browser, ports, and the page itself in headless Chromium."""

from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_training import TINY

from anisdf.cli import main

viser = pytest.importorskip("viser", reason="the viewer extra is not installed (pip install 'anisdf[viewer]')")

from anisdf.viewer.frames import ViewCamera, render_frame  # noqa: E402
from anisdf.viewer.run import open_run, serve  # noqa: E402
from anisdf.viewer.server import Viewer, check_listen  # noqa: E402

CHROMIUM = os.environ.get("ANISDF_CHROMIUM", "/usr/bin/chromium")
FAST = [*TINY, "renderer.march_steps=64", "renderer.init_rays=64", "renderer.min_rays=32"]


@pytest.fixture(scope="module")
def viewed_run(toy_scene, tmp_path_factory) -> Path:
    """A tiny trained run with a mesh and an evaluation, as a user has them after training."""
    out = tmp_path_factory.mktemp("view") / "run"
    assert main(["train", str(toy_scene), "--out", str(out), "--preset", "cpu-quick", "--max-steps", "12",
                 "--no-progress", *FAST]) == 0
    assert main(["extract-mesh", str(out), "--resolution", "32"]) == 0
    assert main(["eval", str(out), "--max-views", "1"]) == 0
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _viser_camera(c2w: np.ndarray, fov: float, aspect: float, stamp: float = 1.0) -> SimpleNamespace:
    """What viser reports for a browser's camera (OpenCV axes, vertical fov)."""
    wxyz = viser.transforms.SO3.from_matrix(c2w[:, :3]).wxyz
    return SimpleNamespace(wxyz=wxyz, position=c2w[:, 3].copy(), fov=fov, aspect=aspect, update_timestamp=stamp)


def test_a_browser_camera_at_a_training_view_renders_that_view(viewed_run):
    """The camera conversion (quaternion, vertical fov, aspect) gives the training camera's own rays."""
    from anisdf.models.views import render_rays_to_maps
    from anisdf.tasks.loading import load_run, scene_for_run

    cfg, model, ck = load_run(viewed_run)
    scene = scene_for_run(viewed_run, cfg, ck, split="train")
    cams = scene.cameras
    c2w = cams.c2w[3].numpy().astype(np.float64)
    fov = 2 * np.arctan(0.5 * cams.height / float(cams.fy[3]))
    frame = render_frame(model, ViewCamera.from_viser(_viser_camera(c2w, fov, cams.width / cams.height)),
                         max(cams.width, cams.height), "rgb", 4096)
    o, d = cams.image_rays(3)
    ref = render_rays_to_maps(model, o.reshape(-1, 3), d.reshape(-1, 3), torch.ones_like(d.reshape(-1, 3)),
                              d.shape[:2], 4096)
    assert frame.image.shape == (cams.height, cams.width, 3)
    assert np.abs(frame.image.astype(float) - np.clip(ref["rgb"], 0, 1) * 255).max() <= 1.0
    hit = ref["opacity"][..., 0] > 0.5
    assert hit.any() and (frame.depth[hit] < 10).all() and (frame.depth[~hit] >= 1000).all()
    # every map, and a model without the blended appearance falls back to rgb for c_ref
    for name in ("normal", "depth", "c_view", "c_ref", "w", "opacity"):
        f = render_frame(model, ViewCamera.from_viser(_viser_camera(c2w, fov, 1.5)), 48, name, 4096)
        assert f.map == name and f.image.shape == (32, 48, 3) and f.image.std() > 0


class _FakeClient:
    """A connected browser as the viewer sees it: a camera and a scene that receives background pictures."""

    def __init__(self, camera: SimpleNamespace) -> None:
        self.client_id = 0
        self.camera = camera
        self.pictures: list[np.ndarray] = []
        self.scene = SimpleNamespace(set_background_image=lambda image, **kw: self.pictures.append(image))


def test_a_moving_camera_gets_a_quick_picture_then_sharper_ones_at_rest(viewed_run):
    from anisdf.tasks.loading import load_run

    _, model, _ = load_run(viewed_run)
    viewer = Viewer(model, None, port=_free_port(), max_resolution=128)
    try:
        c2w = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3.0]])  # looking at the origin down -z
        cam = _viser_camera(c2w, 0.8, 4 / 3, stamp=time.time() + 3600)  # moving (its rest starts in an hour)
        client = _FakeClient(cam)
        viewer._connect(client)
        assert viewer.tick() and client.pictures[-1].shape == (48, 64, 3)  # the first picture: small
        assert not viewer.tick()  # not at rest: nothing more
        cam.update_timestamp = time.time() - 1.0  # moved once more, then rested for a second
        widths = []
        while viewer.tick():
            widths.append(client.pictures[-1].shape[1])
        assert widths and widths[-1] == 128 and widths == sorted(widths)
        viewer.preview_seconds = 1e-4  # another map: a quick picture first again (here the smallest)
        viewer.gui_map.value = "normal"
        assert viewer.tick() and client.pictures[-1].shape[1] == 32
        assert viewer.stats.frames == len(client.pictures)
    finally:
        viewer.close()


def test_open_run_warms_the_renderer_and_sizes_the_first_picture_from_its_speed(viewed_run):
    """``anisdf view`` renders the home view once before any browser connects, so a browser's first picture is
    sized for the preview time from a measured speed instead of the fixed 64 px guess."""
    from anisdf.viewer.run import open_run

    viewer, _ = open_run(viewed_run, port=_free_port(), max_resolution=128)
    try:
        assert viewer.home is not None and viewer._rays_per_second > 0
        viewer.preview_seconds = 1e-4  # so little time that the measured speed allows the smallest picture
        cam = _viser_camera(viewer.home.c2w, viewer.home.fov_y, viewer.home.aspect, stamp=time.time() + 3600)
        client = _FakeClient(cam)
        viewer._connect(client)
        assert viewer.tick() and max(client.pictures[-1].shape[:2]) == 32
        viewer.preview_seconds = 1e3  # and so much that it allows the largest
        cam.update_timestamp += 1
        assert viewer.tick() and max(client.pictures[-1].shape[:2]) == 128
    finally:
        viewer.close()


def test_a_browser_that_leaves_during_a_render_is_sent_nothing(viewed_run, monkeypatch):
    from anisdf.tasks.loading import load_run
    from anisdf.viewer import server

    _, model, _ = load_run(viewed_run)
    viewer = Viewer(model, None, port=_free_port())
    try:
        c2w = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3.0]])
        client = _FakeClient(_viser_camera(c2w, 0.8, 4 / 3, stamp=time.time()))
        viewer._connect(client)
        render = server.render_frame

        def render_then_leave(*a, **k):  # noqa: ANN002, ANN003, ANN202
            frame = render(*a, **k)
            viewer._views.pop(client.client_id)  # viser's disconnect callback, from its own thread
            return frame

        monkeypatch.setattr(server, "render_frame", render_then_leave)
        viewer.tick()
        assert client.pictures == [] and viewer.stats.frames == 0
    finally:
        viewer.close()


def test_a_mesh_goes_to_the_browser_only_when_ticked_and_thinned(viewed_run, monkeypatch):
    """A large extracted mesh would hold back a browser's first picture: it is decimated, and sent on demand."""
    import trimesh

    from anisdf.tasks.loading import load_run
    from anisdf.viewer import server

    _, model, _ = load_run(viewed_run)
    viewer = Viewer(model, None, port=_free_port())
    try:
        sphere = trimesh.creation.icosphere(subdivisions=4)  # 5120 faces
        monkeypatch.setattr(server, "MESH_FACES", 1000)
        added = []
        add = viewer.server.scene.add_mesh_trimesh
        monkeypatch.setattr(viewer.server.scene, "add_mesh_trimesh", lambda name, m, **kw: added.append(m) or add(
            name, m, **kw))
        viewer.set_mesh(sphere)
        assert not added and viewer.mesh is None  # offered, not sent
        assert 500 <= len(viewer.mesh_data.faces) <= 1000
        viewer.gui_mesh.value = True
        assert len(added) == 1 and viewer.mesh is not None and viewer.mesh.visible
        viewer.gui_mesh.value = False
        assert not viewer.mesh.visible and len(added) == 1
        viewer.set_mesh(None)
        assert viewer.mesh is None and viewer.mesh_data is None
    finally:
        viewer.close()


def test_a_browser_starts_at_the_cameras_distance_looking_at_the_centre_among_frustums_sized_to_the_scene(
        viewed_run, toy_scene):
    """The first view: at the training cameras' mean distance from the unit sphere's centre, looking at it with their
    mean up, where no camera stands; each frustum reaches a fixed fraction of that distance, in a scene of any size."""
    from anisdf.data.dataparsers import load_scene
    from anisdf.data.orbit import up_direction
    from anisdf.tasks.loading import load_run
    from anisdf.viewer.server import FRUSTUM_DEPTH

    _, model, _ = load_run(viewed_run)
    scene = load_scene(toy_scene, downscale=1)
    train = scene.splits["train"]
    c2w = scene.cameras.c2w.clone()
    depths = []
    for size in (1.0, 3.0):  # the same cameras, three times as far
        scene.cameras.c2w = torch.cat([c2w[:, :, :3], c2w[:, :, 3:] * size], -1)
        centres = scene.cameras.c2w[train, :, 3].numpy().astype(np.float64)
        dist = float(np.linalg.norm(centres, axis=1).mean())
        viewer = Viewer(model, scene, port=_free_port())
        try:
            start = viewer.server.initial_camera
            eye = np.asarray(start.position)
            assert np.linalg.norm(eye) == pytest.approx(dist, rel=1e-6)
            assert np.allclose(start.look_at, 0.0)
            assert np.allclose(start.up, up_direction(scene.cameras.c2w[train]).numpy(), atol=1e-6)
            home = viewer.home.c2w
            assert np.allclose(home[:, 3], eye) and np.allclose(home[:, 2], -eye / dist, atol=1e-9)  # at the centre
            assert np.dot(-home[:, 1], start.up) > 0.5  # the picture's up is the cameras' up
            assert len(viewer.frustums) == len(train)
            depth = [f.scale * f.compute_canonical_frustum_size()[2] for f in viewer.frustums]
            assert np.allclose(depth, FRUSTUM_DEPTH * dist, rtol=1e-6) and FRUSTUM_DEPTH <= 0.15
            assert np.linalg.norm(centres - eye, axis=1).min() > 2 * depth[0]  # no frustum at the eye
            depths.append(depth[0])
        finally:
            viewer.close()
    assert depths[1] == pytest.approx(3 * depths[0], rel=1e-6)


def test_the_step_hook_changes_nothing_and_costs_nothing_without_a_browser(toy_scene, tmp_path):
    from anisdf.config import load_config
    from anisdf.data.dataparsers import load_scene
    from anisdf.training.trainer import Trainer

    def run(name: str, with_viewer: bool) -> tuple[dict, int, int]:
        cfg = load_config("cpu-quick", [*FAST, "train.max_steps=4"])
        scene = load_scene(toy_scene, downscale=1)
        tr = Trainer(cfg, scene, tmp_path / name, torch.device("cpu"), progress=False)
        viewer = None
        if with_viewer:
            viewer = Viewer(tr.model, scene, port=_free_port(), live=True)
            tr.step_hooks.append(viewer.on_step)
        try:
            tr.fit()
        finally:
            if viewer is not None:
                viewer.close()
        return tr.model.state_dict(), viewer.model_version if viewer else 0, viewer.stats.frames if viewer else 0

    plain, _, _ = run("plain", False)
    viewed, version, frames = run("viewed", True)
    assert version == 4 and frames == 0  # called after every step, rendered nothing
    for k, v in plain.items():
        assert torch.equal(v, viewed[k]), k


def test_the_live_viewer_renders_between_steps_and_ctrl_c_keeps_a_resumable_checkpoint(toy_scene, tmp_path):
    from anisdf.config import load_config
    from anisdf.data.dataparsers import load_scene
    from anisdf.training.trainer import Trainer

    cfg = load_config("cpu-quick", [*FAST, "train.max_steps=50"])
    scene = load_scene(toy_scene, downscale=1)
    tr = Trainer(cfg, scene, tmp_path / "run", torch.device("cpu"), progress=False)
    viewer = Viewer(tr.model, scene, port=_free_port(), live=True, refresh_seconds=0.0, refresh_share=1.0,
                    max_resolution=128)
    c2w = scene.cameras.c2w[0].numpy().astype(np.float64)
    cam = _viser_camera(c2w, 0.7, 1.0, stamp=time.time() - 10)
    client = _FakeClient(cam)
    viewer._connect(client)
    seen: list[int] = []

    def interrupt_at_step_4(trainer: Trainer, stats: dict) -> None:
        seen.append(len(client.pictures))
        if trainer.state.step == 4:
            raise KeyboardInterrupt  # Ctrl-C while the viewer is serving

    tr.step_hooks += [viewer.on_step, interrupt_at_step_4]
    try:
        summary = tr.fit()
    finally:
        viewer.close()
    assert summary["status"] == "interrupted" and summary["step"] == 4
    # pictures between steps: a quick one, a sharper one, then the resting view again as the model learns
    assert seen == [1, 2, 3, 4]
    assert main(["train", str(toy_scene), "--out", str(tmp_path / "run"), "--resume", "--max-steps", "5",
                 "--no-progress"]) == 0


def test_ports_and_hosts(viewed_run, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert not check_listen("127.0.0.1", port)
        from anisdf.tasks.loading import load_run

        _, model, _ = load_run(viewed_run)
        viewer = Viewer(model, None, port=port)
        try:
            assert viewer.port != port and f"port {port} is in use" in viewer.announce()
            assert viewer.url == f"http://127.0.0.1:{viewer.port}/"
        finally:
            viewer.close()
    assert main(["view", str(viewed_run), "--host", "203.0.113.7"]) == 2  # an address this machine does not have
    assert "--host 203.0.113.7: cannot listen there" in capsys.readouterr().err
    assert main(["view", str(viewed_run.parent / "nothing")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["view", str(viewed_run), "--port", "70000"])
    assert "must be a port number from 1 to 65535" in capsys.readouterr().err
    assert main(["train", "data", "--out", "x", "--port", "7100"]) == 2
    assert "add --viewer" in capsys.readouterr().err


def _browser():  # noqa: ANN202
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install chromium; .ci/run does)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright is not installed (pip install -e '.[dev]')")
    return sync_playwright


def _shot(page) -> np.ndarray:  # noqa: ANN001
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(page.locator("canvas").first.screenshot())).convert("RGB")).astype(float)


def _wait(cond, seconds: float = 30.0) -> None:  # noqa: ANN001
    t = time.monotonic()
    while not cond():
        if time.monotonic() - t > seconds:
            raise AssertionError("timed out")
        time.sleep(0.05)


def _settled(page, seconds: float = 30.0) -> np.ndarray:
    """A screenshot once the viewer has stopped refining it: two shots half a second apart within 0.3 levels."""
    shot, t = _shot(page), time.monotonic()
    while True:
        time.sleep(0.5)
        again = _shot(page)
        if np.abs(again - shot).mean() < 0.3:
            return again
        if time.monotonic() - t > seconds:
            raise AssertionError("the picture did not settle")
        shot = again


def test_the_page_shows_the_run_moves_and_switches_to_normals(viewed_run, tmp_path):
    sync_playwright = _browser()
    viewer, watcher = open_run(viewed_run, port=_free_port(), max_resolution=256)
    assert viewer.gui_mesh is not None and viewer.eval_folder is not None and len(viewer.frustums) == 16
    stop = threading.Event()
    server = threading.Thread(target=serve, args=(viewer, watcher, stop), daemon=True)
    server.start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
            page = browser.new_page(viewport={"width": 960, "height": 640})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=30_000)
            _wait(lambda: viewer.stats.frames >= 2)  # a first picture, then a sharper one
            time.sleep(1.0)
            first = _settled(page)
            assert first.std() > 10, "the canvas is blank"
            box = page.locator("canvas").first.bounding_box()
            x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            frames = viewer.stats.frames
            page.mouse.move(x, y)
            page.mouse.down()
            page.mouse.move(x + 300, y + 60, steps=10)
            page.mouse.up()
            _wait(lambda: viewer.stats.frames > frames + 1)
            time.sleep(1.0)
            moved = _settled(page)
            # settled pictures of a resting camera differ by under 0.3 (8-bit levels, mean over the canvas); this drag
            # changes it by 2.6-4.3, the less on a machine busy with other tests
            change = np.abs(moved - first).mean()
            assert change > 1.0, f"the picture did not change when the camera moved ({change:.2f})"
            page.get_by_label("Map", exact=True).click()
            page.get_by_role("option", name="normal", exact=True).click()
            _wait(lambda: viewer.gui_map.value == "normal")
            frames = viewer.stats.frames
            _wait(lambda: viewer.stats.frames > frames + 1)
            time.sleep(1.0)
            normals = _shot(page)
            assert np.abs(normals - moved).mean() > 3, "the normal map looks like the rgb picture"
            assert viewer._status.get("note") is None
            keep = os.environ.get("ANISDF_VIEWER_SCREENSHOT")  # docs/viewer.png is made this way
            path = Path(keep) if keep else tmp_path / "viewer.png"
            page.screenshot(path=str(path))
            browser.close()
    finally:
        stop.set()
        server.join(timeout=10)
