"""Where the TSDF's voxels lie: a box around the cameras, or contracted space for unbounded captures.

Grid coordinates g are in voxels, voxel centres at integers. In a bounded domain (`--bound cameras`) they are
world coordinates, x = centre + voxel * g, inside the box of the camera centres grown by the depth truncation
(every fused depth lies within it of some camera). In contracted space (`--bound contract`, 2DGS's unbounded
meshing and Mip-NeRF 360's contraction) the world is first normalised by the cameras' sphere (centre, radius) and
contracted, y = p for |p| <= 1 and (2 - 1/|p|) p / |p| beyond, p = (x - centre) / radius, so that all of space fits in
the ball |y| < 2; g = y / step with step = voxel / radius. Voxels are `voxel` world units inside the cameras' sphere
and grow with distance beyond it, as far as the horizon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

# Contracted radii are kept below 2 - CONTRACT_EDGE (the horizon, where uncontracting diverges).
CONTRACT_EDGE = 1e-3
# The cameras' focus point is the least-squares point nearest every optical axis; RIDGE pulls it towards the mean
# camera centre along directions the axes do not pin down (cameras looking the same way).
RIDGE = 1e-3
# Below this smallest eigenvalue (per camera) of the focus point's system the axes are nearly parallel (a
# forward-facing capture): the SfM points' median is the centre instead.
PARALLEL_AXES = 0.05


def contract(p: torch.Tensor) -> torch.Tensor:
    """[..., 3] normalised points -> contracted points, |y| < 2."""
    n = p.norm(dim=-1, keepdim=True)
    return torch.where(n <= 1, p, (2 - 1 / n.clamp_min(1)) * p / n.clamp_min(1))


def uncontract(y: torch.Tensor) -> torch.Tensor:
    """Inverse of `contract` for |y| < 2 (|y| is clamped to 2 - CONTRACT_EDGE)."""
    m = y.norm(dim=-1, keepdim=True)
    mc = m.clamp(1, 2 - CONTRACT_EDGE)
    return torch.where(m <= 1, y, y / (m.clamp_min(1) * (2 - mc)))


@dataclass(frozen=True)
class Domain:
    centre: tuple[float, float, float]  # model frame, world units
    radius: float  # the cameras' distance from their focus point (median), world units
    voxel: float  # world units (inside the cameras' sphere in contracted space)
    contract: bool
    half: float  # bounded: half the box's side around centre, world units (contracted: unused)

    @property
    def step(self) -> float:
        """Grid units per voxel: world units (bounded), contracted units (contracted)."""
        return self.voxel / self.radius if self.contract else self.voxel

    @property
    def limit(self) -> int:
        """Grid coordinates lie in [-limit, limit] on each axis."""
        return math.ceil((2.0 if self.contract else self.half) / self.step)

    def _centre(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.centre, dtype=like.dtype, device=like.device)

    def to_grid(self, x: torch.Tensor) -> torch.Tensor:
        """[..., 3] world (model frame) -> grid coordinates (voxel centres at integers)."""
        p = x - self._centre(x)
        if self.contract:
            return contract(p / self.radius) / self.step
        return p / self.step

    def to_world(self, g: torch.Tensor) -> torch.Tensor:
        """[..., 3] grid coordinates -> world (model frame)."""
        if self.contract:
            return self._centre(g) + self.radius * uncontract(g * self.step)
        return self._centre(g) + g * self.step

    def stretch(self, g: torch.Tensor) -> torch.Tensor:
        """[...] world units per voxel along the radial direction at grid coordinates g [..., 3] (the most a voxel
        stretches there; `voxel` everywhere in a bounded domain)."""
        if not self.contract:
            return torch.full(g.shape[:-1], self.voxel, dtype=g.dtype, device=g.device)
        m = (g * self.step).norm(dim=-1).clamp(1, 2 - CONTRACT_EDGE)
        return self.voxel / (2 - m) ** 2

    def tangential_stretch(self, g: torch.Tensor) -> torch.Tensor:
        """[...] world units per voxel across the radial direction (the least a voxel stretches there)."""
        if not self.contract:
            return torch.full(g.shape[:-1], self.voxel, dtype=g.dtype, device=g.device)
        m = (g * self.step).norm(dim=-1).clamp(1, 2 - CONTRACT_EDGE)
        return self.voxel / ((2 - m) * m)


def camera_sphere(centres: np.ndarray, forwards: np.ndarray, points: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of the cameras: the point nearest all optical axes (least squares, 2DGS's focus point) and
    the cameras' median distance from it. centres, forwards [C, 3] (forwards: unit viewing directions). Cameras whose
    axes are nearly parallel (a forward-facing capture) take the median of the SfM points `points` [P, 3] instead."""
    c = np.asarray(centres, np.float64)
    d = np.asarray(forwards, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [C, 3, 3] removes each axis' direction
    a = proj.sum(0)
    b = np.einsum("cij,cj->i", proj, c)
    n = len(c)
    if np.linalg.eigvalsh(a / n)[0] < PARALLEL_AXES and points is not None and len(points):
        centre = np.median(np.asarray(points, np.float64), axis=0)
    else:
        centre = np.linalg.solve(a + RIDGE * n * np.eye(3), b + RIDGE * n * c.mean(0))
    radius = float(np.median(np.linalg.norm(c - centre, axis=1)))
    return centre, max(radius, 1e-9)
