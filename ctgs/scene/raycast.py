"""Exact numpy ray caster for scenes made of textured rectangles (the demo scene's renderer).

Independent of the project's Gaussian renderer on purpose: the demo scene is ground truth.
A rectangle is centre c, orthonormal tangents u, v (normal n = u x v) and half extents (a, b) in world
units. Its texture (if any) covers the rectangle exactly: texture column grows along +u, texture row
grows along -v (so an upright photo stays upright when v points "up"). Colours are sampled with
bilinear filtering from a texture prefiltered to about the finest on-screen texel density, and each
pixel averages ss x ss stratified sub-pixel rays (antialiasing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rect:
    id: str
    kind: str  # "photo" | "flat" | "smooth"
    center: np.ndarray  # [3] world units
    u: np.ndarray  # [3] unit tangent (texture columns)
    v: np.ndarray  # [3] unit tangent (texture rows run along -v)
    half: tuple[float, float]  # half extents along u, v, world units
    color: np.ndarray  # [3] base colour in [0,1] ("flat"), or start colour ("smooth")
    color2: np.ndarray | None = None  # end colour of the "smooth" gradient (along +u, then +v)
    texture: np.ndarray | None = None  # [Ht, Wt, 3] float32 in [0,1] ("photo")
    texture_name: str = ""

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    @property
    def area(self) -> float:
        return 4.0 * self.half[0] * self.half[1]

    def shade(self, lx: np.ndarray, ly: np.ndarray) -> np.ndarray:
        """Colour [M, 3] at local coordinates lx, ly [M] (world units, origin at the centre)."""
        s = (lx / self.half[0] + 1.0) * 0.5  # [0, 1] along u
        t = (ly / self.half[1] + 1.0) * 0.5  # [0, 1] along v
        if self.kind == "photo":
            return bilinear(self.texture, s, 1.0 - t)
        if self.kind == "smooth":
            w = np.clip(0.7 * s + 0.3 * t, 0.0, 1.0)[:, None]
            return (1.0 - w) * self.color[None] + w * self.color2[None]
        return np.broadcast_to(self.color[None], (len(lx), 3))


def bilinear(tex: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Sample tex [Ht, Wt, 3] at normalised coordinates s (columns), t (rows) in [0,1]; clamp to edge."""
    h, w = tex.shape[:2]
    flat = tex.reshape(-1, tex.shape[2])  # [Ht*Wt, 3]: one flat gather per tap is cheaper than 2-D indexing
    x = np.clip(s * w - 0.5, 0.0, w - 1.0)  # texel centres at integer + 0.5 in [0, w]
    y = np.clip(t * h - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(y.astype(np.int64), max(h - 2, 0))
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    top = flat[y0 * w + x0] * (1 - fx) + flat[y0 * w + x1] * fx
    bottom = flat[y1 * w + x0] * (1 - fx) + flat[y1 * w + x1] * fx
    return top * (1 - fy) + bottom * fy


def camera_rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int, ss: int) -> np.ndarray:
    """Camera-space ray directions [H, W, ss*ss, 3] (z = 1) through stratified sub-pixel positions."""
    offsets = (np.arange(ss) + 0.5) / ss  # pixel (i, j) spans [i, i+1) x [j, j+1)
    xs = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1)  # [W*ss]
    ys = (np.arange(height)[:, None] + offsets[None, :]).reshape(-1)  # [H*ss]
    dx = (xs - cx) / fx
    dy = (ys - cy) / fy
    d = np.empty((height * ss, width * ss, 3))
    d[:, :, 0] = dx[None, :]
    d[:, :, 1] = dy[:, None]
    d[:, :, 2] = 1.0
    # [H, ss, W, ss, 3] -> [H, W, ss*ss, 3]
    return d.reshape(height, ss, width, ss, 3).transpose(0, 2, 1, 3, 4).reshape(height, width, ss * ss, 3)


def render(rects: list[Rect], viewmat: np.ndarray, fx: float, fy: float, cx: float, cy: float,
           width: int, height: int, ss: int = 3, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Render float32 [H, W, 3] in [0,1]; viewmat [4, 4] world -> camera (COLMAP cam_from_world)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    origin = -R.T @ t  # [3] camera centre, world
    cam = camera_rays(fx, fy, cx, cy, width, height, ss).reshape(-1, 3)  # [M, 3] camera space
    # World directions R^T d, one component at a time: a [M,3]@[3,3] BLAS call is slow on a loaded
    # machine, and separate contiguous float32 components make the per-surface arithmetic cheap
    # (~1e-7 relative error in hit points, far below a texel).
    cx_, cy_ = cam[:, 0].astype(np.float32), cam[:, 1].astype(np.float32)
    dx, dy, dz = (np.float32(R[0, k]) * cx_ + np.float32(R[1, k]) * cy_ + np.float32(R[2, k]) for k in range(3))
    m = len(dx)
    best_t = np.full(m, np.inf, dtype=np.float32)
    best_id = np.full(m, -1, dtype=np.int64)
    best_lx = np.zeros(m, dtype=np.float32)
    best_ly = np.zeros(m, dtype=np.float32)
    for k, rect in enumerate(rects):
        n, u, v = (a.astype(np.float32) for a in (rect.normal, rect.u, rect.v))
        oc = (origin - rect.center).astype(np.float32)  # [3]
        denom = dx * n[0] + dy * n[1] + dz * n[2]  # [M]
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = -(oc @ n) / denom
        # hit point local coordinates: (o + t d - c) . u = oc . u + t (d . u)
        lx = (oc @ u) + tt * (dx * u[0] + dy * u[1] + dz * u[2])
        ly = (oc @ v) + tt * (dx * v[0] + dy * v[1] + dz * v[2])
        hit = (tt > 1e-6) & (tt < best_t) & (np.abs(lx) <= rect.half[0]) & (np.abs(ly) <= rect.half[1])
        best_t = np.where(hit, tt, best_t)
        best_id[hit] = k
        best_lx = np.where(hit, lx, best_lx)
        best_ly = np.where(hit, ly, best_ly)
    color = np.empty((m, 3))
    color[:] = np.asarray(background, dtype=np.float64)[None]
    for k, rect in enumerate(rects):
        idx = np.nonzero(best_id == k)[0]
        if len(idx):
            color[idx] = rect.shade(best_lx[idx].astype(np.float64), best_ly[idx].astype(np.float64))
    image = color.reshape(height, width, ss * ss, 3).mean(axis=2)
    return np.clip(image, 0.0, 1.0).astype(np.float32)
