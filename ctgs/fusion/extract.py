"""The TSDF's zero level as a triangle mesh (scikit-image's marching cubes), then 2DGS's cleanup.

Marching cubes runs on one region of CHUNK^3 blocks at a time, a dense copy of its voxels plus the first voxel layer
of the regions after it, so every cube between two voxels is in exactly one region. A cube is used only where all
eight of its voxels were observed (weight > 0), as Open3D does. The regions' meshes share the vertices on their faces:
those come out bit-identical from both sides and are welded. Vertex colours are the voxels' colours interpolated
like the positions. Faces come out counter-clockwise seen from the free side (the TSDF grows outwards).

Cleanup (`keep_largest`): 2DGS's post-processing, the pieces (connected components) with at least as many triangles
as the N-th largest and at least MIN_PIECE_TRIANGLES (the largest piece in any case); triangles whose vertices welded together are dropped, and
vertices no triangle uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from ctgs.fusion.volume import BLOCK, TSDFVolume, local_offsets

CHUNK = 8  # blocks per region side: 64 voxels, a 65^3 dense copy (about 6 MB with colours)
MIN_PIECE_TRIANGLES = 50  # 2DGS: pieces smaller than this go whatever the count kept


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float32, model frame
    faces: np.ndarray  # [F, 3] int64, counter-clockwise seen from outside
    colors: np.ndarray  # [V, 3] float32 in [0, 1] (sRGB, as the renders)

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def num_faces(self) -> int:
        return len(self.faces)


def _block_keys(blocks: np.ndarray, lo: np.ndarray, span: np.ndarray) -> np.ndarray:
    """[M] int64 keys of block coordinates [M, 3] inside the box lo .. lo + span (exclusive)."""
    c = blocks - lo
    return (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]


def marching_cubes_blocks(volume: TSDFVolume, progress: Callable[[int, int], None] | None = None,
                          chunk: int = CHUNK) -> Mesh:
    """The zero level of `volume` as a welded mesh in world coordinates (model frame), `chunk`^3 blocks at a time."""
    blocks = volume.blocks.cpu().numpy()
    if not len(blocks):
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
    lo = blocks.min(0)
    span = blocks.max(0) - lo + 1
    keys = _block_keys(blocks, lo, span)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    tsdf = volume.tsdf.cpu().numpy()
    observed = (volume.weight > 0).cpu().numpy()
    colour = volume.colour.cpu().numpy()
    local = local_offsets("cpu").numpy()
    regions = np.unique(np.floor_divide(blocks, chunk), axis=0)
    side = chunk * BLOCK + 1
    offsets = np.stack(np.meshgrid(*[np.arange(chunk + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    verts, faces, cols, count = [], [], [], 0
    for i, region in enumerate(regions):
        if progress is not None:
            progress(i, len(regions))
        cand = region * chunk + offsets  # [(CHUNK+1)^3, 3] blocks that may hold this region's voxels
        inside = ((cand - lo) >= 0).all(1) & ((cand - lo) < span).all(1)
        cand = cand[inside]
        ck = _block_keys(cand, lo, span)
        pos = np.clip(np.searchsorted(sorted_keys, ck), 0, len(sorted_keys) - 1)
        hit = sorted_keys[pos] == ck
        ids = order[pos[hit]]
        if not len(ids):
            continue
        vox = (blocks[ids] - region * chunk)[:, None, :] * BLOCK + local[None]  # [b, 512, 3] region voxel coords
        keep = (vox < side).all(-1)
        v = vox[keep]
        dense_t = np.ones((side, side, side), np.float32)
        dense_o = np.zeros((side, side, side), bool)
        dense_c = np.zeros((side, side, side, 3), np.float32)
        dense_t[v[:, 0], v[:, 1], v[:, 2]] = tsdf[ids][keep]
        dense_o[v[:, 0], v[:, 1], v[:, 2]] = observed[ids][keep]
        dense_c[v[:, 0], v[:, 1], v[:, 2]] = colour[ids][keep]
        cube = dense_o[:-1, :-1, :-1].copy()
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    cube &= dense_o[dx:side - 1 + dx, dy:side - 1 + dy, dz:side - 1 + dz]
        if not cube.any():
            continue
        t_obs = dense_t[dense_o]
        if t_obs.min() > 0 or t_obs.max() < 0:
            continue
        mask = np.zeros_like(dense_o)
        mask[1:, 1:, 1:] = cube  # scikit-image reads a cube's mask at its far corner
        try:
            vr, fr, _, _ = marching_cubes(dense_t, 0.0, mask=mask)
        except RuntimeError:  # "No surface found at the given iso value": nothing crosses zero in the used cubes
            continue
        cols.append(_trilinear(dense_c, vr))
        verts.append(vr.astype(np.float64) + region * chunk * BLOCK)
        faces.append(fr.astype(np.int64) + count)
        count += len(vr)
    if progress is not None:
        progress(len(regions), len(regions))
    if not verts:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
    g = np.concatenate(verts)
    f = np.concatenate(faces)
    c = np.concatenate(cols)
    g, f, c = _weld_region_faces(g, f, c, chunk * BLOCK)
    world = volume.domain.to_world(torch.from_numpy(g)).numpy().astype(np.float32)
    return Mesh(world, f, np.clip(c, 0, 1).astype(np.float32))


def _trilinear(grid: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """grid [D, D, D, C] sampled at pts [V, 3] (grid coordinates) trilinearly."""
    d = grid.shape[0]
    p0 = np.clip(np.floor(pts).astype(np.int64), 0, d - 2)
    f = np.clip(pts - p0, 0, 1)
    out = np.zeros((len(pts), grid.shape[3]), np.float32)
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1 - f[:, 2]
                out += (wx * wy * wz)[:, None] * grid[p0[:, 0] + dx, p0[:, 1] + dy, p0[:, 2] + dz]
    return out


def _weld_region_faces(g: np.ndarray, f: np.ndarray, c: np.ndarray, period: int) -> tuple[np.ndarray, np.ndarray,
                                                                                             np.ndarray]:
    """Merge vertices with identical grid coordinates that lie on a region's face (a multiple of `period` voxels: where
    two regions' meshes meet; inside a region scikit-image already shares them)."""
    on_face = (np.mod(g, period) == 0).any(1)
    idx = np.nonzero(on_face)[0]
    remap = np.arange(len(g))
    if len(idx):
        _, first, inverse = np.unique(g[idx], axis=0, return_index=True, return_inverse=True)
        remap[idx] = idx[first][inverse.reshape(-1)]
    f = remap[f]
    used = np.zeros(len(g), bool)
    used[f.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return g[used], new_index[f], c[used]


def keep_largest(mesh: Mesh, pieces: int) -> tuple[Mesh, int]:
    """(mesh with its degenerate triangles dropped and only the pieces 2DGS keeps, number of pieces dropped).
    pieces <= 0 keeps every piece (degenerate triangles still go)."""
    f = mesh.faces
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    n = mesh.num_vertices
    if not len(f):
        return Mesh(mesh.vertices[:0], f, mesh.colors[:0]), 0
    dropped = 0
    if pieces > 0:
        rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
        cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
        graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
        count, label = connected_components(graph, directed=False)
        face_label = label[f[:, 0]]
        sizes = np.bincount(face_label, minlength=count)
        nonempty = np.sort(sizes[sizes > 0])
        # (the largest piece stays whatever its size)
        threshold = min(max(nonempty[-min(pieces, len(nonempty))], MIN_PIECE_TRIANGLES), nonempty[-1])
        keep = sizes[face_label] >= threshold
        dropped = int((nonempty < threshold).sum())
        f = f[keep]
    used = np.zeros(n, bool)
    used[f.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    return Mesh(mesh.vertices[used], new_index[f], mesh.colors[used]), dropped
