"""The compiled CPU kernel's build never hangs without a word: a killed build's lock is cleared, a live build is
waited for with a bound and a message, and builds for other sources, torch versions or Pythons never share a name.

Every test uses a private extension cache (``TORCH_EXTENSIONS_DIR`` under ``tmp_path``); only the end-to-end test
starts real builds, with stand-in compilers (one that never finishes, one that fails at once), so no test compiles
the kernel.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch

from anisdf.fields.hash_grid import build_lock, cpu_kernel
from anisdf.fields.hash_grid import dispatch as hef

FLAGS = ["-O3", "-fopenmp"]


def test_builds_of_other_sources_torch_versions_or_pythons_have_other_names() -> None:
    base = dict(source=b"kernel v1", flags=FLAGS, tag="avx2", torch_version="2.13.0+cpu abc", abi="cpython-311-x86_64")
    name = cpu_kernel.extension_name(**base)
    assert name == cpu_kernel.extension_name(**base) and name.startswith("anisdf_hashgrid_cpu_avx2_")
    others = [dict(base, source=b"kernel v2"), dict(base, torch_version="2.12.0+cpu def"),
              dict(base, abi="cpython-312-x86_64"), dict(base, flags=[*FLAGS, "-mavx2"])]
    names = {cpu_kernel.extension_name(**o) for o in others}
    assert len(names) == len(others) and name not in names
    assert torch.__version__ in cpu_kernel.torch_identity() and f"{sys.version_info.major}{sys.version_info.minor}" in \
        cpu_kernel.python_abi()


@pytest.mark.parametrize(("cpu", "tag"), [(set(), "generic"), ({"avx2", "fma"}, "avx2"),
                                        ({"avx2", "fma", "avx512f"}, "avx2"),
                                        ({"avx2", "fma", *cpu_kernel.AVX512}, "avx512")])
def test_the_build_flavour_follows_the_cpu(monkeypatch, cpu: set[str], tag: str) -> None:
    """AVX2/FMA where the CPU has both, AVX-512 on top only with every subset the build is compiled for."""
    monkeypatch.setattr(cpu_kernel, "_cpu_flags", lambda: cpu)
    flags, got = cpu_kernel._compile_flags()
    assert got == tag
    assert ("-mavx2" in flags) == (tag != "generic") and ("-mavx512f" in flags) == (tag == "avx512")


def test_the_build_folder_is_under_the_chosen_cache(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("ANISDF_KERNEL_DIR", raising=False)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    assert cpu_kernel.build_directory("n") == tmp_path / "ext" / "n"
    monkeypatch.setenv("ANISDF_KERNEL_DIR", str(tmp_path / "mine"))
    assert cpu_kernel.build_directory("n") == tmp_path / "mine" / "n"


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_whether_the_holder_is_gone() -> None:
    here = socket.gethostname()
    dead = f"pid {_dead_pid()} on {here}"
    alive = f"pid {os.getpid()} on {here}"
    assert build_lock.holder_gone(alive, os_locked=True) is True  # the OS lock is free: no local build runs
    assert build_lock.holder_gone("", os_locked=True) is True
    assert build_lock.holder_gone(f"pid 1 on not-{here}", os_locked=True) is None  # another host: cannot tell
    assert build_lock.holder_gone(dead, os_locked=False) is True
    assert build_lock.holder_gone(alive, os_locked=False) is False
    assert build_lock.holder_gone("garbage", os_locked=False) is None
    assert build_lock.parse_record(build_lock.holder_record()) == (os.getpid(), here)


@pytest.fixture()
def fake_build(tmp_path, monkeypatch) -> Iterator[dict]:
    """A fresh per-process kernel state in a private cache, ``_load`` replaced by a stand-in that records its calls."""
    monkeypatch.delenv("ANISDF_NO_KERNEL", raising=False)
    monkeypatch.delenv("ANISDF_KERNEL_DIR", raising=False)
    monkeypatch.delenv("ANISDF_KERNEL_WAIT", raising=False)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    monkeypatch.setenv("CXX", sys.executable)  # any executable: the stand-in compiles nothing
    monkeypatch.setattr(cpu_kernel, "_state", {"module": None, "error": None, "build_s": None, "name": None,
                                               "flags": None})
    flags, tag = cpu_kernel._compile_flags()
    build_dir = cpu_kernel.build_directory(cpu_kernel.extension_name(cpu_kernel.source_bytes(), flags, tag))
    build_dir.mkdir(parents=True)
    calls: list[bool] = []
    module = ModuleType("fake_kernel")

    def load(name: str, flags: list[str], where: Path) -> ModuleType:
        assert where == build_dir
        calls.append((where / build_lock.TORCH_LOCK_NAME).exists())
        return module

    monkeypatch.setattr(cpu_kernel, "_load", load)
    yield {"dir": build_dir, "torch_lock": build_dir / build_lock.TORCH_LOCK_NAME, "calls": calls, "module": module}


def _hold_os_lock(build_dir: Path, record: str) -> int:
    fd = os.open(build_dir / build_lock.LOCK_NAME, os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    os.write(fd, record.encode())
    return fd


def test_a_killed_builds_lock_is_removed_and_the_build_runs(fake_build, caplog) -> None:
    fake_build["torch_lock"].touch()
    (fake_build["dir"] / build_lock.LOCK_NAME).write_text(f"pid {_dead_pid()} on {socket.gethostname()}")
    with caplog.at_level(logging.INFO, logger="anisdf"):
        assert cpu_kernel.kernel_module() is fake_build["module"]
    assert fake_build["calls"] == [False] and not fake_build["torch_lock"].exists()
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "stale build lock" in warnings[0] and "\n" not in warnings[0]
    assert build_lock.parse_record((fake_build["dir"] / build_lock.LOCK_NAME).read_text())[0] == os.getpid()


def test_a_live_build_is_waited_for_then_loaded(fake_build, monkeypatch, caplog) -> None:
    monkeypatch.setenv("ANISDF_KERNEL_WAIT", "60")
    fd = _hold_os_lock(fake_build["dir"], f"pid 4242 on {socket.gethostname()}")
    fake_build["torch_lock"].touch()

    def finish() -> None:  # the other build ends as torch's does: its lock file goes, then its OS lock
        time.sleep(0.5)
        fake_build["torch_lock"].unlink()
        os.close(fd)

    thread = threading.Thread(target=finish)
    t0 = time.monotonic()
    thread.start()
    with caplog.at_level(logging.INFO, logger="anisdf"):
        assert cpu_kernel.kernel_module() is fake_build["module"]
    thread.join()
    assert time.monotonic() - t0 >= 0.4 and fake_build["calls"] == [False]
    messages = [r.getMessage() for r in caplog.records]
    assert any("pid 4242 on" in m and "waiting up to 60 s" in m for m in messages)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_build_that_outlasts_the_wait_falls_back_with_a_message(fake_build, monkeypatch, caplog) -> None:
    monkeypatch.setenv("ANISDF_KERNEL_WAIT", "0.3")
    fd = _hold_os_lock(fake_build["dir"], f"pid 4242 on {socket.gethostname()}")
    try:
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="anisdf"):
            assert hef.load_fast_encoder() is None
            assert hef.load_fast_encoder() is None  # decided once per process
        assert time.monotonic() - t0 < 10.0
    finally:
        os.close(fd)
    assert fake_build["calls"] == []
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "pid 4242 on" in warnings[0] and "ANISDF_KERNEL_WAIT" in warnings[0]
    assert "falling back to the PyTorch reference" in warnings[0]


def test_without_os_locks_the_recorded_pid_decides(fake_build, monkeypatch, caplog) -> None:
    monkeypatch.setattr(build_lock, "fcntl", None)
    monkeypatch.setenv("ANISDF_KERNEL_WAIT", "0.3")
    record = fake_build["dir"] / build_lock.LOCK_NAME
    fake_build["torch_lock"].touch()
    record.write_text(f"pid {os.getpid()} on {socket.gethostname()}")  # alive: waited for, then given up
    with caplog.at_level(logging.WARNING, logger="anisdf"):
        assert cpu_kernel.kernel_module() is None
    assert fake_build["torch_lock"].exists() and fake_build["calls"] == []
    assert "remove it if no build is running" in caplog.records[-1].getMessage()
    monkeypatch.setattr(cpu_kernel, "_state", {"module": None, "error": None, "build_s": None, "name": None,
                                               "flags": None})
    record.write_text(f"pid {_dead_pid()} on {socket.gethostname()}")  # gone: cleared
    assert cpu_kernel.kernel_module() is fake_build["module"] and fake_build["calls"] == [False]


_LOAD = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
from anisdf.fields.hash_grid import cpu_kernel
print(cpu_kernel.kernel_module() is not None, flush=True)
"""


def _stand_in_compiler(path: Path, body: str) -> str:
    path.write_text(f"#!/bin/sh\n{body}\n")
    path.chmod(0o755)
    return str(path)


@pytest.mark.skipif(shutil.which("ninja") is None, reason="torch's extension builds need ninja")
def test_a_killed_build_does_not_hang_the_next_load(tmp_path, monkeypatch) -> None:
    """A build SIGKILLed mid-compile (its compiler left running, as after an out-of-memory kill of Python) leaves
    torch's lock behind; the next process clears it and goes on within a bounded time, under ``timeout``."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    env = {k: v for k, v in os.environ.items() if k not in ("ANISDF_NO_KERNEL", "ANISDF_KERNEL_DIR")}
    env.update(TORCH_DONT_CHECK_COMPILER_ABI="1", ANISDF_KERNEL_WAIT="60",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}")
    flags, tag = cpu_kernel._compile_flags()
    build_dir = tmp_path / "ext" / cpu_kernel.extension_name(cpu_kernel.source_bytes(), flags, tag)
    torch_lock = build_dir / build_lock.TORCH_LOCK_NAME
    slow = _stand_in_compiler(tmp_path / "slow-c++", "exec sleep 300")
    first = subprocess.Popen([sys.executable, "-c", _LOAD], env={**env, "CXX": slow}, start_new_session=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not torch_lock.exists():
            assert first.poll() is None, f"the first build ended before compiling: {first.communicate()[1]}"
            assert time.monotonic() < deadline, "the first build never took torch's lock"
            time.sleep(0.1)
        first.send_signal(signal.SIGKILL)
        first.communicate()
        assert torch_lock.exists()  # stale now: its holder is gone
        failing = _stand_in_compiler(tmp_path / "failing-c++", "exit 1")
        prefix = ["timeout", "-s", "KILL", "120"] if shutil.which("timeout") else []
        t0 = time.monotonic()
        second = subprocess.run([*prefix, sys.executable, "-c", _LOAD], env={**env, "CXX": failing},
                                capture_output=True, text=True, timeout=180)
        assert second.returncode not in (124, 137, -9), f"the next load hung: {second.stderr[-2000:]}"
        assert second.returncode == 0, second.stderr[-2000:]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(first.pid, signal.SIGKILL)  # the orphaned compiler of the killed build
    assert second.stdout.strip() == "False"  # the stand-in compiler fails: the reference encoding is used
    assert "removed the stale build lock" in second.stderr and str(torch_lock) in second.stderr
    assert "falling back to the PyTorch reference encoding" in second.stderr
    assert not torch_lock.exists() and time.monotonic() - t0 < 120
