"""``anisdf view RUN``: a run folder in the browser, kept up to date while it changes (a run still training, a mesh
extracted or an evaluation written meanwhile)."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from anisdf.errors import AnisdfError
from anisdf.run_dir import RunDir
from anisdf.viewer.server import Viewer, ViewOptions, import_viser

log = logging.getLogger("anisdf")

POLL_SECONDS = 2.0
"""How often the run folder is looked at for a newer checkpoint, mesh or evaluation."""


def _mtime(path: Path) -> float | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def mesh_path(run: Path) -> Path | None:
    """The mesh ``extract-mesh`` wrote (named in RUN/mesh.json), else RUN/mesh.ply|obj|glb, else None."""
    return RunDir(run).existing_mesh()


class RunWatcher:
    """Loads a run's checkpoint, mesh and evaluation into a :class:`Viewer`, again whenever one of them changes."""

    def __init__(self, run: Path, viewer: Viewer, device: Any, to_world: np.ndarray) -> None:
        self.run, self.viewer, self.device = Path(run), viewer, device
        self.to_world = np.asarray(to_world, dtype=np.float64)
        self._stamps: dict[str, Any] = {}
        self._polled = 0.0

    def _changed(self, name: str, stamp: Any) -> bool:
        old = self._stamps.get(name, "never")
        self._stamps[name] = stamp
        return old != stamp

    def poll(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._polled < POLL_SECONDS:
            return
        self._polled = now
        from anisdf.tasks.loading import load_run

        ckpt = RunDir(self.run).checkpoint
        if self._changed("ckpt", _mtime(ckpt)) and not force:  # the first (forced) poll follows open_run's load
            try:
                _, model, ck = load_run(self.run, self.device)
            except AnisdfError as e:  # e.g. caught between a write and its rename on an odd file system
                log.warning("viewer: %s", e)
            else:
                self.viewer.set_model(model)
                self._set_run_status(ck)
        mesh = mesh_path(self.run)
        if self._changed("mesh", (mesh, _mtime(mesh) if mesh else None)):
            self.viewer.set_mesh(self._load_mesh(mesh) if mesh else None)
        rd = RunDir(self.run)
        if self._changed("eval", _mtime(rd.eval_json)) and rd.eval_json.is_file():
            content = rd.read_eval()
            if content is None:
                log.warning("viewer: %s is unreadable", rd.eval_json)
            else:
                metrics = {k: v for k, v in content.items() if k not in ("protocol", "per_view")}
                self.viewer.set_eval(metrics, rd.eval_panels())

    def _set_run_status(self, ck: dict[str, Any]) -> None:
        status = RunDir(self.run).status() or "?"
        self.viewer.set_status(step=int(ck["state"]["step"]), status=f"run {status}")

    def _load_mesh(self, path: Path) -> Any | None:
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as e:  # noqa: BLE001  (trimesh raises many kinds on a damaged file)
            log.warning("viewer: cannot read %s (%s)", path, e)
            return None
        mesh.apply_transform(np.linalg.inv(self.to_world))  # meshes are written in the dataset's frame
        return mesh


def open_run(run: Path, options: ViewOptions | None = None, **changes: Any) -> tuple[Viewer, RunWatcher]:
    """A viewer of the run folder ``run`` with its training cameras (when the dataset is still there), mesh and
    evaluation; ``changes`` replace fields of ``options``."""
    o = dataclasses.replace(options or ViewOptions(), **changes)
    import_viser()
    from anisdf.tasks.loading import load_run, scene_for_run
    from anisdf.utils.devices import pick_device

    run = Path(run)
    if not run.is_dir():
        raise AnisdfError(f"{run}: no such run folder")
    dev = pick_device(o.device or "auto")
    cfg, model, ck = load_run(run, dev)
    try:
        scene = scene_for_run(run, cfg, ck, split="train")
    except AnisdfError as e:
        log.warning("viewer: no training cameras: %s", e)
        scene = None
    viewer = Viewer(model, scene, port=o.port, host=o.host, title=f"anisdf · {run.name}",
                    max_resolution=o.max_resolution)
    watcher = RunWatcher(run, viewer, dev, np.asarray(ck["to_world"]))
    watcher._set_run_status(ck)
    watcher.poll(force=True)
    viewer.warm_up()
    return viewer, watcher


def serve(viewer: Viewer, watcher: RunWatcher | None = None, stop: threading.Event | None = None) -> None:
    """Render for the browsers until ``stop`` is set or Ctrl-C, then close the server."""
    try:
        while stop is None or not stop.is_set():
            if watcher is not None:
                watcher.poll()
            if not viewer.tick():
                time.sleep(0.01)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()


def view(run: Path, options: ViewOptions | None = None, **changes: Any) -> None:
    """``anisdf view``: serve ``run`` until Ctrl-C."""
    viewer, watcher = open_run(run, options, **changes)
    print(viewer.announce() + " (Ctrl-C to stop)", flush=True)
    serve(viewer, watcher)
