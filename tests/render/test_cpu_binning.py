"""The CPU backend's tile lists: every tile's list is in blending order, (camera-space depth, index), with
ties in index order. float32 depths are ordered by a radix sort (kernels/cpu/binning.cpp), float64 by
std::sort: both must give exactly the order of a stable sort by depth."""

from __future__ import annotations

import pytest
import torch

import ctgs.ops.ext as ext


def _tile_lists(dtype, n: int, depth_step: float | None, seed: int = 0):
    from scenes import random_scene

    from ctgs.render.preprocess import to_camera_space

    case = random_scene(n, seed=seed, dtype=dtype, width=48, height=40)
    s, cam = case.surfels, case.camera
    p = to_camera_space(s.means, s.quats, s.sh, cam, 2)
    mu_c = p.mu_c.detach().clone()
    if depth_step is not None:  # many primitives on a few depth planes: ties everywhere
        mu_c[:, 2] = (mu_c[:, 2] / depth_step).round().clamp_min(1.0) * depth_step
    scene = (mu_c.contiguous(), p.Rc.detach().contiguous(), s.scales, s.opacities, p.colors.detach().contiguous(),
             s.texel_size.contiguous(), s.textures, s.tex_res, s.tex_offset, torch.zeros(3, dtype=dtype))
    ext.load_cpu()
    outs = torch.ops.ctgs.rasterize_forward(*scene, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near,
                                            None, 1, False)
    return mu_c[:, 2], outs[5], outs[6]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("depth_step", [None, 0.25, 1e-7])
def test_every_tile_list_is_in_depth_then_index_order(dtype, depth_step):
    z, offsets, lst = _tile_lists(dtype, 600, depth_step)
    assert int(offsets[-1]) == lst.numel() > 600  # several tiles per primitive on average
    if depth_step == 0.25:
        assert torch.unique(z).numel() < 20  # the case is made of ties
    for t in range(offsets.numel() - 1):
        ids = lst[int(offsets[t]):int(offsets[t + 1])].long()
        if ids.numel() < 2:
            continue
        by_index = ids.sort().values
        assert torch.equal(ids, by_index[torch.argsort(z[by_index], stable=True)]), f"tile {t}"


def test_small_and_large_lists_agree_with_a_stable_sort():
    """Below 64 primitives the float32 path sorts with std::sort; above, by radix: the same order."""
    for n in (10, 63, 64, 65, 2000):
        z, offsets, lst = _tile_lists(torch.float32, n, 0.5, seed=n)
        for t in range(offsets.numel() - 1):
            ids = lst[int(offsets[t]):int(offsets[t + 1])].long()
            by_index = ids.sort().values
            assert torch.equal(ids, by_index[torch.argsort(z[by_index], stable=True)]), (n, t)
