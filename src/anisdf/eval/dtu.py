"""DTU Chamfer distance (paper Table 3): the official DTU MVS evaluation, as used by NeuS and 2DGS.

A port of the benchmark's ``BaseEvalMain_web.m`` / ``ComputeStat_web.m`` in the form of the public Python
port (jzhangbs/DTUeval-python ``eval.py``), with scipy instead of open3d / scikit-learn:

1. (optional) ``scale_mat_0`` of a NeuS ``cameras_sphere.npz`` maps the mesh from the unit sphere to DTU
   world coordinates (mm). Meshes written by ``anisdf extract-mesh`` already are in the dataset frame.
2. (optional) mask culling as NeuS / 2DGS ``cull_scan``: vertices that project into an image but outside its
   dilated foreground mask are removed, and so (here) are vertices that no image sees.
3. The mesh is sampled on a regular grid in every triangle at ``density`` spacing, plus its vertices.
4. The points are shuffled (``seed``) and thinned so that no two are within ``density`` (greedy, in the shuffled
   order: ``reducePts_haa``); the STL reference points are thinned the same way, as the MATLAB original does
   (the Python port does not: ``thin_stl=False``).
5. Accuracy uses the points inside ``ObsMask{scan}_10.mat`` (bounding box ``BB``, voxel size ``Res``, voxel
   ``round((p - BB[0]) / Res)`` set); completeness uses the STL points above ``Plane{scan}.mat``
   (``[x, 1] @ P > 0``) against the thinned points within the bounding box grown by ``patch`` mm.
6. Nearest-neighbour distances (cKDTree) of ``max_dist`` mm or more are outliers and are discarded
   (``Ddata = Ddata(Ddata < MaxDist)``); accuracy and completeness are the means of the rest, chamfer their mean.

The protocol is written down in ``docs/evaluation.md`` ("DTU Chamfer (Table 3)").
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io
import scipy.ndimage
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from anisdf.errors import AnisdfError, DataError
from anisdf.eval.metrics import load_mesh

# 2DGS cull_scan dilates the 1600x1200 DTU masks with disk(24); the radius is scaled to the mask width.
MASK_DILATION_PX_AT_1600 = 24
# eval.py's --patch_size: points farther than this outside the ObsMask bounding box are not scored at all.
PATCH_MM = 60.0


def dtu_paths(dtu_root: str | Path, scan: int) -> dict[str, Path]:
    """The three reference files of ``scan`` in the official layout under ``dtu_root``."""
    root = Path(dtu_root)
    return {
        "obs_mask": root / "ObsMask" / f"ObsMask{scan}_10.mat",
        "plane": root / "ObsMask" / f"Plane{scan}.mat",
        "stl": root / "Points" / "stl" / f"stl{scan:03}_total.ply",
    }


def _require(path: Path, what: str) -> None:
    if not path.is_file():
        raise DataError(path, f"{what} is missing (the DTU evaluation data, 'SampleSet' and 'Points' of the DTU "
                              "MVS benchmark, must be downloaded by hand and given with --dtu-root)")


def _loadmat(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    try:
        data = scipy.io.loadmat(str(path))
    except (OSError, ValueError, NotImplementedError, TypeError) as e:
        raise DataError(path, f"cannot read .mat file ({type(e).__name__}: {e})") from None
    missing = [k for k in keys if k not in data]
    if missing:
        raise DataError(path, f"missing key(s) {', '.join(missing)} (expected {', '.join(keys)})")
    return {k: np.asarray(data[k]) for k in keys}


def _load_points(path: Path) -> np.ndarray:
    try:
        loaded: Any = trimesh.load(path, process=False)
    except Exception as e:  # trimesh raises many different types for bad files
        raise DataError(path, f"cannot read point cloud ({type(e).__name__}: {e})") from None
    pts = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise DataError(path, "no 3-D points in this file")
    return pts


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise DataError(path, "cameras file is missing")
    try:
        with np.load(path) as npz:
            return {k: np.asarray(npz[k]) for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise DataError(path, f"cannot read npz ({e})") from None


def load_scale_mat(path: str | Path) -> np.ndarray:
    """``scale_mat_0`` (4x4, unit sphere -> DTU world) of a NeuS ``cameras_sphere.npz``."""
    path = Path(path)
    cams = _load_npz(path)
    if "scale_mat_0" not in cams:
        raise DataError(path, "missing key 'scale_mat_0' (expected a NeuS cameras_sphere.npz)")
    mat = cams["scale_mat_0"].astype(np.float64)
    if mat.shape != (4, 4) or not np.isfinite(mat).all():
        raise DataError(path, f"scale_mat_0 must be a finite 4x4 matrix, got shape {mat.shape}")
    return mat


def apply_affine(mat: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(mat @ [p, 1])[:3]`` for every row ``p`` of ``points``."""
    return points @ mat[:3, :3].T + mat[:3, 3]


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, density: float, chunk: int = 4_000_000) -> np.ndarray:
    """The official sampling: a regular grid in each triangle, then the vertices.

    For a triangle with edges ``v1 = b - a``, ``v2 = c - a`` of lengths ``l1, l2`` and doubled area ``A2``, the
    spacing is ``t = density * sqrt(l1 l2 / A2)``, ``n_k = floor(l_k / t)`` and the points are
    ``a + s1 v1 + s2 v2`` with ``s_k = (i_k + 0.5) / n_k``, ``i_k = 0..n_k``, kept where ``s1 + s2 < 1``.
    Deterministic; degenerate triangles contribute only their vertices. ``chunk`` bounds the grid candidates held
    at once.
    """
    tri = vertices[faces]
    v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    l1, l2 = np.linalg.norm(v1, axis=-1), np.linalg.norm(v2, axis=-1)
    area2 = np.linalg.norm(np.cross(v1, v2), axis=-1)
    ok = area2 > 0
    tri, v1, v2, l1, l2, area2 = tri[ok], v1[ok], v2[ok], l1[ok], l2[ok], area2[ok]
    thr = density * np.sqrt(l1 * l2 / area2)
    n1, n2 = np.floor(l1 / thr).astype(np.int64), np.floor(l2 / thr).astype(np.int64)
    out = [vertices.astype(np.float64)]
    cum = np.cumsum((n1 + 1) * (n2 + 1))
    s = 0
    while s < len(tri):
        stop = max(s + 1, int(np.searchsorted(cum, (cum[s - 1] if s else 0) + chunk, side="right")))
        e, s = slice(s, stop), stop
        c1, c2 = n1[e], n2[e]
        counts = (c1 + 1) * (c2 + 1)
        t = np.repeat(np.arange(len(counts)), counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        i, j = k // (c2[t] + 1), k % (c2[t] + 1)
        s1 = (i + 0.5) / np.maximum(c1[t], 1e-7)
        s2 = (j + 0.5) / np.maximum(c2[t], 1e-7)
        inside = s1 + s2 < 1
        t, s1, s2 = t[inside], s1[inside, None], s2[inside, None]
        out.append(tri[e][t, 0] + s1 * v1[e][t] + s2 * v2[e][t])
    return np.concatenate(out, axis=0)


def downsample(points: np.ndarray, radius: float, seed: int) -> np.ndarray:
    """Shuffle (``seed``), then keep a point unless an earlier kept point lies within ``radius``.

    The greedy thinning of the official script (``reducePts_haa``: visit the points in order, keep a point not yet
    removed and remove its neighbours); the shuffle fixes the order. Computed exactly in vectorised rounds over the
    pairs within ``radius``: a point is removed once an earlier neighbour is kept, and kept once all its earlier
    neighbours are removed.
    """
    pts = np.asarray(points, dtype=np.float64).copy()
    np.random.default_rng(seed).shuffle(pts, axis=0)
    if len(pts) == 0 or radius <= 0:
        return pts
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    a, b = pairs.min(axis=1), pairs.max(axis=1)  # (earlier neighbour, point)
    state = np.zeros(len(pts), dtype=np.int8)  # 0 undecided, 1 kept, 2 removed
    while True:
        state[b[state[a] == 1]] = 2
        live = (state[b] == 0) & (state[a] != 2)  # pairs that can still decide something
        a, b = a[live], b[live]
        blocked = np.zeros(len(pts), dtype=bool)
        blocked[b] = True  # an earlier neighbour is still undecided
        newly = (state == 0) & ~blocked
        if not newly.any():
            break
        state[newly] = 1
    return pts[state == 1]


def _read_mask(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            a = np.asarray(im)
    except OSError as e:
        raise DataError(path, f"cannot read mask image ({e})") from None
    return (a[..., 0] if a.ndim == 3 else a) > 0


def mask_cull_inputs(dataset_dir: str | Path) -> tuple[Path, Path]:
    """``(cameras npz, mask dir)`` of a NeuS dataset folder, for ``dtu_chamfer(mask_cull=...)``."""
    from anisdf.data.dataparsers.neus import NPZ_NAMES, find_npz

    root = Path(dataset_dir)
    npz = find_npz(root)
    if npz is None:
        raise DataError(root / NPZ_NAMES[0], "file is missing (--mask-cull needs a NeuS dataset folder)")
    if not (root / "mask").is_dir():
        raise DataError(root / "mask", "mask folder is missing (--mask-cull needs a NeuS dataset folder)")
    return npz, root / "mask"


def cull_by_masks(vertices: np.ndarray, faces: np.ndarray, cameras_npz: str | Path, mask_dir: str | Path
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Mask culling of NeuS / 2DGS ``cull_scan``, on a mesh in the cameras' world frame (``world_mat_i`` maps it
    to pixels of ``mask_dir``'s i-th mask, sorted by name).

    A vertex is removed if in some view it projects inside the image but outside the foreground mask dilated by a
    disk of ``24 * W / 1600`` px, or if it is inside no image. Faces are kept when all three vertices are.
    """
    from anisdf.data.dataparsers._common import list_images

    cameras_npz, mask_dir = Path(cameras_npz), Path(mask_dir)
    cams = _load_npz(cameras_npz)
    masks = list_images(mask_dir)
    if not masks:
        raise DataError(mask_dir, "no mask images found (expected mask/*.png)")
    hom = np.concatenate([vertices, np.ones((len(vertices), 1))], axis=1)
    keep = np.ones(len(vertices), dtype=bool)
    seen = np.zeros(len(vertices), dtype=bool)
    radius = None
    for i, mpath in enumerate(masks):
        key = f"world_mat_{i}"
        if key not in cams:
            raise DataError(cameras_npz, f"missing key '{key}' for mask {mpath.name} ({len(masks)} masks)")
        P = cams[key].astype(np.float64)[:3, :4]
        mask = _read_mask(mpath)
        h, w = mask.shape
        radius = max(1, round(MASK_DILATION_PX_AT_1600 * w / 1600))
        yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
        mask = scipy.ndimage.binary_dilation(mask, structure=xx**2 + yy**2 <= radius**2)
        uvw = hom @ P.T
        front = uvw[:, 2] > 0
        z = np.where(front, uvw[:, 2], 1.0)
        u, v = np.round(uvw[:, 0] / z), np.round(uvw[:, 1] / z)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
        on_mask = np.zeros(len(vertices), dtype=bool)
        on_mask[inside] = mask[vi, ui]
        keep &= ~inside | on_mask
        seen |= inside
    keep &= seen
    face_keep = keep[faces].all(axis=1)
    remap = np.cumsum(keep) - 1
    info = {"mask_cull": str(mask_dir), "mask_cull_cameras": str(cameras_npz), "mask_cull_views": len(masks),
            "mask_dilation_px": radius, "mask_cull_removed_vertices": int((~keep).sum()),
            "mask_cull_removed_faces": int((~face_keep).sum())}
    return vertices[keep], remap[faces[face_keep]], info


DENSITY_MM = 0.2
"""Sampling and thinning distance of the official evaluation, in mm."""
MAX_DIST_MM = 20.0
"""Distances of this many mm or more are outliers in the official evaluation."""


def dtu_chamfer(mesh_path: str | Path, dtu_root: str | Path, scan: int, scale_mat: str | Path | None = None,
                mask_cull: tuple[str | Path, str | Path] | None = None, density: float = DENSITY_MM,
                max_dist: float = MAX_DIST_MM, seed: int = 0, thin_stl: bool = True) -> dict[str, Any]:
    """Official DTU accuracy, completeness and Chamfer distance (mm) of a mesh for DTU scan ``scan``.

    ``scale_mat``: a NeuS ``cameras_sphere.npz`` whose ``scale_mat_0`` maps the mesh to DTU world (mm);
    ``mask_cull``: ``(cameras npz, mask dir)`` for mask culling before scoring; ``thin_stl=False`` scores against
    every STL point as the Python port does (the MATLAB original thins them). Returns the three numbers and the
    protocol (options, point counts, outliers).
    """
    if density <= 0 or max_dist <= 0:
        raise AnisdfError(f"dtu-chamfer: density ({density}) and max_dist ({max_dist}) must be positive")
    paths = dtu_paths(dtu_root, scan)
    _require(paths["obs_mask"], "observation mask")
    _require(paths["plane"], "ground plane")
    _require(paths["stl"], "STL reference point cloud")
    mesh = load_mesh(mesh_path)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    protocol: dict[str, Any] = {"scan": scan, "mesh": str(mesh_path), "dtu_root": str(dtu_root),
                                "density_mm": density, "max_dist_mm": max_dist, "outliers": "discarded (>= max_dist)",
                                "patch_mm": PATCH_MM, "seed": seed, "thin_stl": thin_stl,
                                "scale_mat": None if scale_mat is None else str(scale_mat), "mask_cull": None}
    if scale_mat is not None:
        vertices = apply_affine(load_scale_mat(scale_mat), vertices)
    if mask_cull is not None:
        vertices, faces, info = cull_by_masks(vertices, faces, *mask_cull)
        protocol.update(info)
        if len(faces) == 0:
            raise AnisdfError(f"dtu-chamfer: mask culling with {mask_cull[1]} removed the whole mesh (is the mesh in "
                              "DTU world coordinates? use --scale-mat for a mesh in the unit sphere)")

    sampled = sample_mesh(vertices, faces, density)
    data = downsample(sampled, density, seed)

    obs = _loadmat(paths["obs_mask"], ("ObsMask", "BB", "Res"))
    # BB in float32 as eval.py reads it
    obs_mask, bb, res = obs["ObsMask"].astype(bool), obs["BB"].astype(np.float32), float(obs["Res"].squeeze())
    if obs_mask.ndim != 3 or bb.shape != (2, 3):
        raise DataError(paths["obs_mask"], f"ObsMask must be 3-D and BB 2x3, got {obs_mask.shape} and {bb.shape}")
    bb = bb.astype(np.float64)
    inbound = np.all((data >= bb[:1] - PATCH_MM) & (data < bb[1:] + 2 * PATCH_MM), axis=1)
    data_in = data[inbound]
    grid = np.around((data_in - bb[:1]) / res).astype(np.int64)
    grid_ok = np.all((grid >= 0) & (grid < np.array(obs_mask.shape)), axis=1)
    in_obs = np.zeros(len(data_in), dtype=bool)
    in_obs[grid_ok] = obs_mask[grid[grid_ok, 0], grid[grid_ok, 1], grid[grid_ok, 2]]
    data_obs = data_in[in_obs]
    if len(data_obs) == 0:
        raise AnisdfError(f"dtu-chamfer: no point of {mesh_path} lies inside {paths['obs_mask']} (is the mesh in "
                          "DTU world coordinates, mm? use --scale-mat for a mesh in the unit sphere)")

    stl_all = _load_points(paths["stl"])
    stl = downsample(stl_all, density, seed) if thin_stl else stl_all
    plane = _loadmat(paths["plane"], ("P",))["P"].astype(np.float64).reshape(-1)
    if plane.shape != (4,):
        raise DataError(paths["plane"], f"P must have 4 coefficients, got {plane.size}")
    stl_above = stl[stl @ plane[:3] + plane[3] > 0]
    if len(stl_above) == 0:
        raise DataError(paths["plane"], "no STL point lies above this plane")

    d2s, _ = cKDTree(stl).query(data_obs, k=1, distance_upper_bound=max_dist, workers=-1)
    s2d, _ = cKDTree(data_in).query(stl_above, k=1, distance_upper_bound=max_dist, workers=-1)
    d2s_in, s2d_in = d2s[d2s < max_dist], s2d[s2d < max_dist]
    if len(d2s_in) == 0 or len(s2d_in) == 0:
        raise AnisdfError(f"dtu-chamfer: every distance is an outlier (>= {max_dist} mm); the mesh is not near the "
                          f"reference of scan {scan} (wrong scan or frame?)")
    accuracy, completeness = float(d2s_in.mean()), float(s2d_in.mean())
    protocol.update({
        "n_mesh_vertices": len(vertices), "n_mesh_faces": len(faces), "n_data_sampled": len(sampled),
        "n_data_points": len(data),
        "n_data_in_bbox": len(data_in), "n_data_in_obs_mask": len(data_obs), "n_stl_points": len(stl_all),
        "n_stl_downsampled": len(stl), "n_stl_above_plane": len(stl_above),
        "n_accuracy_outliers": int(len(d2s) - len(d2s_in)), "n_completeness_outliers": int(len(s2d) - len(s2d_in)),
    })
    return {"accuracy": accuracy, "completeness": completeness, "chamfer": (accuracy + completeness) / 2, **protocol}
