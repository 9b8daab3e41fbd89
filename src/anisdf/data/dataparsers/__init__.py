"""Dataset parsers and format auto-detection.

``load_scene(path)`` detects the format from the files in the folder, parses the cameras, decodes the
images and returns a normalised :class:`~anisdf.data.scene.Scene`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from anisdf.data.dataparsers import blender, colmap, instant_ngp, llff, neus
from anisdf.data.dataparsers._common import ParsedScene, image_size
from anisdf.data.loader import build_scene
from anisdf.data.scene import Scene
from anisdf.errors import DataError

PARSERS: dict[str, Callable[[Path], ParsedScene]] = {
    "nerf-synthetic": blender.parse,
    "neus": neus.parse,
    "instant-ngp": instant_ngp.parse,
    "llff": llff.parse,
    "colmap": colmap.parse,
}

LOOKED_FOR = (
    "transforms_train.json (NeRF-synthetic), cameras_sphere.npz or cameras.npz (NeuS/DTU), "
    "transforms.json (instant-ngp/nerfstudio), poses_bounds.npy (LLFF), "
    "sparse/0/ or sparse/ with cameras+images .bin/.txt (COLMAP)"
)


def detect_format(path: str | Path) -> str:
    """The dataset format of folder ``path``: one of :data:`anisdf.data.scene.FORMATS`."""
    root = Path(path)
    if not root.exists():
        raise DataError(root, "dataset folder does not exist")
    if not root.is_dir():
        raise DataError(root, "expected a dataset folder, got a file")
    if (root / "transforms_train.json").is_file():
        return "nerf-synthetic"
    if neus.find_npz(root) is not None:
        return "neus"
    if (root / "transforms.json").is_file():
        return "instant-ngp"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    if colmap.find_model(root) is not None:
        return "colmap"
    empty = not any(root.iterdir())
    raise DataError(root, f"{'empty folder' if empty else 'unknown dataset format'}; looked for {LOOKED_FOR}")


def parse_dataset(path: str | Path) -> ParsedScene:
    """Cameras, splits and file lists of a dataset, without decoding images."""
    root = Path(path)
    return PARSERS[detect_format(root)](root)


def load_scene(path: str | Path, downscale: float = 1.0, max_images: int = 0, images_dir: str = "",
               split: str | None = None, to_world: np.ndarray | None = None, roi_center: tuple[float, ...] = (),
               roi_radius: float = 0.0, min_size: int = 0, alpha: str = "auto") -> Scene:
    """Load the dataset in folder ``path`` (format auto-detected) as a normalised :class:`Scene`.

    ``downscale`` divides the image size (antialiased resize; intrinsics scaled to match);
    ``max_images`` > 0 keeps at most that many training images, evenly spread over the train split;
    ``images_dir`` reads the same file names from another sub-folder (Mip-NeRF 360's ``images_4``), the intrinsics
    following the size found on disk. ``to_world`` imposes a known normalisation (a trained run's, so that a scene
    reloaded at another resolution lands in the frame the model was trained in) instead of finding the region of
    interest; ``split`` then keeps only that split's views (the others are not decoded). ``roi_center`` (x, y, z)
    and ``roi_radius`` (> 0) replace the automatic region of interest's centre and radius (the dataset's frame and
    units; ``data.roi_center`` / ``data.roi_radius``); a sphere that holds a camera or that no camera sees is an
    error. ``min_size`` > 0 lowers ``downscale`` so that the images' longer side keeps at least that many pixels
    (``data.min_size``; :attr:`Scene.downscale` is the factor applied). ``alpha``: how RGBA images hold colour,
    ``auto`` (told from the images), ``straight`` or ``premultiplied`` (in linear light; read as straight colour;
    ``data.alpha``, :mod:`anisdf.data.alpha`).
    """
    parsed = parse_dataset(path)
    if images_dir:
        parsed.image_paths = [_other_folder(p, Path(path) / images_dir) for p in parsed.image_paths]
    if to_world is not None:
        parsed.to_world = np.asarray(to_world, dtype=np.float64)
        roi_center, roi_radius = (), 0.0  # the run's normalisation already holds its region of interest
    if split is not None:
        if to_world is None:
            raise ValueError("load_scene: split needs to_world (the normalisation cannot be found from one split)")
        parsed = _only_split(parsed, split)
    return build_scene(parsed, downscale=downscale, max_images=max_images, roi_center=tuple(roi_center),
                       roi_radius=float(roi_radius), min_size=min_size, alpha_mode=alpha)


def _only_split(parsed: ParsedScene, split: str) -> ParsedScene:
    """``parsed`` reduced to the views of ``split`` (renumbered; an empty train split when ``split`` is another)."""
    keep = parsed.splits.get(split) or []
    if not keep:
        raise DataError(parsed.root, f"split '{split}' is empty; the dataset has "
                        f"{', '.join(k for k, v in parsed.splits.items() if v)}")
    new = {old: i for i, old in enumerate(keep)}
    return replace(
        parsed,
        image_paths=[parsed.image_paths[i] for i in keep],
        c2w=parsed.c2w[keep],
        intrinsics=parsed.intrinsics[keep],
        splits={"train": [], split: list(range(len(keep)))},
        distortion=None if parsed.distortion is None else parsed.distortion[keep],
        mask_paths=None if parsed.mask_paths is None else [parsed.mask_paths[i] for i in keep],
        normal_paths={new[i]: p for i, p in parsed.normal_paths.items() if i in new},
    )


def image_size_of(path: str | Path, images_dir: str = "") -> tuple[int, int]:
    """``(W, H)`` of the dataset's images as :func:`load_scene` reads them (from ``images_dir`` when given)."""
    image = parse_dataset(path).image_paths[0]
    return image_size(_other_folder(image, Path(path) / images_dir) if images_dir else image)


def _other_folder(image: Path, folder: Path) -> Path:
    if not folder.is_dir():
        raise DataError(folder, "image folder (data.images_dir) does not exist")
    for cand in (folder / image.name, *(folder / (image.stem + e) for e in (".png", ".jpg", ".JPG", ".jpeg"))):
        if cand.is_file():
            return cand
    raise DataError(folder / image.name, f"image missing (data.images_dir has no counterpart of {image.name})")


__all__ = ["PARSERS", "ParsedScene", "detect_format", "image_size_of", "load_scene", "parse_dataset"]
