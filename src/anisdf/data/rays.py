"""Ray batches for training and evaluation.

For objects (RGBA images, or opaque photos with object masks) the target colour is the straight RGB
composited on a background colour, ``rgb * a + bg * (1 - a)``, and the model renders on the same background
(as the authors' release: random colour while training, white at test).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from anisdf.data.scene import Scene
from anisdf.errors import AnisdfError, DataError
from anisdf.utils.images import composite

BACKGROUNDS = ("auto", "white", "black", "random")


@dataclass
class RayBatch:
    origins: Tensor
    directions: Tensor
    """[B,3] ray origins and unit directions in the normalised frame."""
    rgb: Tensor
    """[B,3] float target colour, already composited on ``background`` for objects (alpha or masks)."""
    background: Tensor
    """[B,3] background colour used (zeros for opaque scenes)."""
    mask: Tensor | None
    """[B] float 0..1 object coverage (mask files, else alpha) when known."""
    cam_idx: Tensor
    """[B] long index of the image in the scene (``scene.image_paths`` / ``scene.cameras``)."""
    pixels: Tensor
    """[B,2] float (px, py) pixel coordinates at the scene's loaded resolution (centres at i + 0.5)."""

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def to(self, device: torch.device | str) -> RayBatch:
        return replace(
            self,
            origins=self.origins.to(device),
            directions=self.directions.to(device),
            rgb=self.rgb.to(device),
            background=self.background.to(device),
            mask=None if self.mask is None else self.mask.to(device),
            cam_idx=self.cam_idx.to(device),
            pixels=self.pixels.to(device),
        )

    def __getitem__(self, s: slice | Tensor) -> RayBatch:
        """A sub-batch (e.g. ``batch[i:i + chunk]``)."""
        return RayBatch(
            origins=self.origins[s],
            directions=self.directions[s],
            rgb=self.rgb[s],
            background=self.background[s],
            mask=None if self.mask is None else self.mask[s],
            cam_idx=self.cam_idx[s],
            pixels=self.pixels[s],
        )


def _downscale_uint8(
    images: Tensor, alpha: Tensor | None, size: tuple[int, int]
) -> tuple[Tensor, Tensor | None]:
    """Area-average [M,H,W,3] uint8 images (premultiplied by alpha when given) to ``size`` = (H', W')."""
    out_rgb, out_a = [], []
    for k in range(images.shape[0]):
        rgb = images[k].permute(2, 0, 1).float()[None]
        if alpha is None:
            out_rgb.append(F.interpolate(rgb, size=size, mode="area")[0])
            continue
        a = alpha[k].float()[None, None]
        small = F.interpolate(torch.cat([rgb * a / 255.0, a], dim=1), size=size, mode="area")[0]
        a2 = small[3:4]
        straight = torch.where(a2 > 0, small[:3] * 255.0 / a2.clamp_min(1e-6), torch.zeros_like(small[:3]))
        out_rgb.append(straight)
        out_a.append(a2[0])
    rgb_u8 = torch.stack(out_rgb).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()
    a_u8 = None if alpha is None else torch.stack(out_a).round().clamp(0, 255).to(torch.uint8)
    return rgb_u8, a_u8


def _area_uint8(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Area-average [M,H,W] uint8 maps to ``size`` = (H', W')."""
    small = F.interpolate(x.float()[:, None], size=size, mode="area")[:, 0]
    return small.round().clamp(0, 255).to(torch.uint8)


def eval_background(scene: Scene) -> str:
    """Background for evaluation and pictures: white behind objects (alpha or masks); photos without masks are
    compared as photographed (the model's learned environment colour fills them)."""
    return "white" if scene.background == "rgba" or scene.masks is not None else "auto"


class RayDataset:
    """Pixels of one split of a :class:`Scene` as rays, with images kept on ``device`` as uint8.

    ``background``: ``auto`` gives objects (RGBA images, or opaque photos with object masks, which then
    play the alpha channel's part) a random colour per ray when ``split == "train"`` and white otherwise,
    and leaves opaque photos without masks as photographed. ``white`` / ``black`` / ``random`` force that
    colour and need alpha or masks.
    ``split`` is a key of ``scene.splits`` or ``"all"``. ``downscale`` (int) reduces the image grid
    (area average), e.g. for fast evaluation.
    """

    def __init__(
        self,
        scene: Scene,
        split: str,
        device: torch.device | str = "cpu",
        background: str = "auto",
        downscale: int = 1,
    ) -> None:
        if background not in BACKGROUNDS:
            raise AnisdfError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")
        if split == "all":
            indices = list(range(scene.n_images))
        elif split in scene.splits:
            indices = list(scene.splits[split])
        else:
            raise AnisdfError(f"unknown split {split!r}; the scene has {', '.join(scene.splits)} (and 'all')")
        if not indices:
            raise DataError(scene.root, f"the {split} split has no images")
        if int(downscale) != downscale or downscale < 1:
            raise AnisdfError(f"RayDataset downscale must be a positive integer, got {downscale}")
        self.scene = scene
        self.split = split
        self.device = torch.device(device)
        self.indices = torch.tensor(indices, dtype=torch.long)
        self._indices_dev = self.indices.to(self.device)
        self.downscale = int(downscale)

        # Which channel composites the target on a background colour: alpha, else the object masks.
        composite = scene.alpha if scene.background == "rgba" else scene.masks
        if background == "auto":
            self.mode = ("random" if split == "train" else "white") if composite is not None else "none"
        else:
            if composite is None:
                raise DataError(scene.root, f"background {background!r} needs RGBA images or object masks")
            self.mode = background
        coverage = scene.coverage()

        idx = self.indices
        images = scene.images[idx]
        comp = None if composite is None else composite[idx]
        cov = None if coverage is None else coverage[idx]
        h2, w2 = scene.cameras.image_size(self.downscale)
        if (h2, w2) != (scene.height, scene.width):
            images, comp = _downscale_uint8(images, comp, (h2, w2))
            if cov is not None:
                cov = comp if coverage is composite else _area_uint8(cov, (h2, w2))
        self.height, self.width = h2, w2
        self.images = images.to(self.device)
        self.composite = None if comp is None else comp.to(self.device)
        self.coverage = None if cov is None else cov.to(self.device)
        self.cameras = scene.cameras.to(self.device)
        self.sx = scene.width / w2
        self.sy = scene.height / h2

    def __len__(self) -> int:
        return int(self.indices.numel())

    @property
    def n_pixels(self) -> int:
        return len(self) * self.height * self.width

    def _gather(self, local: Tensor, rows: Tensor, cols: Tensor, bg: Tensor) -> RayBatch:
        cam = self._indices_dev[local]
        px = (cols.float() + 0.5) * self.sx
        py = (rows.float() + 0.5) * self.sy
        origins, directions = self.cameras.rays(cam, px, py)
        rgb = self.images[local, rows, cols].float() / 255.0
        if self.composite is not None and self.mode != "none":
            a = self.composite[local, rows, cols].float().unsqueeze(-1) / 255.0
            rgb = composite(rgb, a, bg)
        else:
            bg = torch.zeros_like(rgb)
        mask = None if self.coverage is None else self.coverage[local, rows, cols].float() / 255.0
        return RayBatch(origins, directions, rgb, bg, mask, cam, torch.stack([px, py], dim=-1))

    def _background(self, n: int, mode: str, generator: torch.Generator | None = None) -> Tensor:
        if mode == "random":
            assert generator is not None
            return torch.rand((n, 3), generator=generator, device=generator.device).to(self.device)
        value = 0.0 if mode == "black" else 1.0
        return torch.full((n, 3), value, device=self.device)

    def sample(self, n_rays: int, generator: torch.Generator) -> RayBatch:
        """``n_rays`` pixels drawn uniformly over all images of the split (pixel centres)."""
        hw = self.height * self.width
        flat = torch.randint(0, len(self) * hw, (n_rays,), generator=generator, device=generator.device)
        flat = flat.to(self.device)
        local = flat // hw
        rem = flat % hw
        rows, cols = rem // self.width, rem % self.width
        mode = self.mode if self.mode in ("random", "white", "black") else "white"
        bg = self._background(n_rays, mode, generator)
        return self._gather(local, rows, cols, bg)

    def image(self, i: int) -> tuple[RayBatch, tuple[int, int]]:
        """Every pixel of the ``i``-th image of the split, row-major, and its ``(H, W)``. RGBA targets are
        composited on white (or on black when the dataset's background is ``black``)."""
        if not 0 <= i < len(self):
            raise IndexError(f"image {i} out of range for the {self.split} split of {len(self)} images")
        rows, cols = torch.meshgrid(
            torch.arange(self.height, device=self.device),
            torch.arange(self.width, device=self.device),
            indexing="ij",
        )
        rows, cols = rows.reshape(-1), cols.reshape(-1)
        local = torch.full_like(rows, i)
        bg = self._background(rows.numel(), "black" if self.mode == "black" else "white")
        return self._gather(local, rows, cols, bg), (self.height, self.width)

    def target_image(self, i: int) -> Tensor:
        """[H,W,3] float target of the ``i``-th image, as :meth:`image` composites it."""
        batch, (h, w) = self.image(i)
        return batch.rgb.reshape(h, w, 3)
