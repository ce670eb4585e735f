"""A trained model and its cameras -> a coloured triangle mesh: plan the volume, fuse every view, extract, clean.

Depth, where the pixel is at least half covered (alpha >= MIN_ALPHA): by default the renderer's median depth, the hit
of the surfel that takes the transmittance below 0.5 (2DGS's `depth_ratio 1`); `depth="mean"` fuses the expected depth
depth / alpha instead (2DGS's `depth_ratio 0`). A textured model draws a surface with few large surfels, and what the
first of them leaves uncovered reaches surfels far behind or in front: on the demo scene the blended depths along a
content-aware model's ray spread a median 1.2 m, which pulls the mean a median 16 cm off the surface while the median
lies 0.9 cm from it (benchmarks/surface_diagnosis.py). Colour: the render's rgb / alpha (the surfel colour without the
black background), so the mesh carries the textures.

Voxel size by default: PIXELS_PER_VOXEL pixels at the distance the cameras look from (their sphere's radius over
their median focal length), what the photos resolve there; coarser where the volume would not fit in memory.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.fusion.domain import Domain, camera_sphere
from ctgs.fusion.extract import Mesh, keep_largest, marching_cubes_blocks
from ctgs.fusion.volume import BLOCK_VOXELS, BYTES_PER_BLOCK, TSDFVolume, coarser_blocks, depth_blocks, grown_blocks
from ctgs.render import render

MIN_ALPHA = 0.5  # pixels less covered than this give no depth (what lies there is mostly transparent)
# The default voxel spans this many pixels of a typical view at the cameras' distance from their focus point: finer
# voxels add vertices the photos cannot place (a depth map samples a surface once a pixel), and the fusion's time
# grows as the voxels' count times the views.
PIXELS_PER_VOXEL = 2.0
TRUNC_VOXELS = 5.0  # the default truncation distance, voxels (2DGS's sdf_trunc = 5 x voxel_size)
DEPTH_TRUNC_RADII = 2.0  # the default depth truncation in cameras' radii (2DGS's depth_trunc)
# What marching cubes and the cleanup need besides the volume, per block (measured: a surface crosses a block in
# about 130 triangles; vertices, faces, colours and the components' graph).
MESH_BYTES_PER_BLOCK = 12 * 1024
# A plan needing more than this fraction of the free memory does not fit (the renders and Python need the rest).
MEMORY_FRACTION = 0.8
FIT_TRIES = 8  # voxel sizes tried when looking for one that fits
# The views' depth and colour maps (10 bytes a pixel) are kept from the survey for the fusion when they take at most
# this fraction of the memory allowed; else every view is rendered again.
MAPS_FRACTION = 0.25
MERGE_VIEWS = 16  # the survey merges its views' block keys every this many views


@dataclass
class MeshOptions:
    bound: str = "cameras"  # "cameras": a box from the cameras; "contract": all of space, contracted
    resolution: int | None = None  # voxels across the scene extent (2 x the cameras' radius); None: `pixel_voxel`
    voxel_size: float | None = None  # world units; overrides resolution
    depth_trunc: float | None = None  # world units; default DEPTH_TRUNC_RADII x radius (bounded), none (contracted)
    sdf_trunc: float | None = None  # world units; default TRUNC_VOXELS voxels
    pieces: int = 50  # keep the largest pieces (2DGS's num_cluster); 0 keeps all
    max_memory: float | None = None  # bytes the volume and mesh may take; default MEMORY_FRACTION of the free memory
    depth: str = "median"  # the depth fused: "median" (where T falls below 0.5) or "mean" (depth / alpha)

    @property
    def voxel_given(self) -> bool:
        """Whether the user chose the voxel size (an error instead of a coarser voxel when it does not fit)."""
        return self.voxel_size is not None or self.resolution is not None


@dataclass
class MeshPlan:
    domain: Domain
    blocks: torch.Tensor  # [B, 3] int64
    trunc: float  # world units
    depth_trunc: float  # world units (inf: none)
    bytes: int  # the volume, mesh and kept maps' estimated memory
    limit: int  # bytes allowed
    maps: list | None  # (depth, colour) of every view, when kept from the survey
    depth: str = "median"  # the depth fused (MeshOptions.depth)
    coarsened_from: float | None = None  # the default voxel size, when the plan's is coarser to fit in memory

    @property
    def voxels(self) -> int:
        return len(self.blocks) * BLOCK_VOXELS


def free_memory(device: torch.device) -> int:
    """Bytes free for the volume on `device`: the GPU's free memory, or the machine's available memory (Linux
    MemAvailable; the physical memory elsewhere)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: no limit


def estimate_bytes(blocks: int) -> int:
    return blocks * (BYTES_PER_BLOCK + MESH_BYTES_PER_BLOCK)


def _camera_arrays(cameras) -> tuple[np.ndarray, np.ndarray]:
    vms = np.stack([c.viewmat.detach().cpu().double().numpy() for c in cameras])  # [C, 4, 4]
    rot, t = vms[:, :3, :3], vms[:, :3, 3]
    centres = -np.einsum("cji,cj->ci", rot, t)
    forwards = rot[:, 2, :]  # camera +z in world
    return centres, forwards


def pixel_voxel(cameras, radius: float) -> float:
    """PIXELS_PER_VOXEL pixels at distance `radius` (world units) in the cameras' median focal length."""
    focal = float(np.median([0.5 * (c.fx + c.fy) for c in cameras]))
    return PIXELS_PER_VOXEL * radius / max(focal, 1e-9)


def make_domain(cameras, points: np.ndarray | None, opts: MeshOptions) -> tuple[Domain, float]:
    """(the domain, the depth truncation) the options ask for, around the cameras' sphere."""
    centres, forwards = _camera_arrays(cameras)
    centre, radius = camera_sphere(centres, forwards, points)
    contract = opts.bound == "contract"
    if opts.depth_trunc is not None:
        depth_trunc = float(opts.depth_trunc)
    else:
        depth_trunc = math.inf if contract else DEPTH_TRUNC_RADII * radius
    if opts.voxel_size:
        voxel = float(opts.voxel_size)
    elif opts.resolution:
        voxel = 2.0 * radius / opts.resolution
    else:
        voxel = pixel_voxel(cameras, radius)
    half = float(np.abs(centres - centre).max() + depth_trunc) if not contract else 0.0
    return Domain(centre=tuple(float(x) for x in centre), radius=radius, voxel=voxel, contract=contract,
                  half=half), depth_trunc


def view_maps(inputs, camera, backend: str, sh_degree: int, depth_trunc: float,
              which: str = "median") -> tuple[torch.Tensor, torch.Tensor]:
    """(depth [H, W]: camera-space depth, the median (`which="median"`) or the expected one ("mean"), 0 where alpha <
    MIN_ALPHA or beyond depth_trunc; colour [H, W, 3] in [0, 1], the render without its black background) of one
    view."""
    out = render(inputs, camera, backend=backend, sh_degree=sh_degree)
    alpha = out.alpha
    covered = alpha >= MIN_ALPHA
    if which == "median" and out.median_depth is not None:
        depth = torch.where(covered, out.median_depth, torch.zeros_like(alpha))
    else:
        depth = torch.where(covered, out.depth / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
    depth = torch.where(depth <= depth_trunc, depth, torch.zeros_like(depth))
    colour = (out.rgb / alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
    return depth, colour


def _views(model, cameras, backend: str, depth_trunc: float, which: str):
    """(camera, depth, colour) of every camera, rendered."""
    device = model.means.device
    with torch.no_grad():
        inputs = model.render_inputs()
        for cam in cameras:
            cam = cam.to(device, inputs.means.dtype)
            yield (cam, *view_maps(inputs, cam, backend, model.sh_degree, depth_trunc, which))


def plan_volume(model, cameras, points: np.ndarray | None, opts: MeshOptions, backend: str = "auto",
                what: str = "the model", progress: Callable[[int, int], None] | None = None) -> MeshPlan:
    """Render every view once (the survey): the blocks where its depth puts a surface, and its maps when they fit.
    UserError naming the voxel size that fits when the volume would not fit in memory."""
    domain, depth_trunc = make_domain(cameras, points, opts)
    if not domain.contract and not math.isfinite(depth_trunc):
        raise UserError("--bound cameras needs a finite --depth-trunc (the box around the cameras reaches that far); "
                        "pass one, or --bound contract for all of space")
    device = model.means.device
    limit = int(opts.max_memory) if opts.max_memory is not None else int(MEMORY_FRACTION * free_memory(device))
    keys, maps, kept = [], [], 0
    for i, (cam, depth, colour) in enumerate(_views(model, cameras, backend, depth_trunc, opts.depth)):
        keys.append(depth_blocks(domain, depth, cam))
        if len(keys) >= MERGE_VIEWS:
            keys = [torch.unique(torch.cat(keys))]
        kept += depth.numel() * 10
        if maps is not None and kept <= MAPS_FRACTION * limit:
            maps.append((depth, colour.half()))
        else:
            maps = None
        if progress is not None:
            progress(i + 1, len(cameras))
    blocks = grown_blocks(torch.cat(keys), domain)
    need = estimate_bytes(len(blocks)) + (kept if maps is not None else 0)
    if need > limit and opts.voxel_given:
        raise too_big(domain, blocks, need, limit, opts.max_memory is not None, what)
    coarsened_from = None
    if need > limit:  # the default voxel: the finest that fits instead
        coarsened_from = domain.voxel
        maps_bytes = kept if maps is not None else 0
        voxel, _ = fitting_voxel(domain, blocks, estimate_bytes(len(blocks)), limit - maps_bytes)
        if voxel is None:
            raise too_big(domain, blocks, need, limit, opts.max_memory is not None, what)
        blocks = coarser_blocks(blocks, domain, voxel)
        domain = replace(domain, voxel=voxel)
        need = estimate_bytes(len(blocks)) + maps_bytes
    trunc = float(opts.sdf_trunc) if opts.sdf_trunc else TRUNC_VOXELS * domain.voxel
    return MeshPlan(domain=domain, blocks=blocks, trunc=trunc, depth_trunc=depth_trunc, bytes=need, limit=limit,
                    maps=maps, depth=opts.depth, coarsened_from=coarsened_from)


def fitting_voxel(domain: Domain, blocks: torch.Tensor, need: int, limit: int) -> tuple[float | None, int]:
    """(a voxel size coarser than the domain's whose covering blocks need at most `limit` bytes, their bytes), or
    (None, the last size's bytes) when FIT_TRIES sizes did not fit. `need`: the bytes of `blocks`."""
    fit, fit_bytes = domain.voxel, need
    for _ in range(FIT_TRIES):
        # A surface's blocks go as 1 / voxel^2: aim a little past the limit's size, then check.
        fit = _round_up(fit * math.sqrt(fit_bytes / max(limit, 1)) * 1.05)
        fit_bytes = estimate_bytes(len(coarser_blocks(blocks, domain, fit)))
        if fit_bytes <= limit:
            return fit, fit_bytes
    return None, fit_bytes


def too_big(domain: Domain, blocks: torch.Tensor, need: int, limit: int, limit_given: bool, what: str) -> UserError:
    """The error for a volume of `blocks` needing `need` bytes of `limit`: it names the voxel size that fits."""
    fit, fit_bytes = fitting_voxel(domain, blocks, need, limit)
    hint = (f"pass --voxel-size {fit:.3g} (about {fit_bytes / 1e9:.3g} GB)" if fit is not None
            else "pass a larger --voxel-size")
    room = f"--max-memory allows {limit / 1e9:.3g} GB" if limit_given else f"{limit / 1e9:.3g} GB are free"
    return UserError(f"{what}: the TSDF volume at voxel size {domain.voxel:.3g} ({len(blocks) * BLOCK_VOXELS / 1e6:.3g}M "
                     f"voxels) needs about {need / 1e9:.3g} GB but {room}; {hint}, or --max-memory GB to allow more")


def _round_up(x: float) -> float:
    """x rounded up to 2 significant digits (a voxel size to type)."""
    scale = 10 ** (math.floor(math.log10(x)) - 1)
    return math.ceil(x / scale - 1e-9) * scale


def fuse(model, cameras, plan: MeshPlan, backend: str, progress: Callable[[int, int], None] | None = None) -> TSDFVolume:
    """Fuse every view's depth and colour (kept from the survey, or rendered again) into the plan's volume."""
    volume = TSDFVolume(plan.domain, plan.blocks, plan.trunc)
    views = (((cam, d, c.float()) for cam, (d, c) in zip(cameras, plan.maps)) if plan.maps is not None
             else _views(model, cameras, backend, plan.depth_trunc, plan.depth))
    for i, (cam, depth, colour) in enumerate(views):
        volume.integrate(depth, colour, cam)
        if progress is not None:
            progress(i + 1, len(cameras))
    return volume


def extract(volume: TSDFVolume, pieces: int, progress: Callable[[int, int], None] | None = None) -> tuple[Mesh, int]:
    """(the cleaned mesh, pieces dropped) of a fused volume."""
    return keep_largest(marching_cubes_blocks(volume, progress), pieces)
