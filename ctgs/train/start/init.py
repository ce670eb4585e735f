"""Initial surfels from SfM points (3DGS/2DGS initialisation)."""

from __future__ import annotations

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.model.surfels import SurfelModel
from ctgs.render.geometry import frames_from_normals, rotmat_to_quat
from ctgs.train.components.shell import shell_points
from ctgs.train.start.fill import fill_points

SH_C0 = 0.28209479177387814


def farthest_point_subsample(points: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices [k] of a greedy farthest-point subset of points [P, 3].

    Exact greedy FPS without touching every point at every pick: a pick at squared distance d (the largest of all
    the points' distances to the chosen set) can only lower the distances of points within sqrt(d) of it, which a
    KD-tree finds; the ball shrinks as the set grows, so a pick costs about P / i point updates instead of P (86k
    SfM points -> 10k: under a second, where updating every point took minutes on a busy 2-core machine)."""
    from scipy.spatial import cKDTree  # scipy: scikit-learn's own dependency

    p = np.ascontiguousarray(points, dtype=np.float32)
    n = p.shape[0]
    if k >= n:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    tree = cKDTree(p)
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = int(rng.integers(n))
    dist = ((p - p[chosen[0]]) ** 2).sum(1)  # [P] squared distance to the chosen set (float32)
    for i in range(1, k):
        c = int(np.argmax(dist))
        chosen[i] = c
        near = np.asarray(tree.query_ball_point(p[c], r=float(np.sqrt(dist[c])) * (1 + 1e-6)), dtype=np.int64)
        dist[near] = np.minimum(dist[near], ((p[near] - p[c]) ** 2).sum(1))
    return chosen


def knn_scale(points: np.ndarray) -> np.ndarray:
    """Per point sqrt(mean squared distance to its 3 nearest neighbours) [P], world units (3DGS)."""
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.neighbors import NearestNeighbors

    k = min(4, len(points))
    nn = NearestNeighbors(n_neighbors=k).fit(points)
    d, _ = nn.kneighbors(points)
    d2 = (d[:, 1:] ** 2).mean(1) if k > 1 else np.ones(len(points))
    return np.sqrt(np.maximum(d2, 1e-14))


def pca_normals(points: np.ndarray, k: int = 16) -> np.ndarray:
    """Per point the unit normal [P, 3] of the plane through its k nearest neighbours (itself included):
    the eigenvector of the smallest eigenvalue of their covariance. Sign arbitrary (surfels are two-sided)."""
    # scikit-learn takes about a second to import: loaded only where it is used
    from sklearn.neighbors import NearestNeighbors

    pts = np.asarray(points, dtype=np.float64)
    k = min(k, len(pts))
    if k < 3:
        return np.tile(np.array([0.0, 0.0, 1.0]), (len(pts), 1))
    _, idx = NearestNeighbors(n_neighbors=k).fit(pts).kneighbors(pts)
    nb = pts[idx] - pts[idx].mean(1, keepdims=True)  # [P, k, 3]
    _, vecs = np.linalg.eigh(np.einsum("pki,pkj->pij", nb, nb))
    return vecs[:, :, 0]


def init_model(points: np.ndarray, colors: np.ndarray, *, max_points: int, opacity: float, max_sh_degree: int,
               random_rotation: bool, texture_mode: str, fixed_res: int, seed: int,
               normals: bool = False, extra_points: np.ndarray | None = None,
               extra_colors: np.ndarray | None = None) -> SurfelModel:
    """A SurfelModel with one surfel per (subsampled) SfM point. Textures empty (allocated at texture start),
    except the fixed_texture baseline whose fixed_res x fixed_res grids exist from the start.
    normals: orient each surfel in the PCA plane of its 16 nearest points (random angle in the plane);
    else random_rotation (uniform random) or identity.
    extra_points / extra_colors: appended after the cap (ctgs.train.components.shell's far shell), never subsampled."""
    if points is None or len(points) == 0:
        raise UserError("scene has no SfM points: run `ctgs sfm` first or check sparse/0/points3D.bin")
    if max_points and len(points) > max_points:
        idx = farthest_point_subsample(points, max_points, seed)
        points, colors = points[idx], colors[idx]
    if extra_points is not None and len(extra_points):
        points = np.concatenate([np.asarray(points, np.float64), np.asarray(extra_points, np.float64)])
        colors = np.concatenate([np.asarray(colors, np.float64), np.asarray(extra_colors, np.float64)])
    pts = torch.from_numpy(np.asarray(points, dtype=np.float32))
    cols = torch.from_numpy(np.asarray(colors, dtype=np.float32))
    n = pts.shape[0]
    scale = torch.from_numpy(knn_scale(np.asarray(points, dtype=np.float64)).astype(np.float32))
    gen = torch.Generator().manual_seed(seed)
    if normals:
        nrm = torch.from_numpy(pca_normals(points)).float()
        quats = rotmat_to_quat(frames_from_normals(nrm, gen))
    elif random_rotation:
        quats = torch.randn(n, 4, generator=gen)
        quats = quats / quats.norm(dim=1, keepdim=True)
    else:
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1
    k = (max_sh_degree + 1) ** 2
    sh = torch.zeros(n, k, 3)
    sh[:, 0] = (cols - 0.5) / SH_C0
    o = torch.full((n,), float(opacity))
    if texture_mode == "fixed":
        tex_res = torch.full((n, 2), fixed_res, dtype=torch.int32)
    else:
        tex_res = torch.zeros(n, 2, dtype=torch.int32)
    sizes = tex_res[:, 0].long() * tex_res[:, 1].long()
    leaf = lambda t: t.contiguous().requires_grad_(True)  # noqa: E731
    return SurfelModel(
        means=leaf(pts), log_scales=leaf(torch.log(scale)[:, None].repeat(1, 2)), quats=leaf(quats),
        opacity_logits=leaf(torch.log(o / (1 - o))), sh=leaf(sh),
        textures_raw=leaf(torch.zeros(int(sizes.sum()), 3)),
        k_min=torch.ones(n), t2p_exp=torch.zeros(n, dtype=torch.int32), tex_res=tex_res,
        tex_offset=torch.cumsum(sizes, 0) - sizes, sh_degree=0, texture_mode=texture_mode,
    )


def scene_model(scene, cfg, max_points: int, texture_mode: str) -> SurfelModel:
    """init_model for a scene and a config: its SfM points capped at max_points, then the extra initial points, the
    far shell's (init_shell) and the fill's (init_fill)."""
    extra = shell_points(scene.points, scene.train, cfg.init_shell) if cfg.init_shell > 0 else (None, None)
    if cfg.init_fill:
        fill = fill_points(scene.points, scene.train)
        extra = tuple(f if e is None else np.concatenate([e, f]) for e, f in zip(extra, fill))
    return init_model(scene.points, scene.point_colors, max_points=max_points, opacity=cfg.init_opacity,
                      max_sh_degree=cfg.max_sh_degree, random_rotation=cfg.random_rotation, normals=cfg.init_normals,
                      texture_mode=texture_mode, fixed_res=cfg.fixed_texture_res, seed=cfg.seed,
                      extra_points=extra[0], extra_colors=extra[1])
