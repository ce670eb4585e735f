"""A block-sparse TSDF: blocks of 8^3 voxels where the depth maps put a surface, fused from depth maps in torch.

Only the blocks holding a depth map's point, and the blocks around them, are stored (as Open3D's scalable volume
does): a surface's neighbourhood, not the space between surfaces. Each voxel keeps a truncated signed distance in
[-1, 1] (float32), its weight (the views that updated it, float32) and a colour (3 x float16): 14 bytes.

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

BLOCK = 8  # voxels per block side
BLOCK_VOXELS = BLOCK**3
BYTES_PER_VOXEL = 4 + 4 + 6  # tsdf float32, weight float32, colour 3 x float16
# Per block besides its voxels: coordinates (3 x int64), bounding sphere (4 x float32).
BYTES_PER_BLOCK = BLOCK_VOXELS * BYTES_PER_VOXEL + 3 * 8 + 4 * 4
# Fusion works on this many blocks of one view at a time (its temporaries: ~60 bytes a voxel, ~60 MB).
FUSE_BLOCKS = 256


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


def depth_blocks(domain: Domain, depth: torch.Tensor, camera) -> torch.Tensor:
    """[K] int64 keys (`block_keys`) of the blocks holding the surface points of a depth map [H, W] (camera-space z at
    the pixel centres, 0 where none), those inside the domain."""
    h, w = depth.shape
    v, u = torch.nonzero(depth > 0, as_tuple=True)
    z = depth[v, u].float()
    vm = camera.viewmat.to(depth.device, torch.float32)
    pc = torch.stack([(u.float() + 0.5 - camera.cx) / camera.fx * z, (v.float() + 0.5 - camera.cy) / camera.fy * z, z], 1)
    g = domain.to_grid((pc - vm[:3, 3]) @ vm[:3, :3])
    ok = (g.abs() <= domain.limit).all(1) & torch.isfinite(g).all(1)
    return torch.unique(block_keys(torch.floor(g[ok] / BLOCK).long(), domain))


def block_keys(blocks: torch.Tensor, domain: Domain) -> torch.Tensor:
    return _pack(blocks, math.ceil(domain.limit / BLOCK) + 1)


def grown_blocks(keys: torch.Tensor, domain: Domain) -> torch.Tensor:
    """[B, 3] sorted block coordinates of the blocks `keys` name and their 26 neighbours (the truncation band on both
    sides of a surface: up to a block away from its points)."""
    limit = math.ceil(domain.limit / BLOCK) + 1
    core = _unpack(torch.unique(keys), limit)
    ring = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=keys.device)] * 3, indexing="ij"), -1)
    grown = (core[:, None, :] + ring.reshape(1, -1, 3)).reshape(-1, 3)
    return _unpack(torch.unique(_pack(grown[(grown.abs() < limit).all(-1)], limit)), limit)


def coarser_blocks(blocks: torch.Tensor, domain: Domain, voxel: float) -> torch.Tensor:
    """[B', 3] the blocks at voxel size `voxel` (coarser than the domain's) that cover `blocks` [B, 3] (each block's
    eight corner voxels mapped: grid coordinates scale with the voxel size in both kinds of domain)."""
    corners = torch.tensor([[i, j, k] for i in (0, BLOCK - 1) for j in (0, BLOCK - 1) for k in (0, BLOCK - 1)],
                           device=blocks.device)
    g = (blocks[:, None, :] * BLOCK + corners[None]).double() * (domain.voxel / voxel)
    limit = math.ceil(domain.limit * domain.voxel / voxel / BLOCK) + 2
    return _unpack(torch.unique(_pack(torch.floor(g / BLOCK).long().reshape(-1, 3), limit)), limit)


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
            u, v, z = u[sel], v[sel], z[sel]
            if self.domain.contract:  # the truncation stretches with the voxels
                g = (self.blocks[idx[sel // BLOCK_VOXELS]] * BLOCK + self.local[sel % BLOCK_VOXELS]).float()
                trunc = self.trunc / self.domain.voxel * self.domain.stretch(g)
            else:
                trunc = torch.full_like(z, self.trunc)
            pix = torch.floor(v).long().clamp_(0, h - 1) * w + torch.floor(u).long().clamp_(0, w - 1)
            d = flat_depth[pix]
            rgb_at = flat_rgb[pix]
            # Near the surface the depth between pixel centres matters: there it is interpolated (_refine). Farther
            # off it cannot change the update (sdf clamps to 1 in front, and is skipped behind), so the pixel's serves.
            band = torch.nonzero((d > 0) & ((d - z).abs() < 2 * trunc)).squeeze(1)
            if len(band):
                d[band], rgb_at[band] = _refine(flat_depth, flat_rgb, w, h, u[band], v[band], trunc[band],
                                                d[band], rgb_at[band])
            sdf = d - z
            keep = torch.nonzero((d > 0) & (sdf > -trunc)).squeeze(1)
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


def _refine(depth: torch.Tensor, rgb: torch.Tensor, w: int, h: int, u: torch.Tensor, v: torch.Tensor,
            agree: torch.Tensor, d: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(depth [M], colour [M, 3]) of a flat depth [H*W] and colour [H*W, 3] image at continuous image coordinates
    (u, v) [M] (on the image): bilinear between the four nearest pixel centres where all four have a depth and
    agree within `agree` [M] (a surface seen across them), else d and c, the pixel's (u, v) falls in (a depth edge:
    never a depth between two surfaces)."""
    x, y = (u - 0.5).clamp(0, w - 1), (v - 0.5).clamp(0, h - 1)
    x0, y0 = torch.floor(x).long().clamp(0, max(w - 2, 0)), torch.floor(y).long().clamp(0, max(h - 2, 0))
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    x1, y1 = (x0 + 1).clamp_max(w - 1), (y0 + 1).clamp_max(h - 1)
    taps = torch.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], 1)  # [M, 4]
    wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    dt = depth[taps]
    lo, hi = dt.aminmax(dim=1)
    smooth = (lo > 0) & (hi - lo < agree)
    return (torch.where(smooth, (dt * wts).sum(1), d),
            torch.where(smooth[:, None], (rgb[taps] * wts[..., None]).sum(1), c))
