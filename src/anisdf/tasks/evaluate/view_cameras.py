"""The camera a scored view is rendered from: as the dataset gives it, or fitted to the view's image.

``given``: the dataset's pose. ``fit``: test-time pose optimisation (BARF, Lin et al. 2021, Sec. 4): with the scene
frozen, an se(3) correction of the view's camera (:class:`~anisdf.models.per_image.CameraRefinement`, zero at the
start) is fitted to its image by photometric error, then the view is rendered and scored from the corrected camera.
Six numbers against thousands of pixels make a small least-squares problem, solved by Levenberg-Marquardt: a pixel's
colour depends on its own ray only, so three backward passes (one a colour channel) give every pixel's Jacobian
with respect to its ray, and the camera's own Jacobian (forward mode, :func:`torch.func.jacfwd`) chains it to the
correction. A few such steps, on one fixed draw of pixels, do what 150 Adam steps on fresh random draws did (the
protocol before) in about a third of the time, at least as well (benchmarks/RESULTS.md, "Rendering a view").
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
from anisdf.tasks.evaluate.view_fit import scene_frozen, view_pixels

PROTOCOLS = ("auto", "given", "fit")
FIT_RAYS = 8192
FIT_ITERATIONS = 8
FIT_TOL = 2e-3
FIT_RETRIES = 5
FIT_PRIOR = 1e-3
FIT_CHUNK = 4096
CHECK_RAYS = 8192


def _rays(cam: CameraRefinement, b, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The origins and directions of the rays ``b`` through the camera corrected by ``xi`` [6] (a pure function of
    ``xi``, so forward mode can differentiate it)."""
    return torch.func.functional_call(cam, {"delta": xi[None]}, (b.origins, b.directions, torch.zeros_like(b.cam_idx)))


def normal_equations(render, cam: CameraRefinement, fit, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
    """``(J^T J, J^T r, mean squared error)`` of the rays ``fit`` rendered from the camera corrected by ``xi`` [6]:
    ``r`` the colour residuals, ``J`` their Jacobian with respect to ``xi`` (float64 sums over chunks of
    :data:`FIT_CHUNK` rays)."""
    jtj, jtr, sse = xi.new_zeros(6, 6, dtype=torch.float64), xi.new_zeros(6, dtype=torch.float64), 0.0
    for s in range(0, len(fit), FIT_CHUNK):
        b = fit[s : s + FIT_CHUNK]
        # [n, 3, 6]: each ray's origin and direction against the correction
        j_o, j_d = torch.func.jacfwd(lambda x, b=b: _rays(cam, b, x))(xi)
        o, d = (t.detach().requires_grad_(True) for t in _rays(cam, b, xi))
        with torch.enable_grad():
            rgb = render(o, d, b.background).rgb.float()
            per_ray = [torch.autograd.grad(rgb[:, k].sum(), (o, d), retain_graph=k < 2) for k in range(3)]
        jac = torch.stack([torch.einsum("ni,nij->nj", g_o, j_o) + torch.einsum("ni,nij->nj", g_d, j_d)
                           for g_o, g_d in per_ray], 1).double().reshape(-1, 6)
        res = (rgb.detach() - b.rgb).double().reshape(-1)
        jtj += jac.T @ jac
        jtr += jac.T @ res
        sse += float(res @ res)
    return jtj, jtr, sse / (3 * len(fit))


def _error(render, cam: CameraRefinement, fit, xi: torch.Tensor) -> float:
    """The mean squared error of the rays ``fit`` rendered from the camera corrected by ``xi`` (no gradients)."""
    with torch.no_grad():
        sse = 0.0
        for s in range(0, len(fit), FIT_CHUNK):
            b = fit[s : s + FIT_CHUNK]
            o, d = _rays(cam, b, xi)
            sse += float(((render(o, d, b.background).rgb.float() - b.rgb) ** 2).sum())
    return sse / (3 * len(fit))


def solve_correction(render, cam: CameraRefinement, fit) -> torch.Tensor:
    """The se(3) correction [6] minimising the photometric error of the rays ``fit`` plus ``mu |xi|^2``:
    Levenberg-Marquardt from zero (damping ``lam * diag(H)``; a step is kept only when it lowers the objective, else
    the damping is raised fourfold, at most :data:`FIT_RETRIES` times in a row, a trial costing one render without
    gradients), at most :data:`FIT_ITERATIONS` steps, stopping when a step changes the objective by less than
    :data:`FIT_TOL` of it either way. ``mu`` is :data:`FIT_PRIOR` of the mean curvature of the error at zero: it
    leaves well-determined directions alone and keeps the nearly flat ones (a turn that a sideways move undoes) near
    zero, where unregularised steps drifted (a maryrose view 7 deg off for no better picture)."""
    n = 3 * len(fit)
    xi, lam, mu = cam.delta.new_zeros(6), 1e-3, None

    def linearised(at: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
        jtj, jtr, err = normal_equations(render, cam, fit, at)
        nonlocal mu
        mu = FIT_PRIOR * float(torch.diag(jtj).mean()) / n if mu is None else mu
        a = at.double()
        return (jtj / n + mu * torch.eye(6, dtype=jtj.dtype, device=jtj.device), jtr / n + mu * a,
                err + mu * float(a @ a))

    def objective(at: torch.Tensor) -> float:
        return _error(render, cam, fit, at) + mu * float(at.double() @ at.double())

    hess, grad, f = linearised(xi)
    for _ in range(FIT_ITERATIONS):
        for _ in range(FIT_RETRIES):
            trial = xi - torch.linalg.solve(hess + lam * torch.diag(torch.diag(hess)), grad).to(xi.dtype)
            t_f = objective(trial)
            if t_f < f:
                break
            if t_f - f < FIT_TOL * f:  # flat where the model points: nothing left worth a step
                return xi
            lam *= 4
        else:
            return xi
        xi, gain = trial, f - t_f
        lam = max(lam / 3, 1e-6)
        if gain < FIT_TOL * t_f:
            break
        hess, grad, f = linearised(xi)
    return xi


def fit_camera(model, data, i: int, left_half: bool = False, seed: int = 0) -> tuple[torch.Tensor, bool]:
    """[3,4] camera-to-world of view ``i`` of ``data`` fitted to its image, and whether the fit was kept: the se(3)
    correction that :func:`solve_correction` finds for a fixed draw of :data:`FIT_RAYS` pixels (of the left half,
    columns ``< W // 2``, when ``left_half``), the scene frozen. The fit is kept only when it lowers the error on
    another draw of :data:`CHECK_RAYS` pixels of the same half; else the given pose is returned (on a fox test view an
    unchecked fit wandered 5 deg off and scored 10 dB below the given pose, benchmarks/RESULTS.md)."""
    batch, (h, w) = data.image(i)
    pixels = view_pixels(h, w, batch.rgb.device, left_half)
    index = int(data.indices[i])
    pose = data.cameras.c2w[index : index + 1]
    cam = CameraRefinement(pose, torch.ones(1, dtype=torch.bool), anchor=False).to(pose.device)
    grid = model.image_grid()  # the grid the scored image marches: the same picture, fewer samples a ray

    def render(o, d, background):
        return model.render_rays(o, d, background, grid=grid)

    def draw(n: int, gen_seed: int):
        order = torch.randperm(pixels.numel(), generator=torch.Generator().manual_seed(gen_seed))
        return batch[pixels[order[:n].to(pixels.device)]]

    fit, check = draw(FIT_RAYS, seed), draw(CHECK_RAYS, seed + 1_000_003)  # two different draws

    zero = cam.delta.new_zeros(6)
    before = _error(render, cam, check, zero)
    with scene_frozen(model):
        xi = solve_correction(render, cam, fit)
    kept = _error(render, cam, check, xi) < before
    with torch.no_grad():
        cam.delta.copy_((xi if kept else zero)[None])
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
                     f"BARF): Levenberg-Marquardt on a fixed draw of {FIT_RAYS} pixels, a prior of {FIT_PRIOR:g} "
                     f"of the error's mean curvature towards no correction, at most {FIT_ITERATIONS} steps, "
                     f"stopping when a step gains less than {FIT_TOL:g} of the error; kept only when it "
                     f"lowers the error on another draw of {CHECK_RAYS} pixels, else the given pose (per_view "
                     "camera_fit_kept); per_view camera_fit_deg / camera_fit_move (normalised units) give each "
                     "correction"}
