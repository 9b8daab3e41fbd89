"""A small analytic scene rendered by sphere tracing, written in NeRF-synthetic format.

Used by ``anisdf demo`` and the tests: nothing is downloaded. The object is a torus with a sphere resting in it
(radius ~0.75 in world units), with a colourful position-dependent albedo, a Lambertian term and a Blinn-Phong
highlight (so the reflection branch has something to model). Cameras lie on a sphere of radius 3 looking at the
origin, Blender/OpenGL convention like the original dataset. Alongside the images it writes the test normal
maps (``r_i_normal.png``, (n+1)/2) and the ground-truth mesh (``gt_mesh.ply``) from marching cubes of the SDF.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image


def scene_sdf(x: torch.Tensor) -> torch.Tensor:
    """Torus (major 0.5, minor 0.18, in the xy plane, z up) united with a sphere of radius 0.28 above it."""
    q = torch.stack([x[..., :2].norm(dim=-1) - 0.5, x[..., 2]], dim=-1)
    torus = q.norm(dim=-1) - 0.18
    sphere = (x - x.new_tensor([0.0, 0.0, 0.22])).norm(dim=-1) - 0.28
    return torch.minimum(torus, sphere)


def scene_normal(x: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    e = torch.eye(3, dtype=x.dtype, device=x.device) * eps
    g = torch.stack([scene_sdf(x + e[i]) - scene_sdf(x - e[i]) for i in range(3)], dim=-1)
    return F.normalize(g, dim=-1)


def albedo(x: torch.Tensor) -> torch.Tensor:
    a = 0.55 + 0.4 * torch.sin(4.0 * x[..., 0:1] + torch.tensor([0.0, 2.1, 4.2]))
    b = 0.8 + 0.2 * torch.cos(9.0 * x[..., 2:3])
    return (a * b).clamp(0.05, 0.95)


def look_at_c2w(eye: np.ndarray) -> np.ndarray:
    """Blender/OpenGL camera-to-world (x right, y up, z backwards) looking at the origin, z up."""
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, eye
    return m


def sphere_trace(origins: torch.Tensor, dirs: torch.Tensor, n_iter: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.zeros(origins.shape[0])
    for _ in range(n_iter):
        d = scene_sdf(origins + dirs * t[:, None])
        t = t + d
    hit = scene_sdf(origins + dirs * t[:, None]).abs() < 1e-3
    return t, hit & (t < 10)


def render(c2w: np.ndarray, size: int, focal: float, ss: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """RGBA uint8 image and normal map (RGBA, (n+1)/2 + coverage), ``ss x ss`` supersampled."""
    n = size * ss
    ys, xs = torch.meshgrid(torch.arange(n) + 0.5, torch.arange(n) + 0.5, indexing="ij")
    f = focal * ss
    d_cam = torch.stack([(xs - n / 2) / f, -(ys - n / 2) / f, -torch.ones_like(xs)], -1).reshape(-1, 3)
    rot = torch.tensor(c2w[:3, :3], dtype=torch.float32)
    dirs = F.normalize(d_cam @ rot.T, dim=-1)
    origins = torch.tensor(c2w[:3, 3], dtype=torch.float32).expand_as(dirs)
    t, hit = sphere_trace(origins, dirs)
    x = origins + dirs * t[:, None]
    nrm = scene_normal(x)
    light = F.normalize(torch.tensor([0.4, -0.5, 0.8]), dim=0)
    diffuse = (nrm @ light).clamp_min(0)[:, None]
    half = F.normalize(light - dirs, dim=-1)
    spec = ((nrm * half).sum(-1).clamp_min(0) ** 60)[:, None]
    rgb = (albedo(x) * (0.25 + 0.75 * diffuse) + 0.5 * spec).clamp(0, 1)
    a = hit.float()[:, None]
    # a miss marches to infinity (NaN colour and normal): zero, so that the coverage average below is the hits' mean
    rgb, nrm = torch.where(hit[:, None], rgb, 0.0), torch.where(hit[:, None], nrm, 0.0)
    rgba = torch.cat([rgb * a, a], -1).reshape(size, ss, size, ss, 4).mean(dim=(1, 3))
    rgba[..., :3] = rgba[..., :3] / rgba[..., 3:].clamp_min(1e-6)
    nmap = torch.cat([(nrm + 1) / 2 * a, a], -1).reshape(size, ss, size, ss, 4).mean(dim=(1, 3))
    nmap[..., :3] = nmap[..., :3] / nmap[..., 3:].clamp_min(1e-6)
    to8 = lambda v: (v.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()  # noqa: E731
    return to8(rgba), to8(nmap)


def make_synthetic_scene(out: Path, n_train: int = 40, n_test: int = 8, size: int = 96,
                         seed: int = 0, mesh_resolution: int = 128) -> Path:
    """Write the scene to ``out`` (transforms_{train,test}.json, train/ test/ PNGs, gt_mesh.ply)."""
    import mcubes
    import trimesh

    out = Path(out)
    rng = np.random.default_rng(seed)
    angle_x = 0.6911
    focal = 0.5 * size / math.tan(0.5 * angle_x)
    for split, n in (("train", n_train), ("test", n_test)):
        (out / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in range(n):
            if split == "train":  # quasi-uniform over the upper 3/4 of the sphere
                z = rng.uniform(-0.3, 0.95)
                phi = rng.uniform(0, 2 * math.pi)
            else:  # an orbit at 30 degrees elevation
                z, phi = math.sin(math.radians(30)), 2 * math.pi * i / n
            eye = 3.0 * np.array([math.sqrt(1 - z * z) * math.cos(phi), math.sqrt(1 - z * z) * math.sin(phi), z])
            c2w = look_at_c2w(eye)
            rgba, nmap = render(c2w, size, focal)
            Image.fromarray(rgba, "RGBA").save(out / split / f"r_{i}.png")
            if split == "test":
                Image.fromarray(nmap, "RGBA").save(out / split / f"r_{i}_normal.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames},
                                                                 indent=1))
    r = mesh_resolution
    lin = torch.linspace(-1, 1, r)
    grid = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
    sdf = scene_sdf(grid).reshape(r, r, r).numpy()
    v, f = mcubes.marching_cubes(-sdf, 0.0)
    v = v / (r - 1) * 2 - 1
    trimesh.Trimesh(v, f[:, ::-1] if trimesh.Trimesh(v, f).volume < 0 else f).export(out / "gt_mesh.ply")
    return out
