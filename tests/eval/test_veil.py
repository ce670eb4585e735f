"""ctgs.metrics.evaluate.veil_share: one primitive centred outside the view, blended in front of the scene."""

from __future__ import annotations

import math
import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "render"))
from scenes import make_surfels, pinhole  # noqa: E402

from ctgs.metrics.evaluate import veil_share  # noqa: E402

W, H, F = 48, 36, 40.0
WALL = dict(mean=[0.0, 0.0, 5.0], scale=[20.0, 20.0], opacity=0.99)  # centred in the view, fills it


def _case(extra: list[dict]):
    prims = [WALL] + extra
    return make_surfels(means=[p["mean"] for p in prims], quats=[p.get("quat", [1.0, 0.0, 0.0, 0.0]) for p in prims],
                        scales=[p["scale"] for p in prims], opacities=[p["opacity"] for p in prims],
                        sh=[[0.5, 0.5, 0.5]] * len(prims), texel_size=[0.1] * len(prims),
                        tex_res=[[0, 0]] * len(prims), dtype=torch.float32)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_a_surfel_centred_off_to_the_side_at_small_depth_is_a_veil(backend):
    cam = pinhole(W, H, F).to("cpu", torch.float32)
    # a plane at depth 1 (in front of the wall at 5), centred 100 units to the side, 100 units wide: its centre
    # depth sorts it first, and at the view it weighs exp(-1/2) x its opacity
    veil = dict(mean=[100.0, 0.0, 1.0], scale=[100.0, 100.0], opacity=0.8)
    share = veil_share(_case([veil]), cam, 0, backend)
    assert share == pytest.approx(0.8 * torch.exp(torch.tensor(-0.5)).item(), rel=0.05)
    # the same surfel behind the wall: the wall hides it
    behind = dict(veil, mean=[100.0, 0.0, 50.0])
    assert veil_share(_case([behind]), cam, 0, backend) < 0.02
    # only the wall, centred in the view: nothing outside it carries any weight
    assert veil_share(_case([]), cam, 0, backend) == 0.0


def test_a_centre_behind_the_camera_counts_as_outside():
    cam = pinhole(W, H, F).to("cpu", torch.float32)
    # centred behind the camera (culled: z < near), so it draws nothing and carries no weight, but it is outside
    behind_cam = dict(mean=[0.0, 0.0, -1.0], scale=[5.0, 5.0], opacity=0.9)
    assert veil_share(_case([behind_cam]), cam, 0, "reference") == 0.0


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_a_surfel_centred_off_to_the_side_that_crosses_the_view_behind_the_wall_is_no_veil(backend):
    """Session 27's veil: centre depth 1 (in front of the wall at 5), 100 units to the side, but tilted so that its
    plane crosses the view about 39 units away. Centre-depth order blended it first (about 0.43 of the view's
    weight); keyed by where its plane crosses the image (docs/renderer.md, "Blending order") it goes behind the
    wall, and the render is the wall's."""
    from ctgs.render import render

    cam = pinhole(W, H, F).to("cpu", torch.float32)
    theta = math.atan2(49.0, 100.0)  # normal (sin, 0, cos): the plane holds (100, 0, 1) and (0, 0, 50)
    tilted = dict(mean=[100.0, 0.0, 1.0], scale=[100.0, 100.0], opacity=0.8,
                  quat=[math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0])
    assert veil_share(_case([tilted]), cam, 0, backend) < 0.02
    wall_only = render(_case([]), cam, backend=backend, sh_degree=0).rgb
    with_it = render(_case([tilted]), cam, backend=backend, sh_degree=0).rgb
    assert (with_it - wall_only).abs().max() < 0.01
    # the same surfel mirrored to cross the view in front of the wall (plane through (0, 0, 2)) is still blended
    # first: a real occluder keeps its place
    theta = math.atan2(1.0, 100.0)
    front = dict(tilted, quat=[math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0])
    assert veil_share(_case([front]), cam, 0, backend) > 0.3
