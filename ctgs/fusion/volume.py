"""A block-sparse TSDF: blocks of 8^3 voxels near the model's surfels, fused from depth maps in torch.

Only blocks near a surfel are stored (the surfels are where surfaces can be; Open3D's scalable volume allocates them
from the depth maps instead, which needs a pass over every view first). Each voxel keeps a truncated signed
distance in [-1, 1] (float32), its weight (the views that updated it, float32) and a colour (3 x float16): 14 bytes.

Fusion is Open3D's and 2DGS's (Curless and Levoy's running average): for each view, every voxel in its frustum whose
pixel has a depth d, with sdf = d - z (z: the voxel's depth in that camera, so positive in front of the surface) and
sdf > -trunc, takes tsdf <- (w tsdf + min(1, sdf / trunc)) / (w + 1), the pixel's colour likewise, w <- w + 1. The
pixel is the one the voxel centre falls in (no interpolation across depth edges). Voxels behind every surface by
more than trunc are never touched: their weight stays 0 and marching cubes skips them.
"""

from __future__ import annotations

import math

import torch

from ctgs.fusion.domain import Domain
from ctgs.render.geometry import quat_to_rotmat

BLOCK = 8  # voxels per block side
BLOCK_VOXELS = BLOCK**3
BYTES_PER_VOXEL = 4 + 4 + 6  # tsdf float32, weight float32, colour 3 x float16
# Per block besides its voxels: coordinates (3 x int64), bounding sphere (4 x float32).
BYTES_PER_BLOCK = BLOCK_VOXELS * BYTES_PER_VOXEL + 3 * 8 + 4 * 4
# Fusion works on this many blocks of one view at a time (its temporaries: ~60 bytes a voxel, ~60 MB).
FUSE_BLOCKS = 2048
# Surfels are sampled at most this many points per tangent axis (a surfel far larger than the voxels, a floater
# across the scene, is allocated along a coarser grid of its points).
MAX_SAMPLES_PER_AXIS = 256
# Points sampled at once while allocating (bounds the temporaries to ~200 MB).
SAMPLE_BATCH = 1 << 22
SURFEL_SIGMAS = 3.0  # a surfel reaches 3 standard deviations (the renderer's cutoff, rho <= 9)


def local_offsets(device) -> torch.Tensor:
    """[512, 3] int64 voxel offsets inside a block, x slowest (the order of a block's voxels)."""
    r = torch.arange(BLOCK, device=device)
    return torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)


def _pack(coords: torch.Tensor, limit: int) -> torch.Tensor:
    """[M, 3] int64 block coordinates in [-limit, limit] -> [M] int64 keys (sortable, unique per block)."""
    span = 2 * limit + 1
    c = coords + limit
    return (c[:, 0] * span + c[:, 1]) * span + c[:, 2]


def _unpack(keys: torch.Tensor, limit: int) -> torch.Tensor:
    span = 2 * limit + 1
    z = keys % span
    y = (keys // span) % span
    x = keys // (span * span)
    return torch.stack([x, y, z], -1) - limit


def surfel_points(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, spacing: torch.Tensor):
    """Yield [M, 3] world points covering every surfel's 3-sigma ellipse on a grid no coarser than spacing [N] (each
    surfel's own, world units; a surfel narrower than it is its centre alone), SAMPLE_BATCH points at most at a time."""
    extent = 2 * SURFEL_SIGMAS * scales  # [N, 2] the ellipse's box, world units
    counts = torch.where(extent < spacing[:, None], torch.ones_like(extent),
                         torch.ceil(extent / spacing[:, None]) + 1).clamp_max(MAX_SAMPLES_PER_AXIS).long()
    per = counts[:, 0] * counts[:, 1]
    ends = torch.cumsum(per, 0)
    start = 0
    while start < len(per):
        # surfels [start, stop) hold at most SAMPLE_BATCH points (at least one surfel)
        base = int(ends[start - 1]) if start else 0
        stop = max(start + 1, int(torch.searchsorted(ends, base + SAMPLE_BATCH, right=True)))
        sl = slice(start, stop)
        n = per[sl]
        owner = torch.repeat_interleave(torch.arange(stop - start, device=means.device), n)
        k = torch.arange(int(n.sum()), device=means.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        cu, cv = counts[sl, 0][owner], counts[sl, 1][owner]
        a = torch.where(cu > 1, (k % cu).to(means.dtype) / (cu - 1).clamp_min(1) - 0.5, torch.zeros_like(k, dtype=means.dtype))
        b = torch.where(cv > 1, (k // cu).to(means.dtype) / (cv - 1).clamp_min(1) - 0.5, torch.zeros_like(k, dtype=means.dtype))
        rot = quat_to_rotmat(quats[sl])  # [n, 3, 3]
        ext = extent[sl][owner]
        yield (means[sl][owner] + rot[owner, :, 0] * (a * ext[:, 0])[:, None]
               + rot[owner, :, 1] * (b * ext[:, 1])[:, None])
        start = stop


def allocate_blocks(domain: Domain, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """[B, 3] int64 sorted block coordinates of the blocks within one block of any surfel's 3-sigma ellipse (the
    surfels given: the caller drops the transparent ones), inside the domain."""
    with torch.no_grad():
        g_centre = domain.to_grid(means)
        # Sample at half a block in the grid: world spacing = 4 voxels stretched as little as a voxel does there.
        spacing = 0.5 * BLOCK * domain.tangential_stretch(g_centre)
        limit = math.ceil(domain.limit / BLOCK) + 1
        keys = []
        for pts in surfel_points(means, quats, scales, spacing):
            g = domain.to_grid(pts)
            ok = (g.abs() <= domain.limit).all(-1) & torch.isfinite(g).all(-1)
            keys.append(torch.unique(_pack(torch.floor(g[ok] / BLOCK).long(), limit)))
        if not keys:
            return torch.zeros(0, 3, dtype=torch.long, device=means.device)
        core = _unpack(torch.unique(torch.cat(keys)), limit)
        ring = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=means.device)] * 3, indexing="ij"), -1)
        grown = (core[:, None, :] + ring.reshape(1, -1, 3)).reshape(-1, 3)
        inside = (grown.abs() < limit).all(-1)
        return _unpack(torch.unique(_pack(grown[inside], limit)), limit)


class TSDFVolume:
    """The voxels of `blocks` [B, 3] (block coordinates: voxels blocks * 8 + 0..7 on each axis) in `domain`, on the
    blocks' device. trunc: the truncation distance in world units (inside the cameras' sphere in contracted space,
    stretched with the voxels beyond it)."""

    def __init__(self, domain: Domain, blocks: torch.Tensor, trunc: float):
        self.domain = domain
        self.trunc = float(trunc)
        self.blocks = blocks
        dev = blocks.device
        n = len(blocks)
        self.tsdf = torch.ones(n, BLOCK_VOXELS, dtype=torch.float32, device=dev)
        self.weight = torch.zeros(n, BLOCK_VOXELS, dtype=torch.float32, device=dev)
        self.colour = torch.zeros(n, BLOCK_VOXELS, 3, dtype=torch.float16, device=dev)
        self.local = local_offsets(dev)
        # A sphere around each block's voxel centres (world): which blocks a view can see. Corners of the block's
        # cube, a hair grown (in contracted space the cube's image bulges a little between its corners).
        corners = torch.tensor([[i, j, k] for i in (0, BLOCK - 1) for j in (0, BLOCK - 1) for k in (0, BLOCK - 1)],
                               device=dev)
        sphere_c, sphere_r = [], []
        step = 1 << 16
        for s in range(0, n, step):
            w = domain.to_world((blocks[s:s + step, None, :] * BLOCK + corners[None]).float())  # [b, 8, 3]
            c = w.mean(1)
            sphere_c.append(c)
            sphere_r.append((w - c[:, None]).norm(dim=-1).amax(1) * 1.05 + 1e-6)
        self.sphere_c = torch.cat(sphere_c) if n else torch.zeros(0, 3, device=dev)
        self.sphere_r = torch.cat(sphere_r) if n else torch.zeros(0, device=dev)

    @property
    def num_blocks(self) -> int:
        return len(self.blocks)

    def visible_blocks(self, camera, depth_max: float) -> torch.Tensor:
        """[b] indices of the blocks that may hold a voxel in the camera's frustum, not behind depth_max + trunc (in
        a bounded domain; contracted space stretches trunc, so there only the frustum counts)."""
        vm = camera.viewmat.to(self.sphere_c.device, torch.float32)
        c = self.sphere_c @ vm[:3, :3].T + vm[:3, 3]
        r = self.sphere_r
        x, y, z = c.unbind(-1)
        ok = z + r > camera.near
        if not self.domain.contract:
            ok &= z - r < depth_max + self.trunc
        # The four side planes of the frustum (through the camera centre), signed distance >= -r.
        for a, b, sx, sy in ((camera.cx / camera.fx, 1.0, 1, 0), ((camera.width - camera.cx) / camera.fx, -1.0, 1, 0),
                             (camera.cy / camera.fy, 1.0, 0, 1), ((camera.height - camera.cy) / camera.fy, -1.0, 0, 1)):
            lateral = x if sx else y
            ok &= (b * lateral + a * z) / math.hypot(1.0, a) > -r
        return torch.nonzero(ok).squeeze(1)

    def _camera_points(self, idx: torch.Tensor, rot: torch.Tensor, tr: torch.Tensor) -> torch.Tensor:
        """[b, 512, 3] camera-space positions of the voxels of blocks idx."""
        if not self.domain.contract:  # a block is its first voxel plus fixed offsets: no per-voxel matrix product
            first = self.domain.to_world((self.blocks[idx] * BLOCK).float())
            return (first @ rot.T + tr)[:, None, :] + ((self.local.float() * self.domain.voxel) @ rot.T)[None]
        g = (self.blocks[idx, None, :] * BLOCK + self.local[None]).float()
        return self.domain.to_world(g) @ rot.T + tr

    def integrate(self, depth: torch.Tensor, rgb: torch.Tensor, camera) -> int:
        """Fuse one view: depth [H, W] (camera-space z, 0 where the pixel has none), rgb [H, W, 3] in [0, 1].
        Returns how many voxels it updated."""
        valid = depth > 0
        if not bool(valid.any()):
            return 0
        depth_max = float(depth[valid].max())
        dev = self.tsdf.device
        vm = camera.viewmat.to(dev, torch.float32)
        rot, tr = vm[:3, :3], vm[:3, 3]
        h, w = depth.shape
        flat_depth = depth.reshape(-1).to(dev, torch.float32)
        flat_rgb = rgb.reshape(-1, 3).to(dev, torch.float32)
        tsdf, weight, colour = self.tsdf.view(-1), self.weight.view(-1), self.colour.view(-1, 3)
        updated = 0
        blocks = self.visible_blocks(camera, depth_max)
        for s in range(0, len(blocks), FUSE_BLOCKS):
            idx = blocks[s:s + FUSE_BLOCKS]
            pc = self._camera_points(idx, rot, tr).reshape(-1, 3)
            z = pc[:, 2]
            zs = z.clamp_min(camera.near)
            u = pc[:, 0] / zs * camera.fx + camera.cx  # continuous image coordinates
            v = pc[:, 1] / zs * camera.fy + camera.cy
            sel = torch.nonzero((z > camera.near) & (u >= 0) & (u < w) & (v >= 0) & (v < h)).squeeze(1)
            if self.domain.contract:  # the truncation stretches with the voxels
                g = (self.blocks[idx[sel // BLOCK_VOXELS]] * BLOCK + self.local[sel % BLOCK_VOXELS]).float()
                trunc = self.trunc / self.domain.voxel * self.domain.stretch(g)
            else:
                trunc = torch.full_like(z[sel], self.trunc)
            d, rgb_at = _sample(flat_depth, flat_rgb, w, h, u[sel], v[sel], trunc)
            sdf = d - z[sel]
            keep = (d > 0) & (sdf > -trunc)
            sel, rgb_at, sdf, trunc = sel[keep], rgb_at[keep], sdf[keep], trunc[keep]
            if not len(sel):
                continue
            vox = idx[sel // BLOCK_VOXELS] * BLOCK_VOXELS + sel % BLOCK_VOXELS  # into the flat voxel arrays
            wt = weight[vox]
            new_w = wt + 1
            tsdf[vox] = (tsdf[vox] * wt + torch.clamp(sdf / trunc, max=1.0)) / new_w
            colour[vox] = ((colour[vox].float() * wt[:, None] + rgb_at) / new_w[:, None]).to(colour.dtype)
            weight[vox] = new_w
            updated += len(vox)
        return updated


def _sample(depth: torch.Tensor, rgb: torch.Tensor, w: int, h: int, u: torch.Tensor, v: torch.Tensor,
            agree: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth [M], colour [M, 3]) of a flat depth [H*W] and colour [H*W, 3] image at continuous image coordinates
    (u, v) [M] (on the image): bilinear between the four nearest pixel centres where all four have a depth and
    agree within `agree` [M] (a surface seen across them), else the pixel (u, v) falls in (a depth edge: never a
    depth between two surfaces)."""
    near = torch.floor(v).long().clamp(0, h - 1) * w + torch.floor(u).long().clamp(0, w - 1)
    x, y = (u - 0.5).clamp(0, w - 1), (v - 0.5).clamp(0, h - 1)
    x0, y0 = torch.floor(x).long().clamp(0, max(w - 2, 0)), torch.floor(y).long().clamp(0, max(h - 2, 0))
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    x1, y1 = (x0 + 1).clamp_max(w - 1), (y0 + 1).clamp_max(h - 1)
    taps = torch.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], 1)  # [M, 4]
    wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    dt = depth[taps]
    smooth = (dt.amin(1) > 0) & (dt.amax(1) - dt.amin(1) < agree)
    d = torch.where(smooth, (dt * wts).sum(1), depth[near])
    c = torch.where(smooth[:, None], (rgb[taps] * wts[..., None]).sum(1), rgb[near])
    return d, c
