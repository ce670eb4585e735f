"""A plain 3DGS-style PLY approximation of a textured surfel model, for existing Gaussian viewers.

What is kept: position, rotation, the two tangent scales, opacity, all SH bands (padded with zeros to
degree 3, the layout viewers expect). What is approximated: each surfel's texture becomes one colour,
the Gaussian-weighted mean of its activated texels, folded into the DC coefficient
(dc += mean / C0, because colour = C0 * dc + 0.5 + texture). What is lost: all texture detail inside a
surfel, the max(colour, 0) clamp applied after adding the texture, and the exact surfel shape: the flat
axis gets a tiny third scale (FLAT_SCALE_RATIO of the smaller tangent scale), so 3DGS viewers splat a
thin 3D Gaussian (EWA projection) instead of intersecting the surfel plane.
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.io.ply import write_ply
from ctgs.model.surfels import SurfelModel
from ctgs.render.constants import CUTOFF_RHO

SH_C0 = 0.28209479177387814
PLAIN_SH_COEFFS = 16  # degree 3: 1 DC + 15 rest per channel, what 3DGS viewers read
# Third (normal-axis) scale relative to the smaller tangent scale: thin enough to look flat, large
# enough that viewers inverting the 3D covariance stay finite in float32.
FLAT_SCALE_RATIO = 1e-3


def texture_means(model: SurfelModel) -> torch.Tensor:
    """[N, 3] Gaussian-weighted mean activated texel of every primitive (0 where it has no texture)."""
    n = model.num_primitives
    out = torch.zeros(n, 3, dtype=torch.float64)
    if model.num_texels == 0 or model.texture_mode == "none":
        return out
    res = model.tex_res.long()  # [N, 2]
    sizes = res[:, 0] * res[:, 1]  # [N]
    prim = torch.repeat_interleave(torch.arange(n), sizes)  # [T'] primitive of every used texel
    local = torch.arange(int(sizes.sum())) - torch.repeat_interleave(torch.cumsum(sizes, 0) - sizes, sizes)
    rows = model.tex_offset.long()[prim] + local  # texel rows in textures_raw
    iu, iv = local % res[prim, 0], local // res[prim, 0]
    k = model.texel_size.detach().double()[prim]  # [T', 2] world units per texel
    scales = model.scales.detach().double()[prim]  # [T', 2]
    lx = (iu.double() - (res[prim, 0].double() - 1) / 2) * k[:, 0]
    ly = (iv.double() - (res[prim, 1].double() - 1) / 2) * k[:, 1]
    rho = (lx / scales[:, 0]) ** 2 + (ly / scales[:, 1]) ** 2
    w = torch.exp(-0.5 * rho) * (rho <= CUTOFF_RHO)  # renderer cutoff: no weight past 3 sigma  # [T']
    tex = model.textures.detach().double()[rows]  # [T', 3]
    wsum = torch.zeros(n, dtype=torch.float64).index_add_(0, prim, w)
    out.index_add_(0, prim, tex * w[:, None])
    return out / wsum.clamp_min(1e-30)[:, None]


def write_plain_ply(model: SurfelModel, path: str) -> None:
    """Write the 3DGS-layout approximation of `model` to `path` (float32, atomically)."""
    n = model.num_primitives
    f32 = lambda t: t.detach().cpu().to(torch.float32).numpy()  # noqa: E731
    sh = model.sh.detach().cpu().double().clone()  # [N, K, 3]
    sh[:, 0, :] += texture_means(model) / SH_C0
    full = torch.zeros(n, PLAIN_SH_COEFFS, 3, dtype=torch.float64)
    k = min(sh.shape[1], PLAIN_SH_COEFFS, (model.sh_degree + 1) ** 2)  # bands the model actually renders
    full[:, :k] = sh[:, :k]
    rest = full[:, 1:, :].transpose(1, 2).reshape(n, -1)  # [N, 45] channel-major, 3DGS order
    log_s = model.log_scales.detach().cpu().double()
    flat = log_s.min(1).values + np.log(FLAT_SCALE_RATIO)
    cols: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        cols[axis] = f32(model.means[:, i])
    for axis in ("nx", "ny", "nz"):
        cols[axis] = np.zeros(n, np.float32)
    for c in range(3):
        cols[f"f_dc_{c}"] = f32(full[:, 0, c])
    for j in range(rest.shape[1]):
        cols[f"f_rest_{j}"] = f32(rest[:, j])
    cols["opacity"] = f32(model.opacity_logits)
    cols["scale_0"], cols["scale_1"], cols["scale_2"] = f32(log_s[:, 0]), f32(log_s[:, 1]), f32(flat)
    for i in range(4):
        cols[f"rot_{i}"] = f32(model.quats[:, i])
    write_ply(path, cols, comments=["ctgs plain 3DGS approximation: texture means folded into f_dc"])
