"""Input of ``anisdf process-data``: a folder of photos or a video, written to ``SCENE/images/``.

Videos are decoded with ffmpeg (imageio-ffmpeg); the frames are split into ``max_frames`` equal groups and the
sharpest frame of each group (largest variance of the Laplacian of its grey levels) is kept, so blurry frames
from camera shake are skipped while the coverage stays even.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import scipy.ndimage
from PIL import Image, ImageOps, UnidentifiedImageError
from tqdm import tqdm

from anisdf.data.dataparsers._common import IMAGE_EXTENSIONS, list_images
from anisdf.errors import AnisdfError, DataError

VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
MIN_IMAGES = 3
DEFAULT_VIDEO_FRAMES = 150
"""Frames kept from a video when ``--max-frames`` is not given (incremental mapping on a CPU stays minutes)."""
ORIENTATION_TAG = 0x0112


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_EXTENSIONS


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (higher = sharper)."""
    grey = rgb[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    return float(scipy.ndimage.laplace(grey).var())


def even_subset(n: int, k: int) -> list[int]:
    """``k`` indices spread evenly over ``range(n)`` (all of them when ``k <= 0`` or ``k >= n``)."""
    if k <= 0 or k >= n:
        return list(range(n))
    return sorted({int(i) for i in np.round(np.linspace(0, n - 1, k))})


def _resize(im: Image.Image, downscale: int) -> Image.Image:
    if downscale <= 1:
        return im
    size = (max(1, round(im.width / downscale)), max(1, round(im.height / downscale)))
    return im.resize(size, Image.Resampling.LANCZOS)


def import_folder(folder: Path, images_dir: Path, max_frames: int = 0, downscale: int = 1,
                  progress: bool = True) -> list[str]:
    """Check every image in ``folder`` (decodes it), then write the kept ones to ``images_dir``.

    Files are copied as they are, or re-encoded when they are downscaled or carry an EXIF rotation (which is
    applied, so COLMAP and anisdf see the same pixels). Returns the written file names, sorted. Raises before
    writing anything when fewer than 3 images are found, any is unreadable, or their sizes differ.
    """
    paths = list_images(folder)
    others = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() not in IMAGE_EXTENSIONS)
    if len(paths) < MIN_IMAGES:
        extra = f" (ignored other files: {', '.join(others[:5])})" if others else ""
        raise DataError(folder, f"{len(paths)} image(s) found, at least {MIN_IMAGES} are needed "
                                f"(extensions {', '.join(IMAGE_EXTENSIONS)}){extra}")
    paths = [paths[i] for i in even_subset(len(paths), max_frames)]
    bad: list[str] = []
    sizes: dict[tuple[int, int], list[str]] = {}
    rotated: set[str] = set()
    for p in tqdm(paths, desc="checking images", unit="img", disable=not progress, leave=False):
        try:
            with Image.open(p) as im:
                im.load()
                orientation = im.getexif().get(ORIENTATION_TAG, 1)
                size = im.size if orientation in (1, 2, 3, 4) else (im.height, im.width)
        except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
            bad.append(f"{p.name} ({str(exc).splitlines()[0][:80]})")
            continue
        if orientation != 1:
            rotated.add(p.name)
        sizes.setdefault(size, []).append(p.name)
    if bad:
        raise DataError(folder, f"{len(bad)} unreadable or corrupt image(s): {'; '.join(bad[:10])}"
                                f"{' ...' if len(bad) > 10 else ''}; remove or replace them and run again")
    if len(sizes) > 1:
        common = max(sizes, key=lambda s: len(sizes[s]))
        odd = [f"{n} ({s[0]}x{s[1]})" for s, names in sizes.items() if s != common for n in names]
        raise DataError(folder, f"images must share one size ({common[0]}x{common[1]} for most); differing: "
                                f"{', '.join(odd[:10])}{' ...' if len(odd) > 10 else ''}")
    images_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for p in tqdm(paths, desc="writing images", unit="img", disable=not progress, leave=False):
        dst = images_dir / p.name
        if downscale <= 1 and p.name not in rotated:
            if p.resolve() != dst.resolve():
                shutil.copyfile(p, dst)
        else:
            with Image.open(p) as im:
                out = _resize(ImageOps.exif_transpose(im), downscale)
                if dst.suffix.lower() in (".jpg", ".jpeg"):
                    out.save(dst, quality=95)
                else:
                    out.save(dst)
        names.append(p.name)
    return names


def _video_frames(video: Path) -> tuple[Iterator[bytes], tuple[int, int], int]:
    """(raw RGB24 frame generator, (W, H), frame count) of ``video`` through ffmpeg."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise AnisdfError("reading a video needs imageio-ffmpeg: pip install 'anisdf[colmap]'") from None
    try:
        n_frames, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
        gen = imageio_ffmpeg.read_frames(str(video))
        meta = next(gen)
    except (RuntimeError, OSError, StopIteration) as exc:
        raise DataError(video, f"cannot read video ({str(exc).strip().splitlines()[-1][:120] if str(exc) else exc})"
                        ) from None
    size = tuple(int(v) for v in meta.get("size", (0, 0)))
    if n_frames <= 0 or min(size) <= 0:
        gen.close()
        raise DataError(video, "the video has no frames")
    return gen, (size[0], size[1]), int(n_frames)


def import_video(video: Path, images_dir: Path, max_frames: int = DEFAULT_VIDEO_FRAMES, downscale: int = 1,
                 progress: bool = True) -> list[str]:
    """Write the sharpest frame of each of ``max_frames`` equal groups of ``video`` frames to
    ``images_dir/frame_00001.png`` ...; returns the names."""
    gen, (w, h), n_frames = _video_frames(video)
    k = n_frames if max_frames <= 0 else min(max_frames, n_frames)
    group_of = np.minimum((np.arange(n_frames) * k) // n_frames, k - 1)
    images_dir.mkdir(parents=True, exist_ok=True)
    names: list[str] = []
    best: tuple[float, np.ndarray] | None = None
    current = 0

    def flush() -> None:
        if best is not None:
            name = f"frame_{len(names) + 1:05d}.png"
            _resize(Image.fromarray(best[1]), downscale).save(images_dir / name)
            names.append(name)

    n_read = 0
    try:
        for raw in tqdm(gen, total=n_frames, desc="reading video", unit="frame", disable=not progress, leave=False):
            frame = np.frombuffer(raw, np.uint8)
            if frame.size != w * h * 3:
                break
            frame = frame.reshape(h, w, 3)
            group = int(group_of[min(n_read, n_frames - 1)])
            if group != current:
                flush()
                best, current = None, group
            score = sharpness(frame[::2, ::2])
            if best is None or score > best[0]:
                best = (score, frame.copy())
            n_read += 1
        flush()
    finally:
        gen.close()
    if n_read == 0:
        raise DataError(video, "no frame could be decoded from the video")
    if len(names) < MIN_IMAGES:
        raise DataError(video, f"only {len(names)} frame(s) in the video; at least {MIN_IMAGES} are needed")
    return names
