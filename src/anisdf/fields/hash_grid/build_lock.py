"""One build at a time per extension build folder, and no endless wait on a build that died.

torch's ``cpp_extension.load`` guards a build folder with a bare ``lock`` file (``torch/utils/file_baton.py``)
and waits for it to vanish, without a bound or a word. A build killed mid-way (an out-of-memory kill, a preempted
or retried worker) leaves that file behind, and every later load of the extension would wait for ever.
:func:`build_lock` wraps a build in an OS lock (``fcntl.flock`` on ``anisdf-build.lock`` beside torch's file),
which the kernel releases when its holder dies, and records the holder (``pid N on HOST``) in that file:

* another live process holds the OS lock: wait for its build (bounded, one log line), then load what it built;
* torch's ``lock`` is there while this process holds the OS lock: the build that made it was killed, so the file
  is removed (one warning) and the build runs again;
* where liveness cannot be checked (a file system without ``flock``, a holder on another host sharing the cache),
  torch's ``lock`` is waited for with the same bound; then :class:`BuildBusy` names the file to remove.

``ANISDF_KERNEL_WAIT`` (seconds, default 300) bounds every wait.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

try:
    import fcntl
except ImportError:  # not a POSIX system: liveness comes from the recorded pid alone
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

LOCK_NAME = "anisdf-build.lock"
TORCH_LOCK_NAME = "lock"
WAIT_ENV = "ANISDF_KERNEL_WAIT"
DEFAULT_WAIT_S = 300.0
POLL_S = 0.2


class BuildBusy(RuntimeError):
    """Another build still held the build folder when the wait ran out."""


def wait_seconds() -> float:
    """The longest wait for another build: ``$ANISDF_KERNEL_WAIT`` seconds, default 300."""
    raw = os.environ.get(WAIT_ENV, "").strip()
    if not raw:
        return DEFAULT_WAIT_S
    try:
        value = float(raw)
    except ValueError:
        raise RuntimeError(f"{WAIT_ENV}={raw!r} is not a number of seconds") from None
    return max(0.0, value)


def holder_record() -> str:
    """How this process names itself in the lock file."""
    return f"pid {os.getpid()} on {socket.gethostname()}"


def parse_record(text: str) -> tuple[int | None, str | None]:
    """``(pid, host)`` from a :func:`holder_record` text; ``(None, None)`` for anything else."""
    parts = text.split()
    if len(parts) == 4 and parts[0] == "pid" and parts[1].isdigit() and parts[2] == "on":
        return int(parts[1]), parts[3]
    return None, None


def pid_alive(pid: int) -> bool:
    """Whether a process with this id runs on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def holder_gone(record: str, os_locked: bool) -> bool | None:
    """Whether the last holder of the build folder, named by ``record``, is gone; ``None`` where nobody can tell.

    ``os_locked``: this process holds the OS lock, which every build of this folder holds while it runs and which
    the kernel releases when its holder dies, so a holder on this machine is gone. Without it, the recorded pid
    decides. A holder on another host (a cache shared over the network) cannot be checked from here.
    """
    pid, host = parse_record(record)
    if host is not None and host != socket.gethostname():
        return None
    if os_locked:
        return True
    return None if pid is None else not pid_alive(pid)


def _read(fd: int) -> str:
    return os.pread(fd, 256, 0).decode(errors="replace").strip()


def _write(fd: int, text: str) -> None:
    os.ftruncate(fd, 0)
    os.pwrite(fd, text.encode(), 0)


def _take_os_lock(fd: int, build_dir: Path, deadline: float, wait_s: float) -> bool:
    """Take the OS lock, waiting until ``deadline`` for a live holder; ``False`` where there is no such lock."""
    if fcntl is None:
        return False
    announced = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            pass
        except OSError:  # no flock on this file system (ENOLCK, EOPNOTSUPP)
            return False
        holder = _read(fd) or "another process"
        if not announced:
            log.info("hash grid: %s is building the compiled CPU kernel in %s; waiting up to %.0f s for it",
                     holder, build_dir, wait_s)
            announced = True
        if time.monotonic() >= deadline:
            raise BuildBusy(f"{holder} was still building it in {build_dir} after {wait_s:.0f} s; "
                            f"set {WAIT_ENV}=SECONDS to wait longer")
        time.sleep(POLL_S)


def _clear_torch_lock(path: Path, previous: str, os_locked: bool, deadline: float, wait_s: float) -> None:
    """Remove torch's lock if its build is gone; else wait until ``deadline`` for it to vanish."""
    if not path.exists():
        return
    holder = previous or "an unknown process"
    gone = holder_gone(previous, os_locked)
    if gone:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        log.warning("hash grid: removed the stale build lock %s left by a killed build (%s); building the "
                    "compiled CPU kernel again", path, holder)
        return
    state = "still running" if gone is False else "which this machine cannot check"
    log.info("hash grid: the build lock %s is held by %s, %s; waiting up to %.0f s for it (remove the file if no "
             "build is running)", path, holder, state, wait_s)
    while path.exists():
        if time.monotonic() >= deadline:
            raise BuildBusy(f"the build lock {path} ({holder}) is still there after {wait_s:.0f} s; remove it if "
                            f"no build is running, or set {WAIT_ENV}=SECONDS to wait longer")
        time.sleep(POLL_S)


@contextlib.contextmanager
def build_lock(build_dir: Path, wait_s: float) -> Iterator[None]:
    """Hold ``build_dir`` for one build: wait (at most ``wait_s``) for a live build there, clear a killed one's lock.

    Raises :class:`BuildBusy` when the wait runs out. The OS lock is released on exit (or when this process dies).
    """
    build_dir.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + wait_s
    fd = os.open(build_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        os_locked = _take_os_lock(fd, build_dir, deadline, wait_s)
        _clear_torch_lock(build_dir / TORCH_LOCK_NAME, _read(fd), os_locked, deadline, wait_s)
        _write(fd, holder_record())
        yield
    finally:
        os.close(fd)
