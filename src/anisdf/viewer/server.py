"""The viser server: training cameras, the model rendered from each browser's camera, map choice, mesh, eval figures.

Rendering happens only in :meth:`Viewer.tick`, called by whoever owns the model: the training loop between steps
(``anisdf train --viewer``) or the loop of ``anisdf view``. viser's own threads only record what the browsers ask
for (their cameras, the chosen map) in plain attributes; nothing here takes a lock the training loop could wait on,
and with no browser connected a tick returns at once.

A camera that moves gets a small picture (sized so that it renders in about ``preview_seconds``); once it rests the
picture is rendered again at twice the size, level after level, up to the "max resolution" slider. While training,
a resting view is rendered again as the model changes, at most every ``refresh_seconds`` and for at most
``refresh_share`` of the time.
"""

from __future__ import annotations

import contextlib
import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.data.orbit import look_at, up_direction
from anisdf.errors import AnisdfError
from anisdf.models.anisdf import AniSDFModel
from anisdf.models.views import MAP_NAMES
from anisdf.utils.options import int_at_least, option, port_number
from anisdf.viewer.frames import Frame, ViewCamera, render_frame

log = logging.getLogger("anisdf")


_PORT = 7007


@dataclass(kw_only=True)
class ViewOptions:
    """How ``anisdf view`` (and ``train --viewer``) serve a run."""

    port: int = option(_PORT, f"viewer port (default {_PORT}; when taken, the next free one, said at start)",
                       port_number)
    host: str = option("127.0.0.1", "viewer address to listen on (0.0.0.0: every interface)")
    max_resolution: int = option(512, "long side in pixels of a resting view (a slider in the page changes it)",
                                 int_at_least(64))
    device: str | None = option(None, "auto | cpu | cuda[:N]")


MIN_PREVIEW = 32
"""Smallest long side (pixels) of a moving camera's picture."""
REST_SECONDS = 0.25
"""A camera unchanged this long counts as resting: its picture is refined."""
MESH_FACES = 200_000
"""The mesh shown in the browser is decimated to at most this many faces."""
FRUSTUM_DEPTH = 0.06
"""A training camera's frustum reaches this fraction of the cameras' mean distance from the centre towards it."""
FRUSTUM_LINE_PX = 1.5
"""Width of the frustums' lines, in screen pixels."""
HOME_NEIGHBOURS = 6
"""A browser's first view is halfway from the first training camera to one of this many nearest neighbours."""


def _display_mesh(mesh: Any) -> Any:
    """``mesh`` with at most :data:`MESH_FACES` faces (the export's quadric decimation)."""
    from anisdf.export.mesh import decimate

    return decimate(mesh, MESH_FACES)


def home_view(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A browser's first view of the scene seen by the training cameras ``c2w`` [N, 3, 4] (normalised frame): its
    pose [3, 4] (OpenCV axes), the cameras' mean up direction, and their mean distance from the centre.

    The view looks at the centre of the unit sphere (the origin) from the cameras' mean distance, with their up,
    from beside the first camera: halfway to whichever of its :data:`HOME_NEIGHBOURS` nearest neighbours leaves the
    eye farthest from every camera, so that no frustum sits at the eye or fills the picture."""
    centres = c2w[:, :, 3]
    norms = np.linalg.norm(centres, axis=1)
    dist = float(norms.mean())
    ways = centres / np.maximum(norms, 1e-12)[:, None]
    way, clearance = ways[0], 0.0
    for k in np.argsort(np.linalg.norm(centres - centres[0], axis=1))[1:HOME_NEIGHBOURS + 1]:
        mid = ways[0] + ways[k]
        if np.linalg.norm(mid) < 1e-6:  # opposite cameras
            continue
        mid = mid / np.linalg.norm(mid)
        gap = float(np.linalg.norm(ways - mid, axis=1).min())
        if gap > clearance:
            way, clearance = mid, gap
    up = up_direction(c2w).numpy()
    return look_at(way * dist, np.zeros(3), up).numpy(), up, dist


def frustum_scale(fov: float, aspect: float, dist: float) -> float:
    """viser's ``scale`` for a frustum whose image plane is :data:`FRUSTUM_DEPTH` x ``dist`` from its apex (viser
    scales a frustum to a constant volume: its depth at scale 1 is ``cbrt(3 / (tan(fov / 2)^2 aspect))``)."""
    half = float(np.tan(fov / 2.0))
    return FRUSTUM_DEPTH * max(dist, 1e-3) * float(np.cbrt(half * half * aspect / 3.0))


def import_viser():  # noqa: ANN201
    """viser, or an AnisdfError saying how to install it."""
    try:
        import viser
    except ImportError:
        raise AnisdfError("the viewer needs viser: pip install 'anisdf[viewer]'") from None
    return viser


def check_listen(host: str, port: int) -> bool:
    """True when ``port`` is free on ``host``, False when it is taken; an AnisdfError naming ``--host`` when nothing
    can listen on ``host`` at all (viser would otherwise try port after port)."""
    import socket

    try:
        family = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0][0]
    except (socket.gaierror, UnicodeError) as e:
        raise AnisdfError(f"--host {host}: unknown address ({e})") from None
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, 0))
        except OSError as e:
            raise AnisdfError(f"--host {host}: cannot listen there ({e.strerror or e})") from None
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server will
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


@dataclass
class _ClientView:
    """What one browser has been shown."""

    client: Any
    camera_stamp: float = -1.0
    """viser's update time of the camera last rendered."""
    key: tuple = ()
    """(map, max resolution, model version) of the last picture."""
    long_side: int = 0
    t_frame: float = 0.0
    last_seconds: float = 0.0
    frames: int = 0


@dataclass
class ViewerStats:
    """Counters for tests and the status line."""

    frames: int = 0
    render_seconds: float = 0.0
    sizes: list[tuple[int, int]] = field(default_factory=list)
    """(height, width) of recent pictures, newest last (at most 50)."""


class Viewer:
    """A viser server showing ``model`` (in ``scene``'s normalised frame) to every connected browser.

    ``scene`` gives the training cameras and their images (None: no frustums). ``live``: the model is training
    (the status shows the step; resting views are refreshed as it changes). Call :meth:`tick` often from the
    thread that owns the model, and :meth:`close` at the end.
    """

    def __init__(self, model: AniSDFModel, scene: Any | None = None, *, port: int = ViewOptions.port,
                 host: str = ViewOptions.host, title: str = "anisdf", live: bool = False,
                 max_resolution: int = ViewOptions.max_resolution,
                 preview_seconds: float = 0.1, refresh_seconds: float = 2.0, refresh_share: float = 0.25,
                 max_cameras: int = 200) -> None:
        viser = import_viser()
        self.model = model
        self.model_version = 0
        self.chunk = model.cfg.renderer.eval_chunk_rays
        self.live = live
        self.title = title
        self.preview_seconds = preview_seconds
        self.refresh_seconds = refresh_seconds
        self.refresh_share = refresh_share
        self.stats = ViewerStats()
        self._rays_per_second = 0.0
        self._views: dict[int, _ClientView] = {}
        self._status: dict[str, Any] = {}
        self._status_shown: float = 0.0
        check_listen(host, port)  # a bad host is an error; a taken port makes viser take the next free one
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: announce() says it in one line
            self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = self.server.get_port()
        self.host = host
        self.requested_port = port
        self.server.gui.configure_theme(control_width="large", show_share_button=False)  # sharing needs internet
        s = self.server.gui
        self.gui_status = s.add_markdown(f"**{title}**")
        self.gui_map = s.add_dropdown("Map", MAP_NAMES, initial_value="rgb", hint="what the view shows")
        self.gui_resolution = s.add_slider("Max resolution", min=64, max=max(2048, max_resolution), step=32,
                                           initial_value=max_resolution,
                                           hint="long side in pixels of a resting view (moving: smaller)")
        self.gui_cameras = s.add_checkbox("Training cameras", True)
        self.gui_cameras.on_update(lambda _: self._show_cameras(self.gui_cameras.value))
        self.frustums: list[Any] = []
        self.mesh = None
        """The mesh's scene node, once shown."""
        self.mesh_data = None
        self.gui_mesh = None
        self.eval_folder = None
        self.home: ViewCamera | None = None
        """Where a new browser's camera starts (:func:`home_view`; None without a scene)."""
        if scene is not None:
            self._add_cameras(scene, max_cameras)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda c: self._views.pop(c.client_id, None))

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def announce(self) -> str:
        """The line printed at start: the URL, and the port given up when the asked one was taken."""
        note = (f" (port {self.requested_port} is in use; took the next free one)"
                if self.port != self.requested_port else "")
        return f"viewer: open {self.url} in a browser{note}"

    # ------------------------------------------------------------------------------------------ scene
    def _add_cameras(self, scene: Any, max_cameras: int) -> None:
        """The training views as frustums showing their images; clicking one moves the browser's camera there."""
        from PIL import Image
        from viser import transforms

        from anisdf.utils.images import to_rgb_uint8

        cams = scene.cameras
        idx = list(scene.splits.get("train") or range(len(cams)))
        if len(idx) > max_cameras:
            idx = [idx[int(i)] for i in np.linspace(0, len(idx) - 1, max_cameras)]
        c2w = cams.c2w.cpu().numpy().astype(np.float64)
        home, up, dist = home_view(c2w[idx])
        self.server.scene.set_up_direction(up)
        fov = [2.0 * float(np.arctan(0.5 * cams.height / float(cams.fy[i]))) for i in idx]
        aspect = cams.width / cams.height
        thumb = (max(1, round(96 * min(1.0, aspect))), max(1, round(96 / max(1.0, aspect))))  # (w, h)
        for n, i in enumerate(idx):
            img = scene.images[i].cpu().numpy()
            cover = scene.coverage()
            if cover is not None and scene.background == "rgba":
                img = to_rgb_uint8(np.concatenate([img, cover[i].cpu().numpy()[..., None]], -1))
            img = np.asarray(Image.fromarray(img).resize(thumb, Image.BILINEAR))
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{n:04d}", fov=fov[n], aspect=aspect, scale=frustum_scale(fov[n], aspect, dist),
                thickness=FRUSTUM_LINE_PX, thickness_units="screen", image=img, format="jpeg", jpeg_quality=80,
                wxyz=transforms.SO3.from_matrix(c2w[i, :, :3]).wxyz, position=c2w[i, :, 3], color=(40, 90, 200))
            handle.on_click(self._go_to_frustum)
            self.frustums.append(handle)
        self.server.initial_camera.position = tuple(home[:, 3])
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self.server.initial_camera.up = tuple(up)
        self.server.initial_camera.fov = fov[0]
        self.home = ViewCamera(home, fov[0], aspect)

    @staticmethod
    def _go_to_frustum(event: Any) -> None:
        frustum, client = event.target, event.client
        if client is None:
            return
        with client.atomic():
            client.camera.wxyz = frustum.wxyz
            client.camera.position = frustum.position
            client.camera.fov = frustum.fov

    def _show_cameras(self, visible: bool) -> None:
        for f in self.frustums:
            f.visible = visible

    def set_mesh(self, mesh: Any | None) -> None:
        """Offer (or replace, or with None remove) a trimesh mesh in the normalised frame behind the "Mesh" checkbox.

        The mesh goes to the browsers only once the box is ticked, decimated to :data:`MESH_FACES` faces: a 512^3
        marching-cubes mesh (over a million faces, tens of MB) sent to every new browser with the scene would hold
        back its first picture by tens of seconds."""
        if self.mesh is not None:
            self.mesh.remove()
            self.mesh = None
        self.mesh_data = None if mesh is None else _display_mesh(mesh)
        if mesh is None:
            return
        if self.gui_mesh is None:
            self.gui_mesh = self.server.gui.add_checkbox("Mesh", False, hint="the extracted mesh (RUN/mesh.*)")
            self.gui_mesh.on_update(lambda _: self._show_mesh(self.gui_mesh.value))
        self._show_mesh(self.gui_mesh.value)

    def _show_mesh(self, visible: bool) -> None:
        if self.mesh is None and visible and self.mesh_data is not None:
            self.mesh = self.server.scene.add_mesh_trimesh("/mesh", self.mesh_data)
        elif self.mesh is not None:
            self.mesh.visible = visible

    def set_eval(self, metrics: dict[str, Any], figures: list[Path]) -> None:
        """The scores of RUN/eval.json and its figures (RUN/eval/*.png), one at a time."""
        from PIL import Image

        if self.eval_folder is not None:
            self.eval_folder.remove()
        self.eval_folder = self.server.gui.add_folder("Evaluation")
        with self.eval_folder:
            rows = [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |"
                    for k, v in metrics.items() if isinstance(v, int | float | str) and k != "gt_mesh"]
            self.server.gui.add_markdown("| | |\n|---|---|\n" + "\n".join(rows))
            if figures:
                names = [p.name for p in figures]
                choice = self.server.gui.add_dropdown("Figure", names, initial_value=names[0])
                image = self.server.gui.add_image(np.asarray(Image.open(figures[0]).convert("RGB")), format="jpeg")

                def show(_: Any) -> None:
                    image.image = np.asarray(Image.open(figures[names.index(choice.value)]).convert("RGB"))

                choice.on_update(show)

    # ------------------------------------------------------------------------------------------ clients
    def _connect(self, client: Any) -> None:
        self._views[client.client_id] = _ClientView(client)

    @property
    def n_clients(self) -> int:
        return len(self._views)

    def set_model(self, model: AniSDFModel) -> None:
        """A new model (a reloaded checkpoint): every view is rendered again."""
        self.model = model
        self.model_version += 1

    def model_changed(self) -> None:
        """The model's weights changed in place (a training step)."""
        self.model_version += 1

    def set_status(self, **status: Any) -> None:
        self._status.update(status)

    def on_step(self, trainer: Any, stats: dict[str, float]) -> None:
        """The training loop's step hook (Trainer.step_hooks): a dict update and a counter when nobody watches."""
        self.model_version += 1
        if self._views:
            self._status.update(step=trainer.state.step, psnr=stats.get("psnr"), loss=stats.get("total"))
            self.tick()

    # ------------------------------------------------------------------------------------------ rendering
    def warm_up(self, long_side: int = 48) -> float | None:
        """Render one small picture of the home view before any browser asks, and return its seconds (None without
        a home view). The renderer's first call in a process costs several times a later one (allocator and thread
        pools); paid here, a browser's first picture comes sooner, and is sized from a measured speed."""
        if self.home is None:
            return None
        render_frame(self.model, self.home, long_side, "rgb", self.chunk)  # the cold call
        frame = render_frame(self.model, self.home, long_side, "rgb", self.chunk)
        self._rays_per_second = frame.rays / max(frame.seconds, 1e-6)
        return frame.seconds

    def _preview_side(self, aspect: float) -> int:
        if self._rays_per_second <= 0:
            return 64
        rays = self._rays_per_second * self.preview_seconds
        side = int(np.sqrt(rays * max(aspect, 1.0 / aspect)))
        return int(np.clip(side // 8 * 8, MIN_PREVIEW, self.gui_resolution.value))

    def _work(self, cv: _ClientView, now: float) -> int | None:
        """The long side of the next picture this browser needs, or None."""
        try:
            stamp, aspect = cv.client.camera.update_timestamp, cv.client.camera.aspect
        except (AssertionError, ZeroDivisionError):  # no camera message yet
            return None
        top = int(self.gui_resolution.value)
        key = (self.gui_map.value, top)
        if stamp != cv.camera_stamp or key != cv.key[:2]:
            return self._preview_side(aspect)  # moved (or another map): a quick picture first
        if now - stamp < REST_SECONDS:
            return None
        if cv.long_side < top:
            return min(top, cv.long_side * 2)  # resting: sharper
        wait = max(self.refresh_seconds, cv.last_seconds * (1.0 / self.refresh_share - 1.0))
        if cv.key[2] != self.model_version and now - cv.t_frame >= wait:
            return cv.long_side  # the model changed under a resting view
        return None

    def tick(self) -> bool:
        """Render at most one picture for one browser that needs one; True when it did. Without browsers, nothing."""
        if not self._views:
            return False
        now = time.time()
        self._show_status(now)
        for cv in sorted(tuple(self._views.values()), key=lambda v: v.t_frame):  # viser's threads may add one
            side = self._work(cv, now)
            if side is None:
                continue
            camera = cv.client.camera
            stamp, map_name, top, version = camera.update_timestamp, self.gui_map.value, self.gui_resolution.value, \
                self.model_version
            frame = render_frame(self.model, ViewCamera.from_viser(camera), side, map_name, self.chunk)
            if cv.client.client_id not in self._views:  # the browser left while this picture was rendered
                return True
            self._show(cv, frame)
            cv.camera_stamp, cv.key, cv.long_side = stamp, (map_name, top, version), side
            cv.t_frame, cv.last_seconds = time.time(), frame.seconds
            return True
        return False

    def _show(self, cv: _ClientView, frame: Frame) -> None:
        cv.client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=90, depth=frame.depth)
        cv.frames += 1
        self.stats.frames += 1
        self.stats.render_seconds += frame.seconds
        self.stats.sizes = (self.stats.sizes + [frame.image.shape[:2]])[-50:]
        rps = frame.rays / max(frame.seconds, 1e-6)
        self._rays_per_second = rps if self._rays_per_second <= 0 else 0.7 * self._rays_per_second + 0.3 * rps
        if frame.map != self.gui_map.value:
            self._status["note"] = f"this model has no {self.gui_map.value} map; showing rgb"
        else:
            self._status.pop("note", None)

    def _show_status(self, now: float) -> None:
        if now - self._status_shown < 1.0:
            return
        self._status_shown = now
        st = self._status
        parts = [f"**{self.title}**"]
        if "step" in st:
            parts.append(f"step {st['step']}" + (" (training)" if self.live else ""))
        if st.get("psnr") is not None:
            parts.append(f"train PSNR {st['psnr']:.2f} dB")
        if "status" in st:
            parts.append(str(st["status"]))
        if "note" in st:
            parts.append(st["note"])
        text = " · ".join(parts)
        if text != self.gui_status.content:
            self.gui_status.content = text

    def close(self) -> None:
        self.server.stop()
