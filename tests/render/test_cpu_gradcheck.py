"""float64 central finite differences of the C++ CPU backend on hand-built scenes, every input.

The scenes stay away from the renderer's discontinuities (see scenes.hand_scene for the list: MAX_ALPHA,
MIN_ALPHA vs the 3-sigma cutoff, T_EPS, the colour clamp, the rho3d/rho2d switch, texel grid kinks).
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from scenes import FLOAT_INPUTS, hand_scene, make_surfels, quat_axis_angle, with_grad

from ctgs.render import Camera, render

FD_EPS = 1e-6
# Central differences in float64: truncation ~eps^2 |f'''| ~ 1e-12 and rounding ~1e-16/eps ~ 1e-10 per
# entry; observed worst abs error 3e-9 on gradients of size up to ~20 (texel kinks are avoided).
FD_ATOL, FD_RTOL = 1e-7, 1e-6
INPUTS = FLOAT_INPUTS + ("background",)


def _offcentre_scene() -> tuple:
    """Two tilted textured surfels on a non-square 13x9 image, off-centre principal point, fx != fy, a
    rolled and shifted camera. Opacities < 0.35 put the MIN_ALPHA contour (alpha jumps from 1/255 to 0)
    inside the 3-sigma one; that contour is the only edge left and no pixel centre lies within FD_EPS
    of it. Texels in [-0.25, 0.25] on base colours >= 0.45 keep the clamp inactive."""
    s = make_surfels(
        means=[[0.1, 0.05, 2.2], [-0.15, -0.05, 2.6]],
        quats=[quat_axis_angle((0.4, 1.0, 0.2), 0.6), quat_axis_angle((1.0, 0.3, -0.5), 0.4)],
        scales=[[0.32, 0.22], [0.25, 0.3]],
        opacities=[0.33, 0.3],
        sh=[[[0.6, 0.3, 0.4]], [[0.2, 0.5, 0.7]]],
        texel_size=[[0.09, 0.12], [0.14, 0.1]],
        tex_res=[[5, 4], [3, 5]],
        seed=7,
    )
    view = torch.eye(4, dtype=torch.float64)
    c, si = 0.995, 0.0998749217771909  # small roll about z
    view[:2, :2] = torch.tensor([[c, -si], [si, c]], dtype=torch.float64)
    view[:3, 3] = torch.tensor([0.02, -0.03, 0.1], dtype=torch.float64)
    cam = Camera(fx=11.0, fy=12.5, cx=5.7, cy=4.9, width=13, height=9, viewmat=view, near=0.1)
    return s, cam


def _scenes():
    case = hand_scene(torch.float64)
    return {"hand_scene": (case.surfels, case.camera), "offcentre": _offcentre_scene()}


def _loss_fn(s, cam, bg, cot):
    out = render(s, cam, backend="cpu", background=bg)
    return (out.rgb * cot[0]).sum() + (out.alpha * cot[1]).sum() + (out.depth * cot[2]).sum()


def fd_table(s, cam) -> dict[str, tuple[float, float, float]]:
    """{input: (max abs error, max rel error, max |grad|)} of analytic vs central-difference gradients."""
    g = torch.Generator().manual_seed(0)
    cot = [torch.rand(cam.height, cam.width, 3, generator=g, dtype=torch.float64) - 0.3,
           torch.rand(cam.height, cam.width, generator=g, dtype=torch.float64) - 0.3,
           torch.rand(cam.height, cam.width, generator=g, dtype=torch.float64) - 0.3]
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
    sg = with_grad(s)
    bgg = bg.clone().requires_grad_(True)
    analytic = torch.autograd.grad(_loss_fn(sg, cam, bgg, cot), [getattr(sg, n) for n in FLOAT_INPUTS] + [bgg])
    table = {}
    for name, ga in zip(INPUTS, analytic):
        base = bg if name == "background" else getattr(s, name)
        num = torch.zeros_like(base).reshape(-1)
        for k in range(base.numel()):
            vals = []
            for sign in (1.0, -1.0):
                x = base.clone().reshape(-1)
                x[k] += sign * FD_EPS
                x = x.reshape(base.shape)
                with torch.no_grad():
                    if name == "background":
                        vals.append(_loss_fn(s, cam, x, cot).item())
                    else:
                        vals.append(_loss_fn(replace(s, **{name: x}), cam, bg, cot).item())
            num[k] = (vals[0] - vals[1]) / (2 * FD_EPS)
        num = num.reshape(base.shape)
        abs_err = (ga - num).abs()
        rel = (abs_err / num.abs().clamp_min(1e-3)).max().item()
        table[name] = (abs_err.max().item(), rel, num.abs().max().item())
    return table


@pytest.mark.parametrize("scene", ["hand_scene", "offcentre"])
def test_finite_differences_cpu_backend(scene):
    s, cam = _scenes()[scene]
    table = fd_table(s, cam)
    print(f"\n{scene}: input | max abs err | max rel err (|g| >= 1e-3) | max |grad|")
    for name, (a, r, m) in table.items():
        print(f"  {name:11s} | {a:.2e} | {r:.2e} | {m:.2e}")
    for name, (a, r, m) in table.items():
        assert m > 0, f"{name}: zero gradient, the check would prove nothing"
        assert a <= FD_ATOL + FD_RTOL * m, f"{name}: analytic vs numeric max abs err {a:.3g} (max |grad| {m:.3g})"
