"""The export task: its options declared once, its missing extra named before any work, its folder written at once.

These tests need neither the export extra nor a trained run."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from anisdf.cli import main
from anisdf.errors import AnisdfError
from anisdf.export.asset_files import AssetFolder, Baked, write_asset
from anisdf.tasks.export import ExportOptions, export


def _no_work(monkeypatch) -> None:
    """Loading a run or running marching cubes fails the test."""
    import anisdf.export.mesh
    import anisdf.tasks.loading

    def forbidden(*_a, **_k):
        pytest.fail("the export started working before its checks")

    monkeypatch.setattr(anisdf.export.mesh, "extract_mesh", forbidden)
    monkeypatch.setattr(anisdf.tasks.loading, "load_run", forbidden)


def test_export_without_its_extra_says_so_before_any_work(tmp_path, monkeypatch, capsys):
    _no_work(monkeypatch)
    run, out = tmp_path / "run", tmp_path / "asset"
    run.mkdir()
    monkeypatch.setitem(sys.modules, "xatlas", None)  # find_spec answers None for a module set to None
    monkeypatch.setitem(sys.modules, "pygltflib", None)
    assert main(["export", str(run), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("anisdf: error:"), err
    assert "xatlas" in err and "pygltflib" in err and "fast_simplification" not in err, err
    assert "pip install 'anisdf[export]'" in err, err
    assert not out.exists()

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "fast_simplification" else real(name, *a))
    monkeypatch.delitem(sys.modules, "xatlas")
    monkeypatch.delitem(sys.modules, "pygltflib")
    with pytest.raises(AnisdfError, match=r"needs fast_simplification, not installed.*anisdf\[export\]"):
        export(run, out)
    assert not out.exists()


def test_export_options_hold_the_defaults_and_their_checks(tmp_path, monkeypatch):
    o = ExportOptions()
    assert (o.faces, o.texture, o.specular_texture, o.lobes, o.directions, o.resolution, o.supersample,
            o.pixel_filter, o.device, o.progress) == (200_000, 1024, 0, 3, 64, 512, 2, 0.6, None, True)
    fields = {f.name: f for f in dataclasses.fields(ExportOptions)}
    assert all(f.metadata["help"] for f in fields.values()) and not fields["progress"].metadata["cli"]
    assert fields["faces"].metadata["parse"]("300k") == 300_000
    b = ExportOptions(lobes=2, specular_texture=256).bake_options()
    assert (b.faces, b.texture, b.specular_texture, b.spec_size, b.lobes, b.directions) == (200_000, 1024, 256, 256,
                                                                                           2, 64)
    for changes, words in (({"lobes": 9}, "--lobes"), ({"texture": 100, "specular_texture": 64}, "multiple"),
                           ({"supersample": 5}, "--supersample"), ({"pixel_filter": 3.0}, "--pixel-filter"),
                           ({"directions": 5}, "--directions")):
        with pytest.raises(AnisdfError, match=words):
            ExportOptions(**changes).validate()
    _no_work(monkeypatch)
    with pytest.raises(TypeError):
        export(tmp_path, tmp_path / "x", lobs=2)
    with pytest.raises(AnisdfError, match="--lobes"):  # options given as a dataclass, changed by keywords
        export(tmp_path / "run", tmp_path / "x", ExportOptions(lobes=2), lobes=9)
    assert not (tmp_path / "x").exists()


def _baked(k: int) -> Baked:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    return Baked(v, np.tile([0, 0, 1], (3, 1)).astype(np.float32), v[:, :2].copy(), np.array([[0, 1, 2]]),
                 np.full((8, 8, 3), 90, np.uint8), np.full((k, 4, 4, 3), 7, np.uint8),
                 np.full((k, 4, 4, 3), 9, np.uint8), {})


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_asset_folder_replaces_its_files_together_or_not_at_all(tmp_path):
    pytest.importorskip("pygltflib", reason="the glb needs the export extra")
    out = tmp_path / "asset"
    man = {"lobes": 2}
    with AssetFolder(out) as folder:
        sizes = write_asset(folder, _baked(2), np.eye(4), man)
        folder.write("export.json", b"{}\n")
        assert all(p.name.startswith(".") for p in out.iterdir())  # temporary names until the block ends
    before = _files(out)
    assert set(before) == {"model.glb", "index.html", "export.json", "specular_0_lobe.png", "specular_0_rgb.png",
                           "specular_1_lobe.png", "specular_1_rgb.png"}
    assert all(len(before[name]) == size for name, size in sizes.items())

    with pytest.raises(RuntimeError), AssetFolder(out) as folder:  # an export with one lobe fails midway
        write_asset(folder, _baked(1), np.eye(4), {"lobes": 1})
        raise RuntimeError("the bake failed")
    assert _files(out) == before  # no file replaced, none removed, no temporary file left

    with AssetFolder(out) as folder:
        write_asset(folder, _baked(1), np.eye(4), {"lobes": 1})
        folder.write("export.json", b"{}\n")
    after = _files(out)
    assert "specular_1_lobe.png" not in after and "specular_1_rgb.png" not in after  # stale lobes removed
    assert after["specular_0_lobe.png"] == before["specular_0_lobe.png"] and after["index.html"] != before["index.html"]
