"""ctgs.evaluation.evaluate.veil_share: one primitive centred outside the view, blended in front of the scene."""

from __future__ import annotations

import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "render"))
from scenes import make_surfels, pinhole  # noqa: E402

from ctgs.evaluation.evaluate import veil_share  # noqa: E402

W, H, F = 48, 36, 40.0
WALL = dict(mean=[0.0, 0.0, 5.0], scale=[20.0, 20.0], opacity=0.99)  # centred in the view, fills it


def _case(extra: list[dict]):
    prims = [WALL] + extra
    return make_surfels(means=[p["mean"] for p in prims], quats=[[1.0, 0.0, 0.0, 0.0]] * len(prims),
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
