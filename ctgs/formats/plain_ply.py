"""A plain 3DGS-style PLY approximation of a textured surfel model, for existing Gaussian viewers.

What is kept: position, rotation, the two tangent scales, opacity, all SH bands (padded with zeros to
degree 3, the layout viewers expect). What is approximated: each surfel's texture becomes one colour,
the Gaussian-weighted mean of its activated texels, folded into the DC coefficient
(dc += mean / C0, because colour = C0 * dc + 0.5 + texture). What is lost: all texture detail inside a
surfel, the max(colour, 0) clamp applied after adding the texture, and the exact surfel shape: the flat
axis gets a tiny third scale (FLAT_SCALE_RATIO of the smaller tangent scale), so 3DGS viewers splat a
thin 3D Gaussian (EWA projection) instead of intersecting the surfel plane. The header carries Brush's tag
`SplatRenderMode: 2dgs`, with which viewers that know 2DGS (Brush; PlayCanvas's tools read it) draw surfels.

`read_plain_ply` reads any 3DGS-layout PLY back as untextured surfels (`surfels_from_gaussians`: the two
largest scales become the tangent axes, the smallest is dropped), so our renderer can show what a 3DGS
viewer gets from the file; .splat files (ctgs.formats.splat) come back the same way.
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.formats.ply import read_ply, write_ply_records
from ctgs.render.geometry import quat_to_rotmat, rotmat_to_quat
from ctgs.model.surfels import SurfelModel
from ctgs.render.constants import CUTOFF_RHO

SH_C0 = 0.28209479177387814
PLAIN_SH_COEFFS = 16  # degree 3: 1 DC + 15 rest per channel, what 3DGS viewers read
# Third (normal-axis) scale relative to the smaller tangent scale: thin enough to look flat, large
# enough that viewers inverting the 3D covariance stay finite in float32.
FLAT_SCALE_RATIO = 1e-3
PLAIN_ROWS = 1 << 16  # rows converted at a time (float64 intermediates; baked models run to millions)


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


def gaussian_view(model: SurfelModel) -> dict:
    """What a Gaussian format holds of `model` (the 3DGS PLY's content), float64 numpy in the model's order: means
    [N, 3], log_scales [N, 3] (the flat axis FLAT_SCALE_RATIO x the smaller tangent scale), quats [N, 4] (w, x, y, z,
    unit), opacity [N] (sigmoid), dc [N, 3] (SH DC with the texture mean folded in), rest [N, R, 3] (the rendered SH
    bands past the DC), degree. UserError for a model without primitives."""
    if model.num_primitives == 0:
        raise UserError("the model has no primitives: nothing to export (check the run trained)")
    degree = min(int(model.sh_degree), 3, round(model.sh.shape[1] ** 0.5) - 1)
    log_s = model.log_scales.detach().cpu().double().numpy()
    sh = model.sh.detach().cpu()[:, :(degree + 1) ** 2].double().numpy()
    return {"means": model.means.detach().cpu().double().numpy(),
            "log_scales": np.concatenate([log_s, (log_s.min(1) + np.log(FLAT_SCALE_RATIO))[:, None]], 1),
            "quats": torch.nn.functional.normalize(model.quats.detach().cpu().double(), dim=1).numpy(),
            "opacity": torch.sigmoid(model.opacity_logits.detach().cpu().double()).numpy(),
            "dc": sh[:, 0] + (texture_means(model) / SH_C0).numpy(), "rest": sh[:, 1:], "degree": degree}


def write_plain_ply(model: SurfelModel, path: str, origin=None) -> None:
    """Write the 3DGS-layout approximation of `model` to `path` (float32, atomically). origin: [3] where the model's
    frame has its origin in the scene's COLMAP frame (a recentred scene), written as a header comment
    `world_origin X Y Z` (positions stay in the model's frame: float32 far from the origin would lose detail).
    Rows are converted PLAIN_ROWS at a time into the file's own record array (baked models run to millions)."""
    n = model.num_primitives
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{c}" for c in range(3)]
    names += [f"f_rest_{j}" for j in range(3 * (PLAIN_SH_COEFFS - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2"] + [f"rot_{i}" for i in range(4)]
    data = np.zeros(n, np.dtype([(name, "<f4") for name in names]))
    means_tex = texture_means(model) / SH_C0  # [N, 3]
    k = min(model.sh.shape[1], PLAIN_SH_COEFFS, (model.sh_degree + 1) ** 2)  # bands the model actually renders
    f32 = lambda t: t.detach().cpu().to(torch.float32).numpy()  # noqa: E731
    for start in range(0, n, PLAIN_ROWS):
        rows = slice(start, min(n, start + PLAIN_ROWS))
        m = rows.stop - rows.start
        sh = model.sh.detach().cpu()[rows, :k].to(torch.float64, copy=True)  # [M, k, 3], never a view of the model
        sh[:, 0, :] += means_tex[rows]
        full = torch.zeros(m, PLAIN_SH_COEFFS, 3, dtype=torch.float64)
        full[:, :k] = sh
        rest = full[:, 1:, :].transpose(1, 2).reshape(m, -1)  # [M, 45] channel-major, 3DGS order
        log_s = model.log_scales.detach().cpu()[rows].double()
        out = data[rows]  # a view: filling it fills data
        for i, axis in enumerate("xyz"):
            out[axis] = f32(model.means[rows, i])
        for c in range(3):
            out[f"f_dc_{c}"] = f32(full[:, 0, c])
        for j in range(rest.shape[1]):
            out[f"f_rest_{j}"] = f32(rest[:, j])
        out["opacity"] = f32(model.opacity_logits[rows])
        out["scale_0"], out["scale_1"] = f32(log_s[:, 0]), f32(log_s[:, 1])
        out["scale_2"] = f32(log_s.min(1).values + np.log(FLAT_SCALE_RATIO))
        for i in range(4):
            out[f"rot_{i}"] = f32(model.quats[rows, i])
    # The model is 2DGS surfels: Brush's tag (read by Brush and PlayCanvas's splat-transform / SuperSplat) tells a
    # viewer that knows 2DGS to draw surfels and ignore scale_2; viewers that do not know it skip the comment.
    comments = ["ctgs plain 3DGS approximation: texture means folded into f_dc", "SplatRenderMode: 2dgs"]
    if origin is not None and any(origin):
        comments.append("world_origin " + " ".join(repr(float(x)) for x in origin))
    write_ply_records(path, data, comments=comments)


def surfels_from_gaussians(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                           opacity_logits: torch.Tensor, sh: torch.Tensor) -> SurfelModel:
    """3D Gaussians -> untextured surfels (texture_mode "none", float32): the smallest of the three axes
    is the normal and is dropped; the other two keep their order as tangents u, v.

    means [N, 3], log_scales [N, 3] (log standard deviations), quats [N, 4] (w, x, y, z), opacity_logits
    [N], sh [N, K, 3] with K in (1, 4, 9, 16). Rows whose smallest scale is already the third (every PLY
    or .splat ctgs writes) keep their quaternion bit-exactly.
    """
    n = means.shape[0]
    f = lambda t: t.detach().to(torch.float32)  # noqa: E731
    log_scales, quats = f(log_scales).clone(), f(quats).clone()
    smallest = log_scales.argmin(1)  # [N]
    tangents = torch.tensor([[1, 2], [0, 2], [0, 1]])[smallest]  # [N, 2] the two axes kept, in order
    moved = smallest != 2
    if bool(moved.any()):
        r = quat_to_rotmat(quats[moved])  # [M, 3, 3] columns = the Gaussian's axes
        idx = tangents[moved]
        tu = r.gather(2, idx[:, None, :1].expand(-1, 3, 1))[..., 0]  # [M, 3]
        tv = r.gather(2, idx[:, None, 1:].expand(-1, 3, 1))[..., 0]
        quats[moved] = rotmat_to_quat(torch.stack([tu, tv, torch.cross(tu, tv, dim=1)], 2))
    k = sh.shape[1]
    if k not in (1, 4, 9, 16):
        raise ValueError(f"sh must have shape [N, K, 3] with K in (1, 4, 9, 16), got {list(sh.shape)}")
    return SurfelModel(
        means=f(means).contiguous(), log_scales=log_scales.gather(1, tangents).contiguous(), quats=quats,
        opacity_logits=f(opacity_logits).contiguous(), sh=f(sh).contiguous(),
        textures_raw=torch.zeros(0, 3), k_min=torch.ones(n), t2p_exp=torch.zeros(n, dtype=torch.int32),
        tex_res=torch.zeros(n, 2, dtype=torch.int32), tex_offset=torch.zeros(n, dtype=torch.int64),
        sh_degree=int(round(k**0.5)) - 1, texture_mode="none",
    )


def read_plain_ply(path: str) -> SurfelModel:
    """A 3DGS-layout PLY (ours or any 3DGS trainer's) as untextured surfels; UserError naming the file and
    the missing property when it is not one."""
    cols, _ = read_ply(path)
    need = ["x", "y", "z", "opacity", *[f"scale_{i}" for i in range(3)], *[f"rot_{i}" for i in range(4)],
            *[f"f_dc_{c}" for c in range(3)]]
    missing = [name for name in need if name not in cols]
    if missing:
        raise UserError(f"{path}: not a 3DGS PLY (properties {missing} missing); pass a PLY written by "
                        "`ctgs export --format ply` or a 3DGS trainer")
    rest = sorted((name for name in cols if name.startswith("f_rest_")), key=lambda s: int(s[7:]))
    k = 1 + len(rest) // 3
    if k not in (1, 4, 9, 16) or len(rest) % 3:
        raise UserError(f"{path}: {len(rest)} f_rest_* properties; a 3DGS PLY has 0, 9, 24 or 45")
    t = lambda names: torch.from_numpy(np.stack([cols[c].astype(np.float32) for c in names], 1))  # noqa: E731
    dc = t([f"f_dc_{c}" for c in range(3)])  # [N, 3]
    sh_rest = t(rest).reshape(-1, 3, k - 1).transpose(1, 2) if rest else torch.zeros(len(dc), 0, 3)
    return surfels_from_gaussians(t(["x", "y", "z"]), t([f"scale_{i}" for i in range(3)]),
                                  t([f"rot_{i}" for i in range(4)]), t(["opacity"])[:, 0],
                                  torch.cat([dc[:, None], sh_rest], 1))
