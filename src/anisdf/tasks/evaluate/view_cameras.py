"""The camera a scored view is rendered from: as the dataset gives it, or fitted to the view's image.

``given``: the dataset's pose. ``fit``: test-time pose optimisation (BARF, Lin et al. 2021, Sec. 4): with the scene
frozen, an se(3) correction of the view's camera (:class:`~anisdf.models.per_image.CameraRefinement`, zero at the
start) is fitted to its image by photometric error, then the view is rendered and scored from the corrected camera.
A run whose training cameras were refined (``cameras.refine``) lives in a frame that the training photos fix only up
to a small rigid motion (the anchor keeps it near the given cameras' frame, not on it), and a real capture's held-out
poses carry the same structure-from-motion errors as its training poses: ``fit`` scores the scene, not those
offsets. Fitting 6 numbers to a whole image leaks almost nothing of it; with ``--appearance fit-left-half`` the camera
is fitted on the left half too, and only the right half is scored.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any

import torch

from anisdf.models.per_image import CameraRefinement, pose_changes
from anisdf.tasks.evaluate.view_fit import fit_to_view, photometric_error, view_pixels

PROTOCOLS = ("auto", "given", "fit")
FIT_STEPS = 150
FIT_RAYS = 2048
FIT_LR = 2e-3
FIT_FINAL = 0.1
CHECK_RAYS = 8192


def fit_camera(model, data, i: int, left_half: bool = False, seed: int = 0) -> tuple[torch.Tensor, bool]:
    """[3,4] camera-to-world of view ``i`` of ``data`` fitted to its image, and whether the fit was kept: Adam on the
    se(3) correction, learning rate :data:`FIT_LR` decaying to :data:`FIT_FINAL` of it (cosine), :data:`FIT_STEPS`
    steps of :data:`FIT_RAYS` random pixels (of the left half, columns ``< W // 2``, when ``left_half``), mean
    squared error, the scene frozen. The fit is kept only when it lowers the error on a fixed draw of :data:`CHECK_RAYS`
    pixels of the same half; else the given pose is returned (on a fox test view an unchecked fit wandered 5 deg
    off and scored 10 dB below the given pose, benchmarks/RESULTS.md)."""
    batch, (h, w) = data.image(i)
    pixels = view_pixels(h, w, batch.rgb.device, left_half)
    index = int(data.indices[i])
    pose = data.cameras.c2w[index : index + 1]
    cam = CameraRefinement(pose, torch.ones(1, dtype=torch.bool), anchor=False).to(pose.device)

    grid = model.image_grid()  # the grid the scored image marches: the same picture, fewer samples a ray

    def render(b):
        return model.render_rays(*cam(b.origins, b.directions, torch.zeros_like(b.cam_idx)), b.background, grid=grid)

    gen = torch.Generator().manual_seed(seed + 1_000_003)  # not the fit's own draws
    check = batch[pixels[torch.randperm(pixels.numel(), generator=gen)[:CHECK_RAYS].to(pixels.device)]]
    with torch.no_grad():
        before = float(photometric_error(render, check))
    fit_to_view(model, batch, pixels, list(cam.parameters()), render, FIT_STEPS, FIT_RAYS, FIT_LR, seed,
                final_lr=FIT_FINAL)
    with torch.no_grad():
        kept = float(photometric_error(render, check)) < before
    if not kept:
        with torch.no_grad():
            cam.delta.zero_()
    return cam.refined_poses()[0], kept


@contextlib.contextmanager
def view_camera(model, data, i: int, protocol: str, left_half: bool = False) -> Iterator[dict[str, float]]:
    """Render view ``i`` from the camera ``protocol`` gives it. Yields the per-view record: for ``fit``, the fitted
    correction's rotation (deg) and centre move (normalised scene units). The scene's cameras (which a baked asset's
    render reads) are corrected alike; the dataset's pose is put back after."""
    if protocol == "given":
        yield {}
        return
    index = int(data.indices[i])
    given, scene_given = data.cameras, data.scene.cameras
    fitted, kept = fit_camera(model, data, i, left_half=left_half, seed=i)
    data.cameras, data.scene.cameras = (dataclasses.replace(c, c2w=c.c2w.index_put((torch.tensor([index]),),
                                                                                  fitted.to(c.c2w)[None]))
                                        for c in (given, scene_given))
    deg, move = pose_changes(*(p[None].double().cpu().numpy() for p in (given.c2w[index], fitted)))
    try:
        yield {"camera_fit_deg": float(deg[0]), "camera_fit_move": float(move[0]), "camera_fit_kept": bool(kept)}
    finally:
        data.cameras, data.scene.cameras = given, scene_given


def resolve_protocol(requested: str, refined: bool) -> str:
    """The protocol ``--cameras`` asks for; ``auto``: ``fit`` for a run that refined its training cameras (its scene
    sits in a frame the photos fix only up to a small rigid motion), else ``given``."""
    if requested != "auto":  # eval's option check has refused anything outside PROTOCOLS
        return requested
    return "fit" if refined else "given"


def view_cameras_record(protocol: str, left_half: bool, requested: str | None = None) -> dict[str, Any]:
    """eval.json's ``protocol.cameras.scored_views`` (``requested``: what ``--cameras`` said, when ``auto``)."""
    asked = {"requested": "auto: fit for runs with refined cameras, else given"} if requested == "auto" else {}
    if protocol == "given":
        return {"protocol": "given", "views": "rendered from the dataset's poses", **asked}
    return {"protocol": "fit", **asked,
            "views": f"rendered from the dataset's pose corrected by an se(3) fitted to the view's "
                     f"{'left half' if left_half else 'image'} with the scene frozen (test-time pose optimisation, "
                     f"BARF): Adam lr {FIT_LR} cosine to {FIT_FINAL:g} of it, {FIT_STEPS} steps of {FIT_RAYS} "
                     f"random pixels, MSE; kept only when it lowers the error on a fixed draw of {CHECK_RAYS} "
                     "pixels, else the given pose (per_view camera_fit_kept); per_view camera_fit_deg / "
                     "camera_fit_move (normalised units) give each correction"}
