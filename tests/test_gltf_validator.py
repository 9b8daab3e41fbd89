"""The glbs anisdf writes, checked by the Khronos glTF Validator (npm ``gltf-validator``, run by
scripts/gltf_validate.mjs): the writers on a small mesh, then the glbs of ``anisdf export`` and ``anisdf export --pbr``.

Skips without Node.js or without the validator: ``make gltf-validator`` installs the version pinned in the Makefile
into .ci/node (``$ANISDF_GLTF_VALIDATOR`` may name another node_modules folder)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pygltflib", reason="the glb writers need the export extra (pip install 'anisdf[export]')")

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "gltf_validate.mjs"
# Information the validator may give on a real export without anything being wrong with the writer: the decimated
# mesh may keep zero-area triangles, and the texture sizes are the user's.
BENIGN = {"ACCESSOR_INDEX_TRIANGLE_DEGENERATE", "IMAGE_NPOT_DIMENSIONS"}


@pytest.fixture(scope="session")
def node() -> str:
    """The node executable, with the validator found (else the tests skip, saying why). Session-scoped and named
    first, so that a test skips before the shared runs it asks for are trained."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node (Node.js) is not installed: the glTF validator cannot run")
    found = subprocess.run([node, str(SCRIPT), "--version"], capture_output=True, text=True, timeout=120)
    if found.returncode != 0:
        pytest.skip(found.stderr.strip() or f"{SCRIPT.name} --version failed ({found.returncode})")
    print(f"gltf-validator {found.stdout.strip()}")
    return node


def validate(node: str, *paths: Path) -> list[dict]:
    """The validator's reports on ``paths`` (all their messages), printed; the script's exit status is checked."""
    done = subprocess.run([node, str(SCRIPT), "--max-messages", "0", *map(str, paths)], capture_output=True,
                          text=True, timeout=300)
    reports = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
    assert len(reports) == len(paths), (done.returncode, done.stderr)
    assert done.returncode == int(any(r["numErrors"] for r in reports)), (done.returncode, done.stderr)
    for r in reports:
        print(f"{Path(r['file']).name}: {r['numErrors']} errors, {r.get('numWarnings')} warnings, "
              f"{r.get('numInfos')} infos, {r.get('numHints')} hints {r.get('failure', '')}")
        for m in r.get("messages", []):
            print(f"  {m['severity']} {m['code']} {m.get('pointer', '')}: {m['message']}")
    return reports


def assert_valid(report: dict, allowed: set[str] = BENIGN) -> None:
    """No errors or warnings, and no information or hints but ``allowed`` ones."""
    assert "failure" not in report, report["failure"]
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    others = [m for m in report["messages"] if m["code"] not in allowed]
    assert not others and not report["truncated"], others


def _small_mesh():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    v = np.asarray(m.vertices, np.float32) + np.float32([0.1, -2.0, 3.0])
    n = np.asarray(m.vertex_normals, np.float32)
    uv = np.random.default_rng(0).random((len(v), 2)).astype(np.float32)
    return v, n, uv, np.asarray(m.faces)


def _png(side: int, value: int) -> bytes:
    from anisdf.export.asset_files import png_bytes

    return png_bytes(np.full((side, side, 3), value, np.uint8))


def test_the_glb_writers_write_glbs_with_nothing_to_report(node, tmp_path):
    """The baked asset's and the PBR asset's glb of a small mesh: not even information or hints."""
    from anisdf.export import baked_format as fmt
    from anisdf.export.asset_files import glb_bytes
    from anisdf.materials.pbr_asset import pbr_glb_bytes

    v, n, uv, f = _small_mesh()
    baked, pbr = tmp_path / "baked.glb", tmp_path / "pbr.glb"
    baked.write_bytes(glb_bytes(v, n, uv, f, _png(16, 128),
                                extras={"anisdf": {"format": fmt.FORMAT, "manifest": fmt.MANIFEST}}))
    pbr.write_bytes(pbr_glb_bytes(v, n, uv, f, _png(16, 200), _png(16, 90)))
    for report in validate(node, baked, pbr):
        assert_valid(report, allowed=set())
        assert report["info"]["totalTriangleCount"] == len(f) and report["info"]["totalVertexCount"] == len(v)


def test_the_validator_reports_a_broken_glb(node, tmp_path):
    """The check can fail: POSITION without its min and max (required by glTF) is an error, the script exits 1."""
    import pygltflib

    from anisdf.export.asset_files import glb_bytes

    v, n, uv, f = _small_mesh()
    gltf = pygltflib.GLTF2.load_from_bytes(glb_bytes(v, n, uv, f, _png(4, 0)))
    gltf.accessors[0].min = gltf.accessors[0].max = None
    broken = tmp_path / "broken.glb"
    broken.write_bytes(b"".join(gltf.save_to_bytes()))
    (report,) = validate(node, broken)
    assert report["numErrors"] >= 1
    assert "MESH_PRIMITIVE_POSITION_ACCESSOR_WITHOUT_BOUNDS" in {m["code"] for m in report["messages"]}


def test_the_baked_export_glb_is_valid(node, exported):
    """``anisdf export``'s model.glb (the shared ``exported`` run of conftest.py)."""
    from anisdf.export import baked_format as fmt

    _, out = exported
    (report,) = validate(node, out / fmt.GLB)
    assert_valid(report)
    manifest = json.loads((out / fmt.MANIFEST).read_text())
    assert report["info"]["totalTriangleCount"] == manifest["faces"]
    assert report["info"]["extensionsUsed"] == ["KHR_materials_unlit"]


def test_the_pbr_export_glb_is_valid(node, fitted_run, tmp_path):
    """``anisdf export --pbr``'s model.glb (the shared ``fitted_run`` of conftest.py)."""
    from anisdf.cli import main
    from anisdf.materials import pbr_asset

    out = tmp_path / "pbr"
    assert main(["export", str(fitted_run), "--pbr", "--out", str(out), "--faces", "2000", "--texture", "64",
                 "--no-progress"]) == 0
    (report,) = validate(node, out / pbr_asset.GLB)
    assert_valid(report)
    manifest = json.loads((out / pbr_asset.MANIFEST).read_text())
    assert report["info"]["totalTriangleCount"] == manifest["faces"]
    assert [r["image"]["width"] for r in report["info"]["resources"] if "image" in r] == [64, 64]
