"""The appearance code a scored view is rendered with, and what eval.json says about it and about the cameras.

A test view has no trained appearance code (``appearance.embedding``). ``mean``: the mean of the training images'
codes. ``fit-left-half``: NeRF-W's protocol (Martin-Brualla et al. 2021, Sec. 6): a code is fitted to the left half of
the test image (the scene frozen), and only the right half is scored.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch

from anisdf.tasks.evaluate.view_fit import fit_to_view, view_pixels

PROTOCOLS = ("mean", "fit-left-half")
FIT_STEPS = 64
FIT_RAYS = 1024
FIT_LR = 0.05


def fit_left_half(model, data, i: int, seed: int = 0) -> torch.Tensor:
    """[dim] appearance code of view ``i`` of ``data`` fitted (Adam, :data:`FIT_STEPS` steps of :data:`FIT_RAYS`
    random pixels, MSE) to the left half of its image (columns ``< W // 2``), starting from the mean code."""
    batch, (h, w) = data.image(i)
    left = view_pixels(h, w, batch.rgb.device, left_half=True)
    code = model.image_codes.mean().detach().clone().requires_grad_(True)
    grid = model.image_grid()  # the grid the scored image marches: the same picture, fewer samples a ray
    fit_to_view(model, batch, left, [code], lambda b: model.render_rays(b.origins, b.directions, b.background,
                                                                        codes=code.expand(len(b), -1), grid=grid),
                FIT_STEPS, FIT_RAYS, FIT_LR, seed)
    return code.detach()


@contextlib.contextmanager
def view_code(model, data, i: int, protocol: str) -> Iterator[None]:
    """Render view ``i`` with the code ``protocol`` gives it (nothing to do without codes, or for ``mean``)."""
    codes = getattr(model, "image_codes", None)
    if codes is None or protocol == "mean":
        yield
        return
    codes.fixed = fit_left_half(model, data, i, seed=i)
    try:
        yield
    finally:
        codes.fixed = None


def appearance_record(model, protocol: str) -> dict[str, Any]:
    """eval.json's ``protocol.appearance``."""
    if getattr(model, "image_codes", None) is None:
        # fit-left-half on a run without codes scores the same right halves, so that runs with and without codes
        # compare under one protocol
        return {"codes": "none (appearance.embedding off): one appearance for every view", "protocol": protocol,
                "scored": "whole image" if protocol == "mean" else
                          "right half (columns >= W // 2) for PSNR and SSIM, as fit-left-half scores a run with codes"}
    transform = getattr(model, "colour_transform", None)
    kind = (f"a colour transform per training image (appearance.embedding, embedding_kind={transform})"
            if transform else "per training image (appearance.embedding)")
    if protocol == "mean":
        return {"codes": kind, "protocol": "mean",
                "view_code": "the mean of the training images' codes, for every scored view", "scored": "whole image"}
    return {"codes": kind, "protocol": "fit-left-half",
            "view_code": f"NeRF-W: fitted to the left half (columns < W // 2) of each scored image, the scene frozen: "
                         f"Adam lr {FIT_LR}, {FIT_STEPS} steps of {FIT_RAYS} random pixels, MSE, from the mean code",
            "scored": "right half (columns >= W // 2) for PSNR and SSIM; normal MAE on the whole image"}


def cameras_record(model, split: str, refined: bool) -> dict[str, Any]:
    """eval.json's ``protocol.cameras``: which poses the scored views were rendered from."""
    if getattr(model, "cameras", None) is None:
        return {"refine": False, "poses": "as the dataset gives them"}
    return {"refine": True,
            "poses": ("training cameras as refined in training (refined_cameras.json); cameras that did not train "
                      "(held-out test views) have no learned correction and use the dataset's poses")
            if refined else "as the dataset gives them (the run has no refined_cameras.json)",
            "split": split}
