"""Scene builders for renderer tests (reference, CPU, CUDA): import with `from scenes import ...`.

Every builder returns a `Case` (SurfelInputs + Camera) in the requested dtype, CPU, no grad. Use
`with_grad(case.surfels)` to get a copy whose float inputs are leaves that require grad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch

from ctgs.render.camera import Camera
from ctgs.render.types import SurfelInputs

# The float inputs that receive gradients (tex_res / tex_offset are integer layout).
FLOAT_INPUTS = ("means", "quats", "scales", "opacities", "sh", "texel_size", "textures")


@dataclass
class Case:
    surfels: SurfelInputs
    camera: Camera


def look_at(eye, target, up=(0.0, -1.0, 0.0), dtype=torch.float64) -> torch.Tensor:
    """World->camera 4x4 for a camera at `eye` looking at `target` (OpenCV: +z forward, y down)."""
    eye, target, up = (torch.tensor(a, dtype=torch.float64) for a in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)  # y down when `up` points up (-y)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return view.to(dtype)


def pinhole(width: int, height: int, focal: float, viewmat: torch.Tensor | None = None,
            near: float = 0.01) -> Camera:
    """Centred pinhole camera; identity pose (at the origin, looking down +z) unless `viewmat` given."""
    view = torch.eye(4, dtype=torch.float64) if viewmat is None else viewmat
    return Camera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height,
                  viewmat=view, near=near)


def quat_axis_angle(axis, angle: float) -> list[float]:
    """(w, x, y, z) for a rotation of `angle` radians about `axis`."""
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    s = math.sin(angle / 2)
    return [math.cos(angle / 2), float(a[0]) * s, float(a[1]) * s, float(a[2]) * s]


def make_surfels(means, quats, scales, opacities, sh, texel_size, tex_res, textures=None,
                 dtype=torch.float64, seed: int = 0) -> SurfelInputs:
    """SurfelInputs from nested lists/tensors. `tex_res` [N,2]; textures [T,3] or None (random in
    [-0.25, 0.25], the jagged layout packed in primitive order)."""
    res = torch.as_tensor(tex_res, dtype=torch.int32).reshape(-1, 2)
    sizes = res[:, 0].long() * res[:, 1].long()
    offset = torch.cumsum(sizes, 0) - sizes
    if textures is None:
        g = torch.Generator().manual_seed(seed)
        textures = (torch.rand(int(sizes.sum()), 3, generator=g, dtype=torch.float64) - 0.5) * 0.5
    f = lambda a: torch.as_tensor(a, dtype=torch.float64).to(dtype)  # noqa: E731
    sh = f(sh)
    if sh.ndim == 2:
        sh = sh[:, None, :]
    return SurfelInputs(means=f(means).reshape(-1, 3), quats=f(quats).reshape(-1, 4), scales=f(scales).reshape(-1, 2),
                        opacities=f(opacities).reshape(-1), sh=sh, texel_size=f(texel_size),
                        textures=f(textures).reshape(-1, 3), tex_res=res, tex_offset=offset)


def cast(s: SurfelInputs, dtype: torch.dtype) -> SurfelInputs:
    return replace(s, **{name: getattr(s, name).detach().to(dtype) for name in FLOAT_INPUTS})


def with_grad(s: SurfelInputs) -> SurfelInputs:
    """A copy whose float inputs are fresh leaves with requires_grad."""
    return replace(s, **{name: getattr(s, name).detach().clone().requires_grad_(True) for name in FLOAT_INPUTS})


def single_surfel(dtype=torch.float64, *, depth: float = 2.0, scale=(0.5, 0.5), opacity: float = 0.8,
                  texel: float = 0.2, tex_res=(3, 3), textures=None, size: int = 21, focal: float = 10.0) -> Case:
    """One fronto-parallel surfel on the optical axis at `depth`, identity camera, odd square image.

    The pixel grid is centred on the surfel: pixel (W//2, H//2) looks straight at its centre, and one
    pixel step is depth/focal world units in the surfel plane (0.2 with the defaults = one texel).
    SH is DC only with value 0, so the base colour is exactly 0.5 per channel.
    """
    s = make_surfels(means=[[0.0, 0.0, depth]], quats=[[1.0, 0.0, 0.0, 0.0]], scales=[list(scale)],
                     opacities=[opacity], sh=[[0.0, 0.0, 0.0]], texel_size=[texel], tex_res=[list(tex_res)],
                     textures=textures, dtype=dtype)
    return Case(s, pinhole(size, size, focal).to("cpu", dtype))


def hand_scene(dtype=torch.float64) -> Case:
    """Three overlapping, moderately tilted, textured surfels on a 14x12 image, for finite differences.

    Built to stay away from every discontinuity of the renderer:
    - MAX_ALPHA: opacities <= 0.7, so o*G < 0.99 everywhere;
    - MIN_ALPHA vs CUTOFF_RHO: o*exp(-4.5) >= 0.3*0.011 > 1/255, so only the (measure-zero) rho = 9
      contour cuts, and no pixel centre lies on it (checked by shifting CUTOFF_RHO in the tests);
    - T_EPS: three layers of alpha <= 0.7 leave T >= 0.027 >> 1e-4;
    - colour clamp: base colours ~0.5-0.9 and texels in [-0.25, 0.25], so colours stay > 0;
    - rho3d/rho2d switch: every surfel spans several pixels and is tilted < 50 degrees, so the 3D
      Gaussian wins everywhere it contributes (checked by shrinking FILTER_INV_SQUARE in the tests);
    - texture grid: bilinear is continuous at the grid edge (outer taps read 0); only integer texel
      coordinates are kinks, hit with probability ~0 by these generic values.
    """
    s = make_surfels(
        means=[[0.05, -0.03, 2.0], [0.35, 0.2, 2.4], [-0.3, 0.15, 2.9]],
        quats=[quat_axis_angle((0.3, 1.0, 0.1), 0.5), quat_axis_angle((1.0, -0.2, 0.4), 0.7),
               quat_axis_angle((0.2, 0.5, 1.0), 0.9)],
        scales=[[0.28, 0.2], [0.22, 0.3], [0.35, 0.25]],
        opacities=[0.55, 0.7, 0.45],
        sh=[[[0.4, 0.1, 0.3], [0.05, -0.1, 0.08], [0.1, 0.02, -0.05], [-0.06, 0.04, 0.1]],
            [[0.2, 0.6, 0.1], [-0.1, 0.05, 0.02], [0.03, -0.08, 0.1], [0.07, 0.01, -0.03]],
            [[0.5, 0.3, 0.7], [0.02, 0.1, -0.06], [-0.05, 0.04, 0.03], [0.1, -0.02, 0.05]]],
        texel_size=[[0.13, 0.11], [0.17, 0.15], [0.19, 0.23]],
        tex_res=[[3, 3], [4, 2], [2, 3]],
        dtype=dtype, seed=1,
    )
    return Case(s, pinhole(14, 12, 16.0).to("cpu", dtype))


def random_scene(n: int = 40, *, seed: int = 0, dtype=torch.float64, width: int = 32, height: int = 24,
                 sh_degree: int = 2, max_res: int = 8) -> Case:
    """n random overlapping, tilted, partly off-screen textured surfels seen by an off-axis camera.

    About 1/8 of the primitives have no texture, texel sizes are anisotropic ([N, 2]), resolutions are
    1..max_res per axis, and some centres fall outside the frustum (partly visible surfels).
    """
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([2.6, 2.0, 1.5], dtype=torch.float64)  # wider than the view
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 0.04 + 0.25 * r(n, 2)
    opacities = 0.05 + 0.9 * r(n)
    k = (sh_degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 0.2
    sh[:, 0] += 0.3
    res = torch.randint(1, max_res + 1, (n, 2), generator=g)
    res[torch.arange(n) % 8 == 3] = 0  # no texture
    # Texel size such that the grid covers roughly +-2.5 sigma: textures are visible near the edges too.
    texel = 5.0 * scales / res.clamp_min(1).to(torch.float64) * (0.7 + 0.6 * r(n, 2))
    s = make_surfels(means, quats, scales, opacities, sh, texel, res, dtype=dtype, seed=seed + 1)
    view = look_at((0.4, -0.3, -2.5), (0.0, 0.0, 0.0))
    cam = Camera(fx=1.1 * width, fy=1.1 * width, cx=width / 2 + 0.3, cy=height / 2 - 0.2, width=width,
                 height=height, viewmat=view.to(dtype), near=0.05)
    return Case(s, cam)


def describe(s: SurfelInputs) -> str:
    return ", ".join(f"{f.name}{list(getattr(s, f.name).shape)}" for f in fields(s))


def bad_value_cases(s: SurfelInputs) -> list[tuple[str, SurfelInputs]]:
    """(the argument validate_inputs names, s with one value made invalid) for every value check of render():
    non-finite, out of range, an all-zero quaternion, a texel block past the end, a negative resolution. s needs
    more than 40001 texel rows, 100 primitives' scales and one textured primitive."""
    bad = []
    for name, index, value in [("means", 7, float("nan")), ("quats", 3, float("inf")), ("scales", 0, 0.0),
                               ("scales", 99, -1e-30), ("opacities", 5, 1.0 + 1e-6), ("opacities", 6, -0.0 - 1e-30),
                               ("sh", -1, float("-inf")), ("texel_size", 1, 0.0),
                               ("textures", 40000, float("nan")), ("textures", -1, float("inf"))]:
        t = getattr(s, name).clone()
        t.view(-1)[index] = value
        bad.append((name, replace(s, **{name: t})))
    q = s.quats.clone()
    q[2] = 0.0
    bad.append(("quats", replace(s, quats=q)))
    off = s.tex_offset.clone()
    used = int(torch.nonzero((s.tex_res[:, 0] * s.tex_res[:, 1]) > 0)[0])
    off[used] = s.textures.shape[0]  # block past the end
    bad.append(("tex_offset", replace(s, tex_offset=off)))
    res = s.tex_res.clone()
    res[4, 1] = -2
    bad.append(("tex_res", replace(s, tex_res=res)))
    return bad
