"""2DGS's geometric terms (Huang et al. 2024, "2D Gaussian Splatting"): depth-normal consistency (eq. 14) and depth
distortion (eq. 13), off by default.

The paper under reproduction trains without it (its sec. 5: the 2DGS regularisers "enhance the geometric
reconstruction but often result in lower NVS quality"); `lambda_normal > 0` turns it on from `normal_from` (a fraction
of the run; 2DGS starts it at 7000 of 30000 iterations).

    L_n = mean over pixels of (1 - alpha.detach() * N_r . N_d)

as in the 2DGS code: N_r = sum_i w_i n_i is the alpha-weighted normal map (n_i a surfel's unit normal turned to face
the camera), N_d the unit normal of the surface the render's expected depth (depth / alpha) describes, from central
differences of the back-projected pixel centres. sum_i w_i (1 - n_i . N_d) would be alpha - N_r . N_d; the 2DGS form
drops the alpha term so the loss never pushes opacity down. Gradients flow through both maps.

N_r comes from a second render of the same surfels (the renderer blends per-primitive colours with exactly the
weights w_i of the colour render: textures change colour, never alpha): each surfel's colour is its camera-space
normal encoded as (n + 1) / 2 (the renderer clamps colours below at 0), no textures, black background, so the
render is (N_r + alpha) / 2 and N_r = 2 rgb - alpha. Its depth gives N_d. One more forward and backward per step.

    L_d = mean over pixels of sum_{i<j} w_i w_j (z_i - z_j)^2 / zbar^2 = (alpha depth2 - depth^2) / zbar^2

from the same render (its alpha, depth = sum w z and depth2 = sum w z^2; the identity is exact, and so are its
gradients): the blending weights' spread along each ray, which is zero when a ray meets one surfel or several at one
depth. 2DGS measures z in a normalised device depth (near 0.2, far 100 in its scene units); here it is relative to the
pixel's expected depth zbar (held constant), so the weight does not depend on the scene's units.
"""

from __future__ import annotations

import torch

from ctgs.render import render
from ctgs.render.geometry import quat_to_rotmat
from ctgs.render.sh import SH_C0
from ctgs.render.types import SurfelInputs


def facing_normals(means: torch.Tensor, quats: torch.Tensor, camera) -> torch.Tensor:
    """[N, 3] each surfel's unit normal in camera space, signed to face the camera (n . mu_c <= 0); differentiable
    w.r.t. quats (the sign is a constant of the step)."""
    vm = camera.viewmat.to(means.device, means.dtype)
    rv, tv = vm[:3, :3], vm[:3, 3]
    n = quat_to_rotmat(quats)[:, :, 2] @ rv.T  # [N, 3]
    mu = means.detach() @ rv.T + tv
    sign = torch.where((n.detach() * mu).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n.dtype)
    return n * sign


def normal_inputs(inputs: SurfelInputs, camera) -> SurfelInputs:
    """The surfels of `inputs` with colour (n + 1) / 2 (n: `facing_normals`) as a degree-0 SH and no textures."""
    n = facing_normals(inputs.means, inputs.quats, camera)
    sh = (((n + 1.0) * 0.5 - 0.5) / SH_C0)[:, None, :]  # sh_to_color: SH_C0 * dc + 0.5
    return SurfelInputs(means=inputs.means, quats=inputs.quats, scales=inputs.scales, opacities=inputs.opacities,
                        sh=sh, texel_size=inputs.texel_size, textures=inputs.textures[:0],
                        tex_res=torch.zeros_like(inputs.tex_res), tex_offset=torch.zeros_like(inputs.tex_offset))


def render_normals(inputs: SurfelInputs, camera, backend: str = "auto"):
    """RenderOutput of `normal_inputs` over a black background: rgb = (N_r + alpha) / 2 (see `blended_normal`),
    alpha and depth as in a colour render of `inputs`."""
    return render(normal_inputs(inputs, camera), camera, backend=backend, sh_degree=0,
                  background=inputs.means.new_zeros(3))


def blended_normal(out) -> torch.Tensor:
    """[H, W, 3] N_r = sum_i w_i n_i from a `render_normals` output."""
    return 2.0 * out.rgb - out.alpha[..., None]


def expected_depth(depth: torch.Tensor, alpha: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """[H, W] depth / alpha where alpha > eps, else 0."""
    return torch.where(alpha > eps, depth / alpha.clamp_min(eps), torch.zeros_like(depth))


def depth_normals(depth: torch.Tensor, alpha: torch.Tensor, camera, eps: float = 1e-6) -> torch.Tensor:
    """[H, W, 3] unit camera-space normals (facing the camera) of the surface at the expected depth depth / alpha;
    zero on the one-pixel border, where alpha <= eps, and where the central differences are degenerate."""
    H, W = depth.shape
    z = expected_depth(depth, alpha, eps)
    u = (torch.arange(W, device=depth.device, dtype=depth.dtype) + 0.5 - camera.cx) / camera.fx
    v = (torch.arange(H, device=depth.device, dtype=depth.dtype) + 0.5 - camera.cy) / camera.fy
    p = torch.stack([z * u[None, :], z * v[:, None], z], -1)  # [H, W, 3]
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    # x right, y down, z forward: du x dv points away from the camera on a fronto-parallel plane; dv x du faces it.
    c = torch.linalg.cross(dv, du, dim=-1)
    norm = c.norm(dim=-1, keepdim=True)
    ok = (norm > 1e-20) & (alpha[1:-1, 1:-1, None] > eps)
    n = torch.where(ok, c / norm.clamp_min(1e-20), torch.zeros_like(c))
    return torch.nn.functional.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def consistency(out, camera, weight: torch.Tensor | None = None) -> torch.Tensor:
    """mean(1 - weight N_r . N_d) of a normal render `out` (RenderOutput of `normal_inputs`); weight [H, W] defaults
    to out.alpha detached (2DGS's form; a constant of the step, so gradients flow through N_r and N_d only)."""
    n_r = blended_normal(out)
    n_d = depth_normals(out.depth, out.alpha, camera)
    weight = out.alpha.detach() if weight is None else weight
    return (1.0 - weight * (n_r * n_d).sum(-1)).mean()


def distortion_map(out, eps: float = 1e-6) -> torch.Tensor:
    """[H, W] (alpha depth2 - depth^2) / zbar^2 of a render `out` (RenderOutput with depth2): the relative depth
    distortion sum_{i<j} w_i w_j (z_i - z_j)^2 / zbar^2, zbar = depth / alpha held constant (0 where alpha <= eps)."""
    a = out.alpha
    zbar = expected_depth(out.depth.detach(), a.detach(), eps)
    inv = torch.where(zbar > 0, 1.0 / zbar.clamp_min(eps) ** 2, torch.zeros_like(zbar))
    return (a * out.depth2 - out.depth * out.depth) * inv


def distortion(out, eps: float = 1e-6) -> torch.Tensor:
    """Scalar: the mean of `distortion_map` over the pixels."""
    return distortion_map(out, eps).mean()


def normal_loss(inputs: SurfelInputs, camera, backend: str = "auto") -> torch.Tensor:
    """Scalar 2DGS normal-consistency term of one view (unweighted), from one more render of `inputs`."""
    return consistency(render_normals(inputs, camera, backend), camera)


def geometry_terms(inputs: SurfelInputs, camera, backend: str = "auto", normal: bool = True,
                   dist: bool = True) -> dict:
    """{"normal": L_n, "dist": L_d} of one view (unweighted, each only if asked), from one more render of `inputs`."""
    out = render_normals(inputs, camera, backend)
    terms = {}
    if normal:
        terms["normal"] = consistency(out, camera)
    if dist:
        terms["dist"] = distortion(out)
    return terms
