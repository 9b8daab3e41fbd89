"""Bad datasets raise DataError naming the offending file, never a traceback from deep inside."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scenes import write_test_scene

from anisdf.data import detect_format, inspect_dataset, load_scene
from anisdf.errors import AnisdfError, DataError


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("good")
    out = {}
    for fmt, kw in [("nerf-synthetic", {}), ("neus", {}), ("instant-ngp", {}), ("llff", {"masks": True}),
                    ("colmap", {"binary": True})]:
        write_test_scene(base / fmt, fmt, **kw)
        out[fmt] = base / fmt
    return out


def copy(scenes: dict[str, Path], fmt: str, tmp_path: Path) -> Path:
    dst = tmp_path / fmt
    shutil.copytree(scenes[fmt], dst)
    return dst


def expect(root: Path, file_name: str, *words: str) -> DataError:
    with pytest.raises(DataError) as info:
        load_scene(root)
    msg = str(info.value)
    assert file_name in msg, msg
    for w in words:
        assert w in msg, msg
    return info.value


def test_empty_and_unknown_folders(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    err = expect(tmp_path / "empty", "empty", "empty folder", "transforms.json", "poses_bounds.npy")
    assert err.path == tmp_path / "empty"
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hello")
    expect(tmp_path / "junk", "junk", "unknown dataset format", "cameras_sphere.npz", "sparse")
    with pytest.raises(DataError, match="does not exist"):
        detect_format(tmp_path / "missing")


def test_truncated_png(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "nerf-synthetic", tmp_path)
    png = root / "train" / "r_2.png"
    png.write_bytes(png.read_bytes()[:60])
    expect(root, "r_2.png", "cannot decode")


def test_missing_image(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "instant-ngp", tmp_path)
    (root / "images" / "r_3.png").unlink()
    expect(root, "r_3.png", "missing")


def test_malformed_json_names_line_and_column(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "nerf-synthetic", tmp_path)
    path = root / "transforms_test.json"
    text = path.read_text().splitlines()
    text[2] = text[2] + ","  # a stray comma on line 3
    path.write_text("\n".join(text))
    expect(root, "transforms_test.json", "malformed JSON", "line")


def test_missing_key(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "nerf-synthetic", tmp_path)
    meta = json.loads((root / "transforms_train.json").read_text())
    del meta["frames"][1]["transform_matrix"]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    expect(root, "transforms_train.json", "transform_matrix", "frame 1")


@pytest.mark.parametrize("bad", ["nan", "scaled"])
def test_bad_pose(scenes: dict[str, Path], tmp_path: Path, bad: str) -> None:
    root = copy(scenes, "instant-ngp", tmp_path)
    meta = json.loads((root / "transforms.json").read_text())
    m = np.array(meta["frames"][2]["transform_matrix"])
    if bad == "nan":
        m[1, 3] = np.nan
    else:
        m[:3, :3] *= 1.5
    meta["frames"][2]["transform_matrix"] = m.tolist()
    (root / "transforms.json").write_text(json.dumps(meta))  # NaN is written as a bare NaN token
    expect(root, "transforms.json", "frame 2", "not finite" if bad == "nan" else "not a rotation")


def test_nan_pose_in_poses_bounds(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "llff", tmp_path)
    arr = np.load(root / "poses_bounds.npy")
    arr[3, 7] = np.nan
    np.save(root / "poses_bounds.npy", arr)
    expect(root, "poses_bounds.npy", "row 3", "not finite")


def test_wrong_shape_poses_bounds(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "llff", tmp_path)
    np.save(root / "poses_bounds.npy", np.load(root / "poses_bounds.npy")[:, :15])
    expect(root, "poses_bounds.npy", "[N,17]")
    np.save(root / "poses_bounds.npy", np.load(scenes["llff"] / "poses_bounds.npy")[:4])
    expect(root, "poses_bounds.npy", "4 poses for 6 images")


def test_mask_count_mismatch(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "llff", tmp_path)
    (root / "masks" / "r_4.png").unlink()
    expect(root, "masks", "5 masks for 6 images")
    root = copy(scenes, "neus", tmp_path)
    (root / "mask" / "000005.png").unlink()
    expect(root, "mask", "5 masks for 6 images")


def test_mask_size_mismatch(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "llff", tmp_path)
    Image.new("L", (8, 6)).save(root / "masks" / "r_1.png")
    expect(root, "r_1.png", "mask is 8x6", "16x12")


def test_image_size_mismatch(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "colmap", tmp_path)
    Image.new("RGB", (20, 12)).save(root / "images" / "r_4.png")
    expect(root, "r_4.png", "20x12", "share one size")


def test_missing_npz_key(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "neus", tmp_path)
    cams = dict(np.load(root / "cameras_sphere.npz"))
    del cams["world_mat_3"]
    np.savez(root / "cameras_sphere.npz", **cams)
    expect(root, "cameras_sphere.npz", "world_mat_3")
    (root / "cameras_sphere.npz").write_bytes(b"not a zip file")
    expect(root, "cameras_sphere.npz", "cannot read")


def test_truncated_colmap_binary(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "colmap", tmp_path)
    path = root / "sparse" / "0" / "images.bin"
    path.write_bytes(path.read_bytes()[:150])
    expect(root, "images.bin", "truncated")


def test_bad_arguments_are_user_errors(scenes: dict[str, Path]) -> None:
    with pytest.raises(AnisdfError, match="downscale"):
        load_scene(scenes["llff"], downscale=0)


def test_inspect_reports_json(scenes: dict[str, Path], tmp_path: Path) -> None:
    report = inspect_dataset(scenes["llff"])
    json.dumps(report)  # JSON-able
    assert report["format"] == "llff" and report["n_images"] == 6
    assert (report["n_train"], report["n_test"]) == (5, 1)
    assert (report["width"], report["height"]) == (16, 12)
    assert report["has_masks"] and not report["has_normals"] and report["scene_radius"] > 0
    assert any("16x12" in w for w in report["warnings"])  # tiny images are flagged
    report = inspect_dataset(scenes["nerf-synthetic"])
    assert report["has_normals"] and report["has_alpha"] and (report["n_train"], report["n_test"]) == (4, 2)
    root = copy(scenes, "neus", tmp_path)
    Image.new("L", (16, 12)).save(root / "mask" / "000002.png")  # an empty mask only warns
    report = inspect_dataset(root)
    assert any("empty" in w for w in report["warnings"])


def _edit_json(path: Path, edit) -> None:
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def _inspect_error(root: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """``anisdf inspect ROOT`` through the CLI: exit code 2 and one line on stderr, which is returned."""
    from anisdf.cli import main

    assert main(["inspect", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize(("key", "value", "words"), [
    ("fl_x", 0.0, ["frame 3", "focal length fx = 0", "positive"]),
    ("fl_y", -120.0, ["frame 3", "focal length fy = -120"]),
    ("w", 0, ["image size w, h = 0, 12", "must be positive"]),  # set for every frame (top level)
    ("cx", None, []),  # None: replaced below by an impossible camera_angle_x instead
])
def test_impossible_camera_in_transforms_json(scenes: dict[str, Path], tmp_path: Path, capsys, key: str,
                                              value: float | None, words: list[str]) -> None:
    root = copy(scenes, "instant-ngp", tmp_path)

    def edit(meta: dict) -> None:
        frame = meta["frames"][3]
        if value is None:
            for k in ("fl_x", "fl_y"):
                meta.pop(k, None)
                frame.pop(k, None)
            frame["camera_angle_x"] = 0.0
        elif key == "w":
            meta[key] = value
        else:
            frame[key] = value

    _edit_json(root / "transforms.json", edit)
    msg = _inspect_error(root, capsys)
    assert "transforms.json" in msg, msg
    for w in words or ["camera_angle_x", "(0, pi)"]:
        assert w in msg, msg


def test_zero_focal_in_nerf_synthetic_and_colmap(scenes: dict[str, Path], tmp_path: Path, capsys) -> None:
    root = copy(scenes, "nerf-synthetic", tmp_path)
    _edit_json(root / "transforms_train.json", lambda meta: meta["frames"][1].update(fl_x=0))
    msg = _inspect_error(root, capsys)
    assert "transforms_train.json" in msg and "frame 1" in msg and "focal length fx = 0" in msg, msg
    root = tmp_path / "colmap-txt"
    write_test_scene(root, "colmap", binary=False)
    cams = root / "sparse" / "0" / "cameras.txt"
    lines = cams.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln and not ln.startswith("#"))
    parts = lines[i].split()
    parts[4] = "0"  # fx
    lines[i] = " ".join(parts)
    cams.write_text("\n".join(lines) + "\n")
    msg = _inspect_error(root, capsys)
    assert "cameras.txt" in msg and f"camera {parts[0]}" in msg and "focal length fx = 0" in msg, msg


def test_llff_bounds_need_near_before_far(scenes: dict[str, Path], tmp_path: Path) -> None:
    root = copy(scenes, "llff", tmp_path)
    arr = np.load(root / "poses_bounds.npy")
    arr[2, 15:] = [5.0, 1.0]
    np.save(root / "poses_bounds.npy", arr)
    expect(root, "poses_bounds.npy", "row 2", "near < far")


def test_impossible_neus_intrinsics(scenes: dict[str, Path], tmp_path: Path) -> None:
    from anisdf.data.dataparsers._common import check_camera

    with pytest.raises(DataError, match="cameras_sphere.npz.*world_mat_0.*focal length fy = 0"):
        check_camera([100.0, 0.0, 8.0, 6.0], None, Path("cameras_sphere.npz"), "world_mat_0")
    with pytest.raises(DataError, match="principal point"):
        check_camera([100.0, 100.0, float("inf"), 6.0], (16, 12), Path("x.json"), "frame 0")
    with pytest.raises(DataError, match="distortion"):
        check_camera([100.0, 100.0, 8.0, 6.0], (16, 12), Path("x.json"), "frame 0", [0.1, float("nan"), 0, 0])
    check_camera([100.0, 100.0, 8.0, 6.0], (16, 12), Path("x.json"), "frame 0", [0.1, 0.0, 0, 0])


@pytest.mark.parametrize(("argv", "option", "words"), [
    (["extract-mesh", "RUN", "--resolution", "0"], "--resolution", "integer >= 2"),
    (["extract-mesh", "RUN", "--resolution", "ten"], "--resolution", "integer >= 2"),
    (["train", "DATA", "--out", "RUN", "--max-steps", "0"], "--max-steps", "integer >= 1"),
    (["train", "DATA", "--out", "RUN", "--max-minutes", "-1"], "--max-minutes", "number >= 0"),
    (["train", "DATA", "--out", "RUN", "--max-minutes", "inf"], "--max-minutes", "finite"),
    (["render", "RUN", "--downscale", "0"], "--downscale", "integer >= 1"),
    (["render", "RUN", "--max-views", "-2"], "--max-views", "integer >= 0"),
    (["eval", "RUN", "--chamfer-points", "0"], "--chamfer-points", "integer >= 1"),
    (["eval", "RUN", "--mesh-resolution", "1"], "--mesh-resolution", "integer >= 2"),
    (["chamfer", "a.ply", "b.ply", "--points", "0"], "--points", "integer >= 1"),
    (["chamfer", "a.ply", "b.ply", "--seed", "-1"], "--seed", "integer >= 0"),
    (["demo", "--minutes", "0"], "--minutes", "number > 0"),
    (["bench", "--minutes", "nan"], "--minutes", "finite number > 0"),
    (["train", "DATA", "--out", "FILE"], "--out", "is an existing file, not a folder"),
    (["demo", "--out", "FILE"], "--out", "is an existing file, not a folder"),
])
def test_impossible_command_arguments(tmp_path: Path, capsys, argv: list[str], option: str, words: str) -> None:
    from anisdf.cli import main

    (tmp_path / "file.txt").write_text("not a folder")
    names = {"RUN": str(tmp_path / "run"), "DATA": str(tmp_path), "FILE": str(tmp_path / "file.txt")}
    with pytest.raises(SystemExit) as info:
        main([names.get(a, a) for a in argv])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"argument {option}: " in err[0] and words in err[0] and f"anisdf {argv[0]}" in err[0], err[0]
    assert not (tmp_path / "run").exists()


def test_unknown_device_is_a_user_error(tmp_path: Path, capsys) -> None:
    from anisdf.cli import main

    assert main(["render", str(tmp_path / "run"), "--device", "gpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device 'gpu'" in err[0], err
