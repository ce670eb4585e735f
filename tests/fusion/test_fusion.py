"""TSDF fusion, marching cubes and cleanup (ctgs.fusion) on exact depth maps of a sphere: no renderer, no training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ctgs.errors import UserError
from ctgs.fusion.domain import Domain, camera_sphere, contract, uncontract
from ctgs.fusion.extract import Mesh, keep_largest, marching_cubes_blocks
from ctgs.fusion.pipeline import estimate_bytes, too_big
from ctgs.fusion.volume import BLOCK, TSDFVolume, coarser_blocks, depth_blocks, grown_blocks
from ctgs.render.camera import Camera

RADIUS = 1.0
CAM_DISTANCE = 3.0


def _look_at(centre: np.ndarray, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    f = -centre / np.linalg.norm(centre)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    vm = np.eye(4)
    vm[:3, :3] = np.stack([r, np.cross(f, r), f])
    vm[:3, 3] = -vm[:3, :3] @ centre
    return torch.tensor(vm, dtype=torch.float32)


def _cameras() -> list[Camera]:
    """Cameras all around the sphere (three rings and the poles), 48x36 pixels, looking at its centre."""
    centres = [CAM_DISTANCE * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
               for e in (-0.9, 0.0, 0.9) for a in np.linspace(0, 2 * math.pi, 6, endpoint=False)]
    views = [_look_at(c) for c in centres]
    views += [_look_at(np.array([0, 0, s * CAM_DISTANCE]), up=(0.0, 1.0, 0.0)) for s in (1, -1)]
    return [Camera(fx=40.0, fy=40.0, cx=24.0, cy=18.0, width=48, height=36, viewmat=v, near=0.01) for v in views]


def _sphere_maps(cam: Camera, offset=(0.0, 0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """(camera-space depth [H, W], 0 off the sphere; colour [H, W, 3] = (p / RADIUS + 1) / 2) of the sphere at offset."""
    h, w = cam.height, cam.width
    u = (torch.arange(w) + 0.5 - cam.cx) / cam.fx
    v = (torch.arange(h) + 0.5 - cam.cy) / cam.fy
    d = torch.stack([u[None].expand(h, w), v[:, None].expand(h, w), torch.ones(h, w)], -1) @ cam.R  # world, z = 1
    o = cam.center - torch.tensor(offset, dtype=torch.float32)
    b = (d * o).sum(-1)
    a = (d * d).sum(-1)
    disc = b * b - a * ((o * o).sum() - RADIUS**2)
    s = (-b - torch.sqrt(disc.clamp_min(0))) / a  # along d with unit z: the depth itself
    hit = disc > 0
    colour = ((o + s[..., None] * d) / RADIUS + 1) / 2
    return torch.where(hit, s, torch.zeros_like(s)), colour.clamp(0, 1)


def _volume(dom: Domain, cams: list[Camera], trunc: float) -> TSDFVolume:
    """The sphere fused from `cams` into the blocks its depth maps name."""
    maps = [_sphere_maps(cam) for cam in cams]
    vol = TSDFVolume(dom, grown_blocks(torch.cat([depth_blocks(dom, d, cam) for (d, _), cam in zip(maps, cams)]), dom),
                     trunc)
    for (depth, colour), cam in zip(maps, cams):
        vol.integrate(depth, colour, cam)
    return vol


CHUNK = 2  # blocks per marching-cubes region: 16 voxels, so the sphere crosses several regions' seams


def _fused(contracted: bool, voxel: float = 0.06) -> tuple[Mesh, TSDFVolume]:
    dom = Domain(centre=(0.0, 0.0, 0.0), radius=CAM_DISTANCE, voxel=voxel, contract=contracted, half=2 * CAM_DISTANCE)
    vol = _volume(dom, _cameras(), 5 * voxel)
    return marching_cubes_blocks(vol, chunk=CHUNK), vol


@pytest.fixture(scope="module", params=[False, True], ids=["box", "contracted"])
def sphere(request):
    return _fused(request.param)


def test_the_sphere_comes_back_within_a_quarter_voxel_on_average(sphere):
    mesh, vol = sphere
    r = np.linalg.norm(mesh.vertices, axis=1)
    # (TSDF fusion of projective distances leaves a convex surface about 0.2 voxel outside at a 5-voxel truncation)
    assert np.abs(r - RADIUS).mean() < 0.25 * vol.domain.voxel, np.abs(r - RADIUS).mean()
    assert np.abs(r - RADIUS).max() < vol.domain.voxel
    # the colours are the views' colours at the surface, interpolated like the positions
    assert np.abs(mesh.colors - (mesh.vertices / RADIUS + 1) / 2).mean() < 0.01


def test_faces_point_outwards_and_the_regions_are_welded_into_one_closed_surface(sphere):
    mesh, vol = sphere
    v, f = mesh.vertices, mesh.faces
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert ((normal * v[f].mean(1)).sum(1) > 0).all()
    assert 2 * RADIUS / vol.domain.voxel > CHUNK * BLOCK  # the sphere spans several regions: their seams are crossed
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert (uses == 2).all(), np.bincount(uses)  # every edge between exactly two triangles: closed, no seam
    n = len(v)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    assert connected_components(graph, directed=False)[0] == 1


def test_unobserved_voxels_make_no_surface():
    """Views from x > 1 only: they see the sphere down to x = -0.8 (each sees a cap 70.5 degrees around its direction);
    the far side was never seen (weight 0) and stays open rather than closed by guesses."""
    cams = [c for c in _cameras() if float(c.center[0]) > 1.0]
    dom = Domain(centre=(0.0, 0.0, 0.0), radius=CAM_DISTANCE, voxel=0.05, contract=False, half=6.0)
    mesh = marching_cubes_blocks(_volume(dom, cams, 0.25), chunk=CHUNK)
    assert len(mesh.faces) and mesh.vertices[:, 0].max() > 0.99 and mesh.vertices[:, 0].min() > -0.9


def test_contraction_round_trip_and_domain_coordinates():
    p = torch.randn(1000, 3, dtype=torch.float64) * 20
    assert torch.allclose(uncontract(contract(p)), p, rtol=1e-9, atol=1e-9)
    assert (contract(p).norm(dim=-1) < 2).all()
    for contracted in (False, True):
        dom = Domain(centre=(1.0, -2.0, 0.5), radius=3.0, voxel=0.01, contract=contracted, half=10.0)
        x = torch.randn(100, 3, dtype=torch.float64) * 5
        assert torch.allclose(dom.to_world(dom.to_grid(x)), x, atol=1e-9)


def test_camera_sphere_is_the_point_the_cameras_look_at():
    target = np.array([0.5, -1.0, 2.0])
    centres = np.array([[4 * math.cos(a), 4 * math.sin(a), 0.3 * math.sin(3 * a)] for a in np.linspace(0, 6, 20)])
    centres += target
    centre, radius = camera_sphere(centres, target - centres)
    assert np.allclose(centre, target, atol=1e-2) and abs(radius - 4.0) < 0.05
    # cameras looking the same way (forward-facing): the points' median instead of a point at infinity
    pts = np.random.default_rng(0).normal(size=(500, 3)) + [0, 0, 10]
    centre, _ = camera_sphere(centres, np.repeat([[0.0, 0.0, 1.0]], len(centres), 0), pts)
    assert np.allclose(centre, np.median(pts, axis=0))


def _grid_mesh(n: int, origin) -> Mesh:
    """An n x n grid of squares (2 n^2 triangles) in the plane z = 0 at origin."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    v = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], 1) + origin
    k = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]).ravel()
    f = np.concatenate([np.stack([k, k + n + 1, k + 1], 1), np.stack([k + 1, k + n + 1, k + n + 2], 1)])
    return Mesh(v.astype(np.float32), f, np.zeros((len(v), 3), np.float32))


def test_keep_largest_drops_small_pieces_and_degenerate_triangles():
    big, small, tiny = _grid_mesh(10, (0, 0, 0)), _grid_mesh(6, (50, 0, 0)), _grid_mesh(2, (90, 0, 0))
    parts = [big, small, tiny]
    starts = np.cumsum([0] + [p.num_vertices for p in parts])[:-1]
    mesh = Mesh(np.concatenate([p.vertices for p in parts]),
                np.concatenate([p.faces + s for p, s in zip(parts, starts)] + [np.array([[0, 0, 1]])]),
                np.concatenate([p.colors for p in parts]))
    kept, dropped = keep_largest(mesh, 1)  # 200 triangles kept; 72 and 8 go
    assert kept.num_faces == 200 and dropped == 2 and kept.num_vertices == 121
    kept, dropped = keep_largest(mesh, 50)  # the 50 largest, but none under 50 triangles (2DGS)
    assert kept.num_faces == 272 and dropped == 1
    kept, dropped = keep_largest(mesh, 0)
    assert kept.num_faces == 280 and dropped == 0  # (the degenerate triangle goes in any case)
    lone = _grid_mesh(2, (0, 0, 0))
    assert keep_largest(lone, 50)[0].num_faces == 8  # the largest piece stays whatever its size


def test_blocks_hold_the_surface_and_its_band_only():
    """The blocks are those of the depth maps' points and their neighbours: a shell around the sphere, no more."""
    voxel = 0.02
    dom = Domain(centre=(0.0, 0.0, 0.0), radius=CAM_DISTANCE, voxel=voxel, contract=False, half=6.0)
    blocks = grown_blocks(torch.cat([depth_blocks(dom, _sphere_maps(c)[0], c) for c in _cameras()]), dom)
    side = BLOCK * voxel
    r = ((blocks.double() + 0.5) * side).norm(dim=-1)
    assert (r > RADIUS - 2.6 * side).all() and (r < RADIUS + 2.6 * side).all()  # within the band
    shell = 4 * math.pi * RADIUS**2 * 3 * side / side**3  # a 3-block thick shell's blocks
    assert shell < len(blocks) < 2 * shell
    # at a twice coarser voxel the same surface takes about a quarter of the blocks
    assert 0.15 * len(blocks) < len(coarser_blocks(blocks, dom, 2 * voxel)) < 0.4 * len(blocks)


def test_a_volume_that_does_not_fit_names_the_voxel_size_that_does():
    dom = Domain(centre=(0.0, 0.0, 0.0), radius=CAM_DISTANCE, voxel=0.02, contract=False, half=6.0)
    cams = _cameras()
    blocks = grown_blocks(torch.cat([depth_blocks(dom, _sphere_maps(c)[0], c) for c in cams]), dom)
    need = estimate_bytes(len(blocks))
    limit = need // 10
    msg = str(too_big(dom, blocks, need, limit, True, "RUN"))
    assert msg.startswith("RUN: the TSDF volume at voxel size 0.02 (") and f"--max-memory allows {limit / 1e9:.3g} GB" in msg
    fit = float(msg.split("pass --voxel-size ")[1].split()[0])
    assert 0.02 < fit < 0.1
    # that voxel size fits: the sphere's blocks surveyed afresh at it take no more than the limit
    dom_fit = Domain(centre=(0.0, 0.0, 0.0), radius=CAM_DISTANCE, voxel=fit, contract=False, half=6.0)
    fitted = grown_blocks(torch.cat([depth_blocks(dom_fit, _sphere_maps(c)[0], c) for c in cams]), dom_fit)
    assert estimate_bytes(len(fitted)) <= limit
    assert "GB are free" in str(too_big(dom, blocks, need, limit, False, "RUN"))
