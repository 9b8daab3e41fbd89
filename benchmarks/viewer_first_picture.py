"""What the web viewer costs: ``python benchmarks/viewer_first_picture.py RUN [--data DATA] [--steps 150]
[--repeats 2] [--skip-training]``.

1. First picture: ``anisdf view RUN`` (its :func:`~anisdf.viewer.run.open_run`) served to headless Chromium (Debian's
   ``chromium``, SwiftShader WebGL, as the tests use it). Times, from ``page.goto``: the browser's connection, its
   first camera message, the first picture sent (and how long that picture took to render, its size), the sharper
   pictures that follow while the camera rests; beside them, how long a bare viser page (empty scene) takes to load
   and connect. The target: a first picture within 2 s.
2. ``train --viewer`` with nobody connected: ``--steps`` steps of cpu-quick on DATA (default: the run's dataset) with
   and without the viewer, ``--repeats`` times each, alternating; the step hook's own time is also timed per call.

Prints a table; CPU timings on a shared machine: say what else ran.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import threading
import time
from pathlib import Path

from anisdf.cli import main as cli_main

CHROMIUM = os.environ.get("ANISDF_CHROMIUM", "/usr/bin/chromium")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _open(p):  # noqa: ANN001, ANN202  (playwright's sync API)
    """Headless Debian Chromium with software WebGL (as the tests run it) and a 960 x 640 page."""
    browser = p.chromium.launch(executable_path=CHROMIUM, args=[
        "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
    return browser, browser.new_page(viewport={"width": 960, "height": 640})


def first_picture(run: Path, rest_seconds: float = 6.0) -> dict[str, float | str]:
    """Seconds from page.goto to the browser's connection, its camera, the first and later pictures."""
    from playwright.sync_api import sync_playwright

    from anisdf.viewer.run import open_run, serve

    t0 = time.perf_counter()
    viewer, watcher = open_run(run, port=_free_port())
    t_open = time.perf_counter() - t0
    events: dict[str, float] = {}
    shown: list[tuple[float, tuple[int, int], float]] = []
    show = viewer._show

    def timed_show(cv, frame):  # noqa: ANN001, ANN202
        shown.append((time.perf_counter(), frame.image.shape[:2], frame.seconds))
        return show(cv, frame)

    viewer._show = timed_show
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(viewer, watcher, stop), daemon=True)
    thread.start()
    try:
        with sync_playwright() as p:
            browser, page = _open(p)
            start = time.perf_counter()
            page.goto(viewer.url)
            while time.perf_counter() - start < 120 and (not shown or time.perf_counter() - shown[0][0] < rest_seconds):
                now = time.perf_counter()
                if "connected" not in events and viewer.n_clients:
                    events["connected"] = now - start
                if "camera" not in events and viewer.n_clients:
                    cv = next(iter(viewer._views.values()))
                    try:
                        cv.client.camera.update_timestamp  # noqa: B018  (raises until the first camera message)
                        events["camera"] = now - start
                    except (AssertionError, ZeroDivisionError):
                        pass
                time.sleep(0.005)
            browser.close()
    finally:
        stop.set()
        thread.join(timeout=10)
    if not shown:
        raise SystemExit("no picture was sent in 120 s")
    out: dict[str, float | str] = {"open_run_s": t_open, **{f"{k}_s": v for k, v in events.items()}}
    out["first_picture_s"] = shown[0][0] - start
    out["first_after_camera_s"] = shown[0][0] - start - events.get("camera", 0.0)
    out["first_render_s"] = shown[0][2]
    out["first_size"] = "x".join(map(str, shown[0][1][::-1]))
    out["pictures"] = len(shown)
    out["last_size"] = "x".join(map(str, shown[-1][1][::-1]))
    out["last_at_s"] = shown[-1][0] - start
    return out


def bare_viser_connect() -> float:
    """Seconds from page.goto to the connection of a viser server with an empty scene: the page's own load."""
    import contextlib
    import io

    import viser
    from playwright.sync_api import sync_playwright

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(port=_free_port(), verbose=False)
    clients: list[float] = []
    server.on_client_connect(lambda _c: clients.append(time.perf_counter()))
    try:
        with sync_playwright() as p:
            browser, page = _open(p)
            start = time.perf_counter()
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            while not clients and time.perf_counter() - start < 60:
                time.sleep(0.005)
            browser.close()
    finally:
        server.stop()
    if not clients:
        raise SystemExit("the bare viser page did not connect in 60 s")
    return clients[0] - start


def training_overhead(data: Path, steps: int, repeats: int, work: Path) -> dict[str, list[float]]:
    """Wall seconds of ``steps`` cpu-quick steps with and without ``--viewer`` (nobody connected)."""
    times: dict[str, list[float]] = {"plain": [], "viewer": []}
    for r in range(repeats):
        for kind in ("plain", "viewer") if r % 2 == 0 else ("viewer", "plain"):
            out = work / f"{kind}{r}"
            extra = ["--viewer", "--port", str(_free_port())] if kind == "viewer" else []
            t = time.perf_counter()
            assert cli_main(["train", str(data), "--out", str(out), "--preset", "cpu-quick", "--max-steps", str(steps),
                             "--no-progress", *extra, "train.val_every=0"]) == 0
            times[kind].append(time.perf_counter() - t)
    return times


def hook_cost(run: Path, calls: int = 20000) -> float:
    """Microseconds per ``Viewer.on_step`` call with no browser connected."""
    from types import SimpleNamespace

    from anisdf.viewer.run import open_run

    viewer, _ = open_run(run, port=_free_port())
    trainer = SimpleNamespace(state=SimpleNamespace(step=0))
    t = time.perf_counter()
    for _ in range(calls):
        viewer.on_step(trainer, {"psnr": 30.0, "total": 0.1})
    dt = (time.perf_counter() - t) / calls * 1e6
    viewer.close()
    return dt


def main(argv: list[str] | None = None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--data", type=Path, default=None, help="dataset for the overhead runs (default: the run's)")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--skip-training", action="store_true")
    args = ap.parse_args(argv)

    fp = first_picture(args.run)
    fp["bare_viser_page_connected_s"] = bare_viser_connect()
    print("| first picture (anisdf view, headless Chromium) | seconds / value |\n|---|---|")
    for k, v in fp.items():
        print(f"| {k} | {v:.2f} |" if isinstance(v, float) else f"| {k} | {v} |")
    print(f"\n| Viewer.on_step, no browser | {hook_cost(args.run):.1f} us a call |")
    if args.skip_training:
        return 0
    data = args.data
    if data is None:
        import json

        data = Path(json.loads((args.run / "run.json").read_text())["data"])
    with tempfile.TemporaryDirectory() as work:
        t = training_overhead(data, args.steps, args.repeats, Path(work))
    plain, viewer = statistics.median(t["plain"]), statistics.median(t["viewer"])
    print(f"\n| train {args.steps} steps (cpu-quick, nobody connected) | runs (s) | median (s) |\n|---|---|---|")
    print(f"| plain | {', '.join(f'{x:.1f}' for x in t['plain'])} | {plain:.1f} |")
    print(f"| --viewer | {', '.join(f'{x:.1f}' for x in t['viewer'])} | {viewer:.1f} |")
    print(f"\noverhead of --viewer with no browser: {100 * (viewer / plain - 1):+.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
