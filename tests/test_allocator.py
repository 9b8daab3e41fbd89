"""glibc malloc thresholds (utils/allocator.py): applied by every command, skipped on request and off glibc."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

import anisdf.cli
from anisdf.utils import allocator

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")

_PROBE = "from anisdf.utils.allocator import tune_malloc; print(tune_malloc(), tune_malloc())"


def _probe(**env: str) -> str:
    out = subprocess.run([sys.executable, "-c", _PROBE], env={**os.environ, **env}, capture_output=True, text=True,
                         check=True)
    return out.stdout.strip()


@glibc
def test_settings_apply_once_per_process() -> None:
    assert _probe(ANISDF_MALLOC="") == "True True"


def test_default_keeps_glibc_settings() -> None:
    assert _probe(ANISDF_MALLOC="default") == "False False"


def test_other_c_libraries_are_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(allocator, "_applied", False)
    monkeypatch.setattr(platform, "libc_ver", lambda: ("musl", "1.2"))
    assert allocator.tune_malloc() is False


def test_every_command_tunes_before_it_runs(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    calls = []
    monkeypatch.setattr(anisdf.cli, "tune_malloc", lambda: calls.append(1) or True)
    assert anisdf.cli.main(["inspect", str(tmp_path / "missing")]) == 2  # a user error, after the tuning
    assert calls == [1]


def test_a_ray_worker_tunes_before_its_task(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    from anisdf.orchestration import cluster

    calls = []
    monkeypatch.setattr(cluster, "tune_malloc", lambda: calls.append("tune") or True)
    result, _ = cluster.attempt(lambda: calls.append("task") or {"ok": 1}, tmp_path / "run", {}, remote=True)
    assert result == {"ok": 1} and calls == ["tune", "task"]
