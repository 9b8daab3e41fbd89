"""What a real capture learns per training image: a correction of its camera and an appearance code.

Camera refinement (``cameras.refine``): camera ``i``'s pose becomes ``c2w_i exp(xi_i)`` with ``xi_i = (omega, v)`` in
se(3), zero at the start, the correction right-multiplied so that it acts in the camera's own frame (a rotation
about the camera centre, a move along the camera's axes), as nerfstudio's SE3 camera optimiser. Appearance codes
(``appearance.embedding``): NeRF-W's per-image embedding, zero at the start; a view with no trained code takes the
mean of the training images' codes.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn


def _skew(w: Tensor) -> Tensor:
    """[...,3,3] cross-product matrices ``[w]_x``."""
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], dim=-1).reshape(*w.shape[:-1], 3, 3)


def se3_exp(xi: Tensor) -> tuple[Tensor, Tensor]:
    """The exponential map of se(3): ``xi = (omega, v)`` ``[...,6]`` to a rotation ``[...,3,3]`` and translation
    ``[...,3]``: ``R = I + A [w] + B [w]^2`` (Rodrigues) and ``t = (I + B [w] + C [w]^2) v`` with ``A = sin(th)/th``,
    ``B = (1 - cos th)/th^2``, ``C = (th - sin th)/th^3``; Taylor series below ``th = 1e-2`` keep it exact and
    differentiable at zero."""
    w, v = xi[..., :3], xi[..., 3:]
    th2 = (w * w).sum(-1, keepdim=True)[..., None]
    small = th2 < 1e-4
    th2s = torch.where(small, torch.ones_like(th2), th2)  # no 0/0 in the branch that is not taken
    th = th2s.sqrt()
    a = torch.where(small, 1 - th2 / 6 + th2 * th2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - torch.cos(th)) / th2s)
    c = torch.where(small, 1 / 6 - th2 / 120 + th2 * th2 / 5040, (th - torch.sin(th)) / (th2s * th))
    k = _skew(w)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    rot = eye + a * k + b * k2
    t = ((eye + b * k + c * k2) @ v[..., None])[..., 0]
    return rot, t


def rodrigues(w: Tensor) -> Tensor:
    """Rotation matrices [...,3,3] of rotation vectors ``w`` [...,3] (the rotation part of :func:`se3_exp`)."""
    return se3_exp(torch.cat([w, torch.zeros_like(w)], dim=-1))[0]


def common_motion(turn: Tensor, move: Tensor, centres: Tensor) -> tuple[Tensor, Tensor]:
    """The small rigid motion of the whole world that best explains per-camera world-frame corrections: rotation
    vectors ``turn`` [N,3] and centre moves ``move`` [N,3] of cameras at ``centres`` [N,3]. A world rotation ``w``
    about the origin and shift ``v`` turn every camera by ``w`` and move centre ``o`` by ``w x o + v``; least squares
    over both, the rotations weighted by the cameras' spread so that the two parts weigh alike. Returns (w, v)."""
    n = centres.shape[0]
    scale2 = ((centres - centres.mean(0)) ** 2).sum(-1).mean().clamp_min(1e-8)
    eye = torch.eye(3, dtype=centres.dtype, device=centres.device)
    # rows: sqrt(scale2) (w) = sqrt(scale2) turn_i ;  -[o_i]x w + v = move_i
    a_rot = torch.cat([eye * scale2.sqrt(), torch.zeros_like(eye)], dim=1).expand(n, 3, 6)
    a_mov = torch.cat([-_skew(centres), eye.expand(n, 3, 3)], dim=2)
    a = torch.cat([a_rot, a_mov], dim=1).reshape(-1, 6)
    b = torch.cat([turn * scale2.sqrt(), move], dim=1).reshape(-1, 1)
    ata = a.T @ a + 1e-9 * torch.eye(6, dtype=a.dtype, device=a.device)
    x = torch.linalg.solve(ata, a.T @ b)[:, 0]
    return x[:3], x[3:]


class CameraRefinement(nn.Module):
    """Per-camera se(3) corrections of ``poses`` ([N,3,4] camera-to-world, normalised frame); only the cameras
    ``trained`` ([N] bool) are corrected, the others keep their pose.

    ``anchor``: the rigid motion common to all the corrections is taken out of them (:func:`common_motion`, applied
    to the corrections' world-frame rotation vectors and centre moves). Moving every camera and the scene together
    changes no training photo, so nothing in the photos pins it, while it moves the scene against the held-out
    cameras, which are not corrected: refining dtu_scan65's exact cameras without the anchor turned them all by a
    common 0.37 deg (benchmarks/RESULTS.md)."""

    def __init__(self, poses: Tensor, trained: Tensor, anchor: bool = True) -> None:
        super().__init__()
        self.delta = nn.Parameter(torch.zeros(poses.shape[0], 6))
        self.register_buffer("poses", poses.detach().float().clone())
        self.register_buffer("trained", trained.detach().bool().clone())
        self.anchor = bool(anchor)

    def corrections(self) -> tuple[Tensor, Tensor]:
        """Each camera's correction ``exp(xi)`` as a rotation [N,3,3] and translation [N,3] (identity when frozen),
        with the common motion taken out when anchored."""
        xi = self.delta * self.trained[:, None]
        d_rot, d_t = se3_exp(xi)
        if not self.anchor or int(self.trained.sum()) < 3:
            return d_rot, d_t
        rot, centre = self.poses[:, :, :3], self.poses[:, :, 3]
        turn = (rot @ xi[:, :3, None])[..., 0]  # R exp([w]) R^T = exp([R w]): the world-frame rotation vector
        move = (rot @ d_t[..., None])[..., 0]  # the centre's move in the world
        idx = self.trained.nonzero()[:, 0]
        w, v = common_motion(turn[idx], move[idx], centre[idx])
        mask = self.trained[:, None].to(xi.dtype)
        turn = turn - w * mask
        move = move - (torch.linalg.cross(w.expand_as(centre), centre) + v) * mask
        rt = rot.transpose(1, 2)
        return rodrigues((rt @ turn[..., None])[..., 0]), (rt @ move[..., None])[..., 0]

    def forward(self, origins: Tensor, dirs: Tensor, cam_idx: Tensor) -> tuple[Tensor, Tensor]:
        """Rays of the corrected cameras: with ``c2w' = [R | o] [dR | dt]``, ``o' = o + R dt`` and
        ``d' = R dR R^T d`` (unit directions stay unit)."""
        d_rot, d_t = self.corrections()
        rot = self.poses[:, :, :3]
        turn = rot @ d_rot @ rot.transpose(1, 2)  # [N,3,3]: the correction as a world-frame rotation
        move = (rot @ d_t[..., None])[..., 0]
        idx = cam_idx.long()  # index_select: a deterministic backward (see AniSDFModel.render_rays)
        o = origins + move.index_select(0, idx)
        d = (turn.index_select(0, idx) @ dirs[..., None])[..., 0]
        return o, d

    def regulariser(self) -> Tensor:
        """Mean over the trained cameras of ``|xi|^2``: keeps the corrections small (they are a nudge, and the
        scene's frame should stay the one the test cameras live in)."""
        return (self.delta[self.trained] ** 2).sum(-1).mean()

    @torch.no_grad()
    def refined_poses(self) -> Tensor:
        """[N,3,4] corrected camera-to-world matrices ``c2w exp(xi)`` (normalised frame)."""
        d_rot, d_t = self.corrections()
        rot, origin = self.poses[:, :, :3], self.poses[:, :, 3]
        return torch.cat([rot @ d_rot, (origin + (rot @ d_t[..., None])[..., 0])[..., None]], dim=-1)


TRANSFORM_DIMS = {"affine": 12, "gain": 3}
"""Numbers of a per-image colour transform (``appearance.embedding_kind``): affine, ``M`` row by row then ``b``;
gain, the three channels' log gains."""


def colour_affine(c: Tensor, a: Tensor, coverage: Tensor) -> Tensor:
    """``c + M c + b * coverage`` [B, 3] for premultiplied colours ``c`` [B, 3] of rays whose opacity is ``coverage``
    [B], ``a`` [B, 12] each ray's image transform (zero: identity). Exposure and white balance scale the light a pixel
    gathers, so the offset ``b`` grows with the coverage: an empty ray stays empty."""
    m = a[:, :9].reshape(-1, 3, 3)
    return c + torch.einsum("bij,bj->bi", m, c) + a[:, 9:] * coverage[:, None]


def colour_gain(c: Tensor, a: Tensor) -> Tensor:
    """``c * exp(a)`` [B, 3], ``a`` [B, 3] each ray's image log gains (zero: identity). A camera's exposure and white
    balance scale linear light by a gain a channel; through the sRGB curve (about a power 1/2.2) that stays a gain."""
    return c * a.exp()


def colour_transform(kind: str, c: Tensor, a: Tensor, coverage: Tensor) -> Tensor:
    """:func:`colour_affine` or :func:`colour_gain` (``kind``) of premultiplied colours ``c`` [B, 3]."""
    return colour_affine(c, a, coverage) if kind == "affine" else colour_gain(c, a)


def undo_colour_transform(kind: str, c: Tensor, a: Tensor) -> Tensor:
    """The scene's own colours [..., 3] of one photo's colours ``c`` (pixels the scene covers) under its transform
    ``a`` [dim]: the inverse of :func:`colour_transform` at full coverage."""
    if kind == "gain":
        return c * (-a).exp()
    m = torch.eye(3, dtype=a.dtype, device=a.device) + a[:9].reshape(3, 3)
    return (c - a[9:]) @ torch.linalg.inv(m).T


class ImageCodes(nn.Module):
    """An appearance code per image ([N, dim], zero at the start; or a colour transform, :func:`colour_transform`);
    images not ``trained`` read the mean code, or ``fixed`` when set (a code fitted to a test view,
    :mod:`anisdf.tasks.evaluate.appearance`)."""

    def __init__(self, n_images: int, dim: int, trained: Tensor) -> None:
        super().__init__()
        self.codes = nn.Parameter(torch.zeros(n_images, dim))
        self.register_buffer("trained", trained.detach().bool().clone())
        self.fixed: Tensor | None = None

    def mean(self) -> Tensor:
        return self.codes[self.trained].mean(0)

    def untrained(self) -> Tensor:
        """[dim] the code of a view without its own: ``fixed``, else the mean."""
        return self.fixed if self.fixed is not None else self.mean()

    def forward(self, cam_idx: Tensor | None, n: int) -> Tensor:
        """[n, dim] codes of the images ``cam_idx`` ([n]), :meth:`untrained`'s for the others or when None."""
        if cam_idx is None:
            return self.untrained().expand(n, -1)
        idx = cam_idx.long()
        return torch.where(self.trained[idx, None], self.codes.index_select(0, idx), self.untrained())


def dataset_poses(poses: Tensor, to_world: np.ndarray) -> np.ndarray:
    """[N,4,4] camera-to-world in the dataset's frame of normalised ``poses`` [N,3,4] (``to_world`` a similarity)."""
    t = np.asarray(to_world, dtype=np.float64)
    c2w = np.tile(np.eye(4), (poses.shape[0], 1, 1))
    c2w[:, :3, :4] = poses.detach().double().cpu().numpy()
    c2w = t @ c2w
    c2w[:, :3, :3] /= np.cbrt(np.linalg.det(t[:3, :3]))
    return c2w


def normalised_poses(c2w: np.ndarray, to_world: np.ndarray) -> Tensor:
    """The inverse of :func:`dataset_poses`: [N,3,4] normalised camera-to-world of dataset-frame ``c2w`` [N,4,4]."""
    t = np.asarray(to_world, dtype=np.float64)
    out = np.linalg.inv(t) @ np.asarray(c2w, dtype=np.float64)
    out[:, :3, :3] *= np.cbrt(np.linalg.det(t[:3, :3]))
    return torch.from_numpy(out[:, :3, :4]).float()


def pose_changes(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[N] rotation angles (deg) and centre moves between camera-to-world matrices ``a`` and ``b`` ([N,3,4] or
    [N,4,4])."""
    rel = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return angle, np.linalg.norm(b[:, :3, 3] - a[:, :3, 3], axis=-1)


def image_key(path: Path, root: Path) -> str:
    """How refined_cameras.json names an image: its path inside the dataset folder (its file name when outside)."""
    try:
        return Path(os.path.abspath(path)).relative_to(os.path.abspath(root)).as_posix()  # symlinks as they are
    except ValueError:
        return Path(path).name


def refined_cameras_record(refinement: CameraRefinement, image_paths: list[Path], root: Path,
                           to_world: np.ndarray, step: int) -> dict[str, Any]:
    """RUN/refined_cameras.json: every trained camera's pose as the dataset gives it and as refined, in the dataset's
    frame, with the rotation (deg) and camera-centre move (dataset units) between them."""
    idx = refinement.trained.nonzero()[:, 0].cpu()
    original = dataset_poses(refinement.poses[idx], to_world)
    refined = dataset_poses(refinement.refined_poses()[idx], to_world)
    angle, move = pose_changes(original, refined)
    cameras = [{"image": image_key(image_paths[i], root), "index": int(i), "rotation_deg": round(float(a), 6),
                "translation": float(m), "original": o.tolist(), "refined": r.tolist()}
               for i, a, m, o, r in zip(idx.tolist(), angle, move, original, refined, strict=True)]
    return {"frame": "the dataset's own frame and units (as its camera files give the poses)",
            "axes": "4x4 camera-to-world, OpenCV camera axes (x right, y down, z forward)",
            "refined": "c2w exp(xi): the learned se(3) correction applied in the camera's frame",
            "step": int(step), "mean_rotation_deg": float(angle.mean()), "mean_translation": float(move.mean()),
            "cameras": cameras}


def apply_refined_cameras(scene: Any, record: dict[str, Any], to_world: np.ndarray) -> int:
    """Replace, in place, the cameras of ``scene`` (normalised by ``to_world``) that ``record`` (refined_cameras.json)
    refined by their refined poses; returns how many."""
    refined = {c["image"]: c["refined"] for c in record.get("cameras", [])}
    hits = [(i, refined[k]) for i, p in enumerate(scene.image_paths) if (k := image_key(p, scene.root)) in refined]
    if hits:
        c2w = scene.cameras.c2w.clone()
        poses = normalised_poses(np.asarray([r for _, r in hits]), to_world).to(c2w.device)
        c2w[[i for i, _ in hits]] = poses
        scene.cameras = replace(scene.cameras, c2w=c2w)
    return len(hits)
