"""The texels-per-area measure of the benchmarks (benchmarks/measures/allocation.py), on hand-built cases."""

from __future__ import annotations

import math

import torch

from measures.allocation import allocation_measures, texel_density_by_kind, texel_position_density_by_kind
from train_helpers import model

# Two unit squares in the plane z = 2 (normal z, facing the helpers' identity-rotation surfels):
# "photo" on x in [-1, 0], "flat" on x in [0, 1].
META = {"surfaces": [
    {"id": "p", "kind": "photo", "center": [-0.5, 0.0, 2.0], "normal": [0, 0, 1], "u": [1, 0, 0], "v": [0, 1, 0],
     "half_extents": [0.5, 0.5], "area": 1.0},
    {"id": "f", "kind": "flat", "center": [0.5, 0.0, 2.0], "normal": [0, 0, 1], "u": [1, 0, 0], "v": [0, 1, 0],
     "half_extents": [0.5, 0.5], "area": 1.0},
]}


def test_texels_are_counted_where_they_lie():
    # One 8x8 texture on the photo square, one 2x2 on the flat square; texel 0.05 (k_min 0.025 x 2^1).
    m = model([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0]], [[0.05, 0.05]] * 2, [0.5, 0.5], [[8, 8], [2, 2]],
              k_min=[0.025, 0.025])
    d = texel_position_density_by_kind(m, META)
    assert d == {"flat": 4.0, "photo": 64.0} == texel_density_by_kind(m, META)


def test_a_primitive_on_an_edge_spends_texels_on_both_sides():
    # 8x8 texels of 0.1 centred on the edge x = 0 (columns at +-0.05 .. +-0.35, clear of the 5% margin by
    # which allocation.py grows each rectangle): half the columns lie on each square.
    m = model([[0.0, 0.0, 2.0]], [[0.05, 0.05]], [0.5], [[8, 8]], k_min=[0.05])
    assert texel_position_density_by_kind(m, META) == {"flat": 32.0, "photo": 32.0}
    # Rotated 90 degrees about the normal: still split by columns of the world, not of the texture.
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    m.quats.data.copy_(q)
    assert texel_position_density_by_kind(m, META) == {"flat": 32.0, "photo": 32.0}
    # Texels in the air (surfel 1 unit in front of the plane) count nowhere.
    m.means.data[:, 2] = 1.0
    assert texel_position_density_by_kind(m, META) == {"flat": 0.0, "photo": 0.0}


def test_allocation_measures_texel_size_and_params_per_area():
    # Photo square: three primitives with fine texels (exponent 1); flat square: one with coarse texels (4).
    m = model([[-0.7, 0.0, 2.0], [-0.5, 0.0, 2.0], [-0.3, 0.0, 2.0], [0.5, 0.0, 2.0]], [[0.05, 0.05]] * 4,
              [0.5] * 4, [[8, 8], [8, 8], [4, 4], [2, 2]], k_min=[0.025] * 4)
    m.t2p_exp = torch.tensor([1, 1, 2, 4], dtype=torch.int32)
    r = allocation_measures(m, META)
    assert r["photo"]["primitives"] == 3 and r["flat"]["primitives"] == 1
    assert math.isclose(r["photo"]["texel_size_prim"], 0.05, rel_tol=1e-6)
    assert math.isclose(r["flat"]["texel_size_prim"], 0.4, rel_tol=1e-6)
    # Per texel: the 8x8 textures (128 of 144 texels) dominate the photo median.
    assert math.isclose(r["photo"]["texel_size_texel"], 0.05, rel_tol=1e-6)
    assert math.isclose(r["ratios"]["texel_size_prim_flat_over_photo"], 8.0, rel_tol=1e-6)
    # These helper surfels carry SH degree 0: 3 + 2 + 4 + 1 + 3 + 1 = 14 parameters each (59 at degree 3).
    assert math.isclose(r["photo"]["params_per_area"], 3 * 14 + 3 * 144, rel_tol=1e-6)
    assert math.isclose(r["flat"]["params_per_area"], 14 + 3 * 4, rel_tol=1e-6)
    assert math.isclose(r["ratios"]["params_per_area_photo_over_flat"], (3 * 14 + 3 * 144) / (14 + 12), rel_tol=1e-6)
    # A model without textures: sizes are undefined, parameters per area still count (no texel exponent).
    m.texture_mode = "none"
    r = allocation_measures(m, META)
    assert math.isnan(r["photo"]["texel_size_prim"]) and math.isclose(r["flat"]["params_per_area"], 13 + 12, rel_tol=1e-6)
