"""``anisdf process-data``: a textured box on a textured floor, ray cast here in numpy from 20 known cameras, is
posed by pycolmap; the poses must agree with the truth after a similarity alignment (Umeyama)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage
from PIL import Image, ImageFilter

from anisdf.cli import main
from anisdf.data.dataparsers import colmap, load_scene, parse_dataset
from anisdf.data.process.export import Poses, bounding_sphere
from anisdf.data.process.inputs import import_video
from anisdf.errors import AnisdfError, DataError

BOX_LO, BOX_HI = np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 1.0])
W, H, F = 160, 120, 140.0


def _texture(rng: np.random.Generator, n: int, sigmas: tuple[float, ...]) -> np.ndarray:
    """Band-pass colour noise: blobs a few pixels wide in the images, which SIFT detects well."""
    out = sum(scipy.ndimage.gaussian_filter(rng.standard_normal((n, n, 3)), (s, s, 0), mode="wrap") * s
              for s in sigmas)
    out = (out - out.mean()) / out.std()
    return 1.0 / (1.0 + np.exp(-2.0 * out))


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    n = tex.shape[0]
    x, y = np.clip(u, 0, 1) * (n - 1), np.clip(v, 0, 1) * (n - 1)
    x0, y0 = np.floor(x).astype(int).clip(0, n - 2), np.floor(y).astype(int).clip(0, n - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = tex[y0, x0] * (1 - fx) + tex[y0, x0 + 1] * fx
    bottom = tex[y0 + 1, x0] * (1 - fx) + tex[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) with world +z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
    return m


def _render(c2w: np.ndarray, textures: list[np.ndarray]) -> np.ndarray:
    """Ray cast the 4x4 floor (z = 0) and the unit box standing on it; pixel centres at i + 0.5."""
    j, i = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    d = np.stack([(i - W / 2) / F, (j - H / 2) / F, np.ones_like(i)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    colour = np.zeros((H, W, 3)) + [0.6, 0.65, 0.7]
    t_floor = -o[2] / d[..., 2]
    p = o + t_floor[..., None] * d
    floor = (t_floor > 0) & (np.abs(p[..., 0]) < 2) & (np.abs(p[..., 1]) < 2)
    colour[floor] = _sample(textures[0], (p[..., 0] + 2) / 4, (p[..., 1] + 2) / 4)[floor]
    t0, t1 = (BOX_LO - o) / d, (BOX_HI - o) / d
    t_near, t_far = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    box = (t_near < t_far) & (t_near > 0) & (~floor | (t_near < t_floor))
    face_axis = np.argmax(np.minimum(t0, t1), -1)
    q = (o + t_near[..., None] * d - BOX_LO) / (BOX_HI - BOX_LO)
    for a in range(3):
        hit = box & (face_axis == a)
        u, v = (k for k in range(3) if k != a)
        colour[hit] = (_sample(textures[1 + a], q[..., u], q[..., v]) * (0.8 + 0.1 * a))[hit]
    return (np.clip(colour, 0, 1) * 255).astype(np.uint8)


def render_views(folder: Path, n: int = 20, seed: int = 0) -> np.ndarray:
    """Write ``view_XX.png`` from ``n`` cameras on a wavy ring around the box; returns their [n,4,4] c2w."""
    rng = np.random.default_rng(seed)
    textures = [_texture(rng, 512, (3, 6))] + [_texture(rng, 128, (2, 4)) for _ in range(3)]
    folder.mkdir(parents=True, exist_ok=True)
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c2w = _look_at(np.array([2.6 * np.cos(a), 2.6 * np.sin(a), 2.2 + 0.3 * np.sin(3 * a)]),
                       np.array([0.0, 0.0, 0.4]))
        Image.fromarray(_render(c2w, textures)).save(folder / f"view_{k:02d}.png")
        poses.append(c2w)
    return np.stack(poses)


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@pytest.fixture(scope="module")
def views(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    folder = tmp_path_factory.mktemp("views") / "photos"
    return folder, render_views(folder)


def test_process_data_registers_and_matches_true_cameras(views: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    import pycolmap

    from anisdf.data.process import process_data
    from anisdf.data.process.sfm import refine_principal_point

    photos, truth = views
    scene = tmp_path / "scene"
    summary = process_data(photos, scene, progress=False)
    assert summary["matcher"] == "exhaustive" and not summary["principal_point_refined"]
    assert summary["n_registered"] == summary["n_images"] == len(truth)
    assert summary["not_registered"] == []
    assert 0.0 < summary["mean_reprojection_error_px"] < 1.0
    assert summary["n_points"] > 200
    for name in ("transforms.json", "cameras.png", "sparse_pc.ply", "process_data.json", "colmap/database.db"):
        assert (scene / name).is_file(), name
    assert len(list((scene / "images").iterdir())) == len(truth)
    assert (scene / summary["colmap_model"] / "images.bin").is_file()

    parsed = parse_dataset(scene)  # the transforms.json anisdf reads, OpenCV c2w in the scene frame
    assert parsed.format == "instant-ngp" and parsed.roi_method == "sparse-points"
    order = [int(p.stem.split("_")[1]) for p in parsed.image_paths]
    sim = pycolmap.estimate_sim3d(parsed.c2w[:, :3, 3], truth[order, :3, 3])  # Umeyama: scene -> truth
    assert sim is not None
    rot = sim.rotation.matrix()
    errors = [rotation_deg(rot @ est[:3, :3], true[:3, :3]) for est, true in zip(parsed.c2w, truth[order],
                                                                                    strict=True)]
    assert max(errors) < 2.0, errors
    aligned = (sim.scale * parsed.c2w[:, :3, 3] @ rot.T) + sim.translation
    spread = np.linalg.norm(truth[:, :3, 3] - truth[:, :3, 3].mean(0), axis=1).mean()
    assert np.median(np.linalg.norm(aligned - truth[order, :3, 3], axis=1)) < 0.01 * spread
    # The cameras' up (-y) is the scene's +z: the truth's world up maps to it.
    assert (rot @ np.array([0.0, 0.0, 1.0]))[2] > 0.99

    # The bounding sphere (ROI) holds the box and leaves the cameras outside.
    loaded = load_scene(scene)
    assert loaded.roi_method == "sparse-points"
    corners = np.array([[x, y, z] for x in (BOX_LO[0], BOX_HI[0]) for y in (BOX_LO[1], BOX_HI[1])
                        for z in (BOX_LO[2], BOX_HI[2])])
    corners_scene = (corners - sim.translation) @ rot / sim.scale
    assert np.all(np.linalg.norm(loaded.to_normalised_frame(corners_scene), axis=1) < 1.0)
    assert float(loaded.cameras.centers.norm(dim=-1).min()) > 1.0
    inspected = json.loads((scene / "process_data.json").read_text())
    assert inspected["sphere_method"] == "sparse-points"

    # the COLMAP parser reads the model process-data wrote (through pycolmap) with the poses transforms.json holds
    model = scene / summary["colmap_model"]
    cams, images, _, _ = colmap.read_model(model)
    assert len(images) == summary["n_registered"] and len(cams) == 1
    rec = pycolmap.Reconstruction(model)

    # --refine-principal-point: here (true point at the centre) the refined copy is accepted, keeps the point within
    # 10% of the centre and the error no worse, and leaves the model it was given alone. (Its poses are not checked:
    # the point drifts 1-5 px on this ring, tilting the views by up to ~2 deg; hence the option is opt-in.)
    params = np.array(rec.cameras[next(iter(rec.cameras))].params)
    refined = refine_principal_point(rec)
    assert refined is not None and refined.num_reg_images() == rec.num_reg_images()
    cam = next(iter(refined.cameras.values()))
    assert abs(cam.principal_point_x - W / 2) < 0.1 * W and abs(cam.principal_point_y - H / 2) < 0.1 * H
    assert refined.compute_mean_reprojection_error() <= 1.05 * rec.compute_mean_reprojection_error()
    np.testing.assert_array_equal(rec.cameras[next(iter(rec.cameras))].params, params)


def test_video_input_end_to_end(views: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    import pycolmap
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="reading videos needs imageio-ffmpeg")
    from anisdf.data.process import process_data

    photos, truth = views
    video = tmp_path / "walk.mp4"
    writer = imageio_ffmpeg.write_frames(str(video), (W, H), fps=10, quality=10, macro_block_size=8)
    writer.send(None)
    for p in sorted(photos.iterdir()):
        writer.send(np.ascontiguousarray(np.asarray(Image.open(p))))
    writer.close()
    summary = process_data(video, tmp_path / "scene", progress=False)
    assert summary["kind"] == "video" and summary["matcher"] == "sequential"
    assert summary["n_registered"] == summary["n_images"] == len(truth)
    parsed = parse_dataset(tmp_path / "scene")
    order = [int(p.stem.split("_")[1]) - 1 for p in parsed.image_paths]  # frame_00001 is view 0
    sim = pycolmap.estimate_sim3d(parsed.c2w[:, :3, 3], truth[order, :3, 3])
    errors = [rotation_deg(sim.rotation.matrix() @ e[:3, :3], t[:3, :3]) for e, t in zip(parsed.c2w, truth[order],
                                                                                          strict=True)]
    assert max(errors) < 2.0, errors


def test_unrelated_images_fail_with_advice_and_keep_files(tmp_path: Path) -> None:
    from anisdf.data.process import process_data

    rng = np.random.default_rng(1)
    photos = tmp_path / "noise"
    photos.mkdir()
    for k in range(4):  # independent noise: features everywhere, no geometry between any two
        noise = scipy.ndimage.gaussian_filter(rng.random((120, 160, 3)), (1.5, 1.5, 0))
        Image.fromarray((255 * (noise - noise.min()) / np.ptp(noise)).astype(np.uint8)).save(photos / f"{k}.png")
    with pytest.raises(AnisdfError, match="more overlap") as err:
        process_data(photos, tmp_path / "scene", progress=False)
    assert "--matcher" in str(err.value)
    assert len(list((tmp_path / "scene" / "images").iterdir())) == 4  # what was written stays
    assert (tmp_path / "scene" / "colmap" / "database.db").is_file()


def _copy_views(views: tuple[Path, np.ndarray], dst: Path, n: int) -> Path:
    dst.mkdir()
    for p in sorted(views[0].iterdir())[:n]:
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


def test_too_few_images(views: tuple[Path, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    photos = _copy_views(views, tmp_path / "two", 2)
    assert main(["process-data", str(photos), "--out", str(tmp_path / "scene"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "2 image(s) found, at least 3 are needed" in err and str(photos) in err
    assert not (tmp_path / "scene").exists()


def test_corrupt_image_is_named(views: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    from anisdf.data.process import process_data

    photos = _copy_views(views, tmp_path / "photos", 4)
    (photos / "view_02.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really a png" * 10)
    (photos / "broken.jpg").write_bytes(b"")
    with pytest.raises(DataError, match="2 unreadable or corrupt image") as err:
        process_data(photos, tmp_path / "scene", progress=False)
    assert "view_02.png" in str(err.value) and "broken.jpg" in str(err.value)
    assert not (tmp_path / "scene").exists()


def test_existing_scene_is_not_overwritten(views: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    from anisdf.data.process import process_data

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "transforms.json").write_text("{}")
    with pytest.raises(DataError, match="already exists"):
        process_data(views[0], scene, progress=False)
    assert (scene / "transforms.json").read_text() == "{}"


def test_video_keeps_the_sharpest_frame_of_each_group(views: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="reading videos needs imageio-ffmpeg")
    frames = [np.asarray(Image.open(p)) for p in sorted(views[0].iterdir())[:6]]
    video = tmp_path / "clip.mp4"
    writer = imageio_ffmpeg.write_frames(str(video), (W, H), fps=10, quality=9, macro_block_size=8)
    writer.send(None)
    sharp_at = (1, 3, 5)  # three groups of two frames: (blurred, sharp) each
    sent = []
    for k, frame in enumerate(frames):
        im = Image.fromarray(frame)
        if k not in sharp_at:
            im = im.filter(ImageFilter.GaussianBlur(3))
        sent.append(np.asarray(im, np.float32))
        writer.send(np.ascontiguousarray(np.asarray(im)))
    writer.close()
    out = tmp_path / "frames"
    names = import_video(video, out, max_frames=3, progress=False)
    assert names == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    for name, k in zip(names, sharp_at, strict=True):  # nearest of the frames sent: the sharp one of its group
        got = np.asarray(Image.open(out / name), np.float32)
        assert int(np.argmin([np.abs(got - f).mean() for f in sent])) == k


def test_video_without_frames(tmp_path: Path) -> None:
    pytest.importorskip("imageio_ffmpeg", reason="reading videos needs imageio-ffmpeg")
    video = tmp_path / "empty.mp4"
    video.write_bytes(b"\x00" * 64)
    with pytest.raises(DataError, match="video") as err:
        import_video(video, tmp_path / "frames", progress=False)
    assert str(video) in str(err.value)


def test_bounding_sphere_ignores_outliers_and_uses_the_look_at_point() -> None:
    rng = np.random.default_rng(0)
    centre = np.array([0.3, -0.2, 0.1])
    ball = rng.normal(size=(2000, 3))
    ball = centre + 0.5 * ball / np.linalg.norm(ball, axis=1, keepdims=True) * rng.random((2000, 1)) ** (1 / 3)
    far = centre + rng.normal(size=(40, 3)) * 30.0  # background points and mismatches
    points = np.vstack([ball, far])
    c2w = []
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        eye = centre + 4.0 * np.array([np.cos(a), np.sin(a), 0.5])
        z = (centre - eye) / np.linalg.norm(centre - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
        c2w.append(m)
    poses = Poses(names=[str(i) for i in range(12)], image_ids=list(range(12)), c2w=np.stack(c2w),
                  intrinsics=np.array([100.0, 100.0, 80.0, 60.0]), distortion=np.zeros(4), width=160, height=120,
                  model="PINHOLE", points=points, colors=np.zeros((len(points), 3), np.uint8),
                  errors=np.full(len(points), 0.5), track_lengths=np.full(len(points), 4))
    sphere = bounding_sphere(poses)
    assert sphere.method == "sparse-points"
    assert np.linalg.norm(sphere.center - centre) < 0.05
    assert 0.5 <= sphere.radius < 0.65


def test_bounding_sphere_in_transforms_json_is_validated(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "a.png")
    meta = {"fl_x": 10.0, "w": 8, "h": 8, "bounding_sphere": {"center": [0, 0], "radius": 1.0},
            "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="'center' must be a list of 3 numbers"):
        parse_dataset(tmp_path)
    meta["bounding_sphere"] = {"center": [1, 2, 3], "radius": 2.5, "method": "sparse-points"}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    parsed = parse_dataset(tmp_path)
    assert parsed.roi_method == "sparse-points"
    np.testing.assert_allclose(parsed.to_world, [[2.5, 0, 0, 1], [0, 2.5, 0, 2], [0, 0, 2.5, 3], [0, 0, 0, 1]])


@pytest.mark.parametrize("kwargs, message", [({"matcher": "vocab"}, "vocabulary tree"),
                                             ({"camera_model": "pinhole_ish"}, "--camera-model 'pinhole_ish'")])
def test_bad_options_fail_before_writing(views: tuple[Path, np.ndarray], tmp_path: Path, kwargs: dict,
                                         message: str) -> None:
    from anisdf.data.process import process_data

    with pytest.raises(AnisdfError, match=message):
        process_data(views[0], tmp_path / "scene", progress=False, **kwargs)
    assert not (tmp_path / "scene").exists()
