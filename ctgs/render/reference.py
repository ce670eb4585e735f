"""Pure-PyTorch reference renderer for textured 2D Gaussian surfels (docs/reference/renderer.md, exactly).

Dense: every (pixel, primitive) pair is evaluated with tensor ops, and autograd differentiates it end to
end. It is the ground truth the C++/CUDA backends are compared against, so it shares NO code with them
(own constants, quaternion->rotation, SH, texture lookup) and favours readable, literal semantics over
speed. Works in float32 and float64, on whatever device the inputs live on.

Memory: pixels are processed in chunks of about `chunk_pairs` (pixel, primitive) pairs, all primitives
at once. One chunk holds ~40 live [P, M] tensors (P pixels in the chunk, M primitives in front of the
near plane) plus a [P, M, 3] colour tensor, i.e. roughly 60 * chunk_pairs * itemsize bytes (~500 MB in
float32 at the default 2**21 pairs). When gradients are needed each chunk runs under activation
checkpointing, so autograd keeps only the chunk inputs/outputs and recomputes one chunk at a time in
backward: peak memory stays one chunk, whatever H*W*M is (256x256 with thousands of primitives fits).

NaN-safety ("double where"): every masked branch is fed safe values *before* the risky op (division by
n.d, huge l/s ratios, floor of huge uv), so masked entries produce exact-zero gradients, never 0*inf.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from ctgs.render.camera import Camera
from ctgs.render.types import ErrorStats, RenderOutput, SurfelInputs

# ---- constants: an independent copy of docs/reference/renderer.md (deliberately not imported from the backend) ----
PARALLEL_EPS = 1e-6  # hit valid iff |n.d| > PARALLEL_EPS * |d|
FILTER_INV_SQUARE = 2.0  # rho2d = FILTER_INV_SQUARE * |pix - m|^2, pixels^-2
CUTOFF_RHO = 9.0  # contributes only if rho <= 9 (3 sigma)
MAX_ALPHA = 0.99
MIN_ALPHA = 1.0 / 255.0
T_EPS = 1e-4  # stop before a blend that would leave T < T_EPS

# |l / s| above this means rho3d > CUTOFF_RHO for sure (3 < 4): such entries can only be culled or lose
# to the fallback, so rho3d is replaced by +inf before squaring (no overflow, no 0*inf in backward).
_RATIO_BOUND = 4.0
DEFAULT_CHUNK_PAIRS = 1 << 21

# 3DGS real spherical-harmonics constants (degrees 0..3).
_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm > 0 -> [N, 3, 3] rotation; columns = tangent u, tangent v, normal."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """3DGS SH colour (without the +0.5): sh [N, K, 3], unit dirs [N, 3], degree 0..3 -> [N, 3]."""
    out = _SH_C0 * sh[:, 0]
    if degree < 1:
        return out
    x, y, z = (dirs[:, i : i + 1] for i in range(3))  # each [N, 1]
    out = out - _SH_C1 * y * sh[:, 1] + _SH_C1 * z * sh[:, 2] - _SH_C1 * x * sh[:, 3]
    if degree < 2:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (out + _SH_C2[0] * xy * sh[:, 4] + _SH_C2[1] * yz * sh[:, 5]
           + _SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + _SH_C2[3] * xz * sh[:, 7]
           + _SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree < 3:
        return out
    return (out + _SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9] + _SH_C3[1] * xy * z * sh[:, 10]
            + _SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
            + _SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
            + _SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13] + _SH_C3[5] * z * (xx - yy) * sh[:, 14]
            + _SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15])


@dataclass
class _Prims:
    """The M primitives in front of the near plane, sorted front to back (centre depth, then index)."""

    index: torch.Tensor  # [M] int64 original index
    mu: torch.Tensor  # [M, 3] camera-space centre, world units
    rot: torch.Tensor  # [M, 3, 3] camera-space rotation, columns u, v, n
    scales: torch.Tensor  # [M, 2] world units
    opacities: torch.Tensor  # [M]
    colors: torch.Tensor  # [M, 3] SH + 0.5, unclamped
    texel_size: torch.Tensor  # [M, 2] world units per texel
    tex_res: torch.Tensor  # [M, 2] int64
    tex_offset: torch.Tensor  # [M] int64


def _check(s: SurfelInputs) -> None:
    n = s.num_primitives

    def need(name: str, t: torch.Tensor, shape: str, ok: bool) -> None:
        if not ok:
            raise ValueError(f"{name} must have shape {shape}, got {list(t.shape)}")

    need("means", s.means, "[N, 3]", s.means.ndim == 2 and s.means.shape[1] == 3)
    need("quats", s.quats, f"[{n}, 4]", tuple(s.quats.shape) == (n, 4))
    need("scales", s.scales, f"[{n}, 2]", tuple(s.scales.shape) == (n, 2))
    need("opacities", s.opacities, f"[{n}]", tuple(s.opacities.shape) == (n,))
    need("sh", s.sh, f"[{n}, K, 3], K in 1,4,9,16",
         s.sh.ndim == 3 and s.sh.shape[0] == n and s.sh.shape[2] == 3 and s.sh.shape[1] in (1, 4, 9, 16))
    need("texel_size", s.texel_size, f"[{n}] or [{n}, 2]",
         tuple(s.texel_size.shape) in ((n,), (n, 2)))
    need("textures", s.textures, "[T, 3]", s.textures.ndim == 2 and s.textures.shape[1] == 3)
    need("tex_res", s.tex_res, f"[{n}, 2]", tuple(s.tex_res.shape) == (n, 2))
    need("tex_offset", s.tex_offset, f"[{n}]", tuple(s.tex_offset.shape) == (n,))


def _preprocess(s: SurfelInputs, camera: Camera, sh_degree: int) -> _Prims:
    dtype, device = s.means.dtype, s.means.device
    view = camera.viewmat.to(device=device, dtype=dtype)
    rv, tv = view[:3, :3], view[:3, 3]  # [3, 3], [3]
    mu_all = s.means @ rv.T + tv  # [N, 3]
    keep = torch.nonzero(mu_all[:, 2].detach() >= camera.near).squeeze(1)  # z < near: culled
    order = torch.sort(mu_all[keep, 2].detach(), stable=True).indices  # stable: ties by index
    idx = keep[order]  # [M]

    rot = rv @ quat_to_rotmat(s.quats[idx])  # [M, 3, 3]
    center = -rv.T @ tv  # [3] camera centre, world
    dirs = s.means[idx] - center  # [M, 3]
    sq = (dirs * dirs).sum(-1, keepdim=True)
    nonzero = sq > 0
    dirs = dirs * torch.where(nonzero, torch.rsqrt(torch.where(nonzero, sq, torch.ones_like(sq))), 0.0)
    colors = eval_sh(s.sh[idx], dirs, sh_degree) + 0.5

    k = s.texel_size[idx]
    if k.ndim == 1:
        k = k[:, None].expand(-1, 2)
    return _Prims(index=idx, mu=mu_all[idx], rot=rot, scales=s.scales[idx], opacities=s.opacities[idx],
                  colors=colors, texel_size=k, tex_res=s.tex_res[idx].long(), tex_offset=s.tex_offset[idx].long())


def _texture(lx: torch.Tensor, ly: torch.Tensor, cand: torch.Tensor, p: _Prims,
             textures: torch.Tensor) -> torch.Tensor:
    """Bilinear four-tap lookup for the candidate pairs `cand` [P, M] -> texture offsets [P, M, 3].

    lx, ly [P, M]: hit point in the surfel plane, world units (finite where cand).
    """
    P, M = cand.shape
    out = lx.new_zeros(P, M, 3)
    pi, mi = torch.nonzero(cand, as_tuple=True)
    if pi.numel() == 0:
        return out
    ku, kv = p.texel_size[mi, 0], p.texel_size[mi, 1]
    ru, rv = p.tex_res[mi, 0], p.tex_res[mi, 1]
    lu, lv = lx[pi, mi], ly[pi, mi]
    half_u, half_v = (ru - 1).to(lx.dtype) * 0.5, (rv - 1).to(lx.dtype) * 0.5
    with torch.no_grad():
        uu, vv = lu / ku + half_u, lv / kv + half_v
        inside = (torch.isfinite(uu) & torch.isfinite(vv) & (uu > -1) & (uu < ru.to(lx.dtype))
                  & (vv > -1) & (vv < rv.to(lx.dtype)))
    sel = torch.nonzero(inside).squeeze(1)
    if sel.numel() == 0:
        return out
    pi, mi, ru, rv = pi[sel], mi[sel], ru[sel], rv[sel]
    # Same ops as above, now only on in-range entries: finite, and safe to floor and cast.
    uu = lu[sel] / ku[sel] + half_u[sel]  # [S] texel coordinates, texel centres at integers
    vv = lv[sel] / kv[sel] + half_v[sel]
    u0, v0 = torch.floor(uu.detach()), torch.floor(vv.detach())
    fu, fv = uu - u0, vv - v0  # [S], d/duu = 1 (floor has no gradient)
    u0, v0 = u0.long(), v0.long()
    base = p.tex_offset[mi]
    val = lx.new_zeros(sel.numel(), 3)
    for du, dv, wgt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)),
                        (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        iu, iv = u0 + du, v0 + dv
        tap_ok = (iu >= 0) & (iu < ru) & (iv >= 0) & (iv < rv)  # taps outside the grid read 0
        row = torch.where(tap_ok, base + iv * ru + iu, 0)
        val = val + torch.where(tap_ok, wgt, 0.0)[:, None] * textures[row]
    return out.index_put((pi, mi), val)


def _render_chunk(px: torch.Tensor, py: torch.Tensor, err: torch.Tensor | None, p: _Prims,
                  textures: torch.Tensor, background: torch.Tensor, camera: Camera, with_stats: bool):
    """Pixels (px, py) [P] (column, row indices as floats) -> rgb [P, 3], T [P], depth [P], median depth [P]
    (detached), depth2 [P] (sum of w z^2), stats."""
    fx, fy, cx, cy, near = camera.fx, camera.fy, camera.cx, camera.cy, camera.near
    dx, dy = (px + 0.5 - cx) / fx, (py + 0.5 - cy) / fy  # [P] ray d = (dx, dy, 1), camera space
    d = torch.stack([dx, dy, torch.ones_like(dx)], -1)  # [P, 3]
    d_norm = torch.sqrt(dx * dx + dy * dy + 1.0)  # [P]
    u, v, n = p.rot[:, :, 0], p.rot[:, :, 1], p.rot[:, :, 2]  # [M, 3] each
    mu = p.mu

    # 1. plane hit (paper eq. 1); t = camera-space depth since d.z = 1.
    denom = d @ n.T  # [P, M]
    valid = denom.abs() > PARALLEL_EPS * d_norm[:, None]
    num = (n * mu).sum(-1)  # [M]
    t = torch.where(valid, num / torch.where(valid, denom, torch.ones_like(denom)), mu[:, 2])  # [P, M]
    # (t for invalid hits is mu.z: exactly the depth step 7 asks for, and a safe value for lx, ly.)
    # u.(t d - mu) = t (u.d) - u.mu: avoids a [P, M, 3] hit-point tensor.
    lx = t * (d @ u.T) - (u * mu).sum(-1)  # [P, M] world units
    ly = t * (d @ v.T) - (v * mu).sum(-1)
    in_front = ~(valid & (t < near))
    sx, sy = p.scales[:, 0], p.scales[:, 1]  # [M]
    near3d = valid & (lx.abs() <= _RATIO_BOUND * sx) & (ly.abs() <= _RATIO_BOUND * sy)
    lx = torch.where(near3d, lx, 0.0)  # safe values for the masked entries (double where)
    ly = torch.where(near3d, ly, 0.0)
    ax, ay = lx / sx, ly / sy
    rho3d = torch.where(near3d, ax * ax + ay * ay, math.inf)

    # 2. screen-space fallback around the projected centre (pixels).
    mx = fx * mu[:, 0] / mu[:, 2] + cx  # [M]
    my = fy * mu[:, 1] / mu[:, 2] + cy
    ex, ey = (px + 0.5)[:, None] - mx, (py + 0.5)[:, None] - my  # [P, M]
    rho2d = FILTER_INV_SQUARE * (ex * ex + ey * ey)

    # 3-4. falloff, alpha, skip rules.
    use3d = rho3d <= rho2d  # hit valid and the 3D Gaussian wins: texture allowed
    rho = torch.where(use3d, rho3d, rho2d)
    alpha = torch.clamp(p.opacities * torch.exp(-0.5 * rho), max=MAX_ALPHA)
    contrib = in_front & (rho <= CUTOFF_RHO) & (alpha >= MIN_ALPHA)
    alpha = torch.where(contrib, alpha, 0.0)

    # 8 (stop rule). Skipped entries have alpha 0 and cannot trigger the stop since T >= T_EPS holds
    # before every step; cumprod is non-increasing, so "first failure stops all later ones" is the
    # cummin below (kept explicit for clarity).
    with torch.no_grad():
        t_after = torch.cumprod(1.0 - alpha, dim=1)
        blended = (t_after >= T_EPS).to(torch.int8).cummin(dim=1).values.bool() & contrib
    alpha = torch.where(blended, alpha, 0.0)
    trans = torch.cumprod(1.0 - alpha, dim=1)  # [P, M] T after each entry (1 - alpha >= 0.01)
    t_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    w = alpha * t_before  # [P, M]

    # 5-6. texture and colour.
    has_tex = (p.tex_res[:, 0] > 0) & (p.tex_res[:, 1] > 0)  # [M]
    cand = blended & use3d & has_tex
    tex = _texture(lx, ly, cand, p, textures) if textures.shape[0] > 0 else lx.new_zeros(*lx.shape, 3)
    color = torch.relu(p.colors + tex)  # [P, M, 3], zero gradient where clamped

    rgb = (w[:, :, None] * color).sum(1) + trans[:, -1:] * background  # [P, 3]
    depth = (w * t).sum(1)  # [P]
    with torch.no_grad():  # median depth: t of the last entry blended while T before it > 0.5 (0 if none)
        before_half = alpha.gt(0) & (t_before > 0.5)
        last = torch.where(before_half, torch.arange(t.shape[1], device=t.device), -1).amax(1)  # [P]
        median = torch.where(last >= 0, t.gather(1, last.clamp_min(0)[:, None])[:, 0], torch.zeros_like(depth))
    stats = None
    if with_stats:
        with torch.no_grad():
            wd = w.detach()
            stats = (blended.sum(0).to(torch.int32), wd.sum(0), (err[:, None] * wd).sum(0))
    return rgb, trans[:, -1], depth, median.detach(), (w * t * t).sum(1), stats


def render_reference(surfels: SurfelInputs, camera: Camera, *, sh_degree: int | None = None,
                     background: torch.Tensor | None = None, error_image: torch.Tensor | None = None,
                     chunk_pairs: int = DEFAULT_CHUNK_PAIRS) -> RenderOutput:
    """Render `surfels` from `camera` exactly as docs/reference/renderer.md defines it (dense, autograd).

    Args:
        sh_degree: active SH degree (default: the largest that surfels.sh's K allows).
        background: [3] colour behind everything (default black).
        error_image: [H, W] per-pixel error; when given, RenderOutput.stats holds count/contrib/err [N].
        chunk_pairs: about how many (pixel, primitive) pairs one chunk evaluates (memory knob only).
    Returns: RenderOutput with rgb [H, W, 3], alpha [H, W], depth [H, W] (alpha-weighted, world units).
    """
    _check(surfels)
    s = surfels
    dtype, device = s.means.dtype, s.means.device
    max_degree = math.isqrt(s.sh.shape[1]) - 1
    degree = max_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= max_degree:
        raise ValueError(f"sh_degree must be in [0, {max_degree}] for sh with K={s.sh.shape[1]}, got {degree}")
    H, W = camera.height, camera.width
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else background.to(device, dtype)
    if error_image is not None and tuple(error_image.shape) != (H, W):
        raise ValueError(f"error_image must have shape [{H}, {W}], got {list(error_image.shape)}")

    # Zero that depends on every input: gradients always exist (zeros when nothing is visible).
    tie = sum(x[:0].sum() for x in (s.means, s.quats, s.scales, s.opacities, s.sh, s.texel_size, s.textures))
    p = _preprocess(s, camera, degree)
    M = int(p.index.shape[0])
    ys, xs = torch.meshgrid(torch.arange(H, device=device, dtype=dtype),
                            torch.arange(W, device=device, dtype=dtype), indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)  # [H*W] pixel column / row
    err = None if error_image is None else error_image.detach().to(device, dtype).reshape(-1)
    with_stats = err is not None
    n = s.num_primitives
    count = torch.zeros(n, dtype=torch.int32, device=device)
    contrib = torch.zeros(n, dtype=dtype, device=device)
    err_sum = torch.zeros(n, dtype=dtype, device=device)

    if M == 0:
        rgb = bg.expand(H * W, 3) + tie
        trans = torch.ones(H * W, dtype=dtype, device=device)
        depth = torch.zeros(H * W, dtype=dtype, device=device)
        median = torch.zeros(H * W, dtype=dtype, device=device)
        depth2 = torch.zeros(H * W, dtype=dtype, device=device)
    else:
        step = max(1, chunk_pairs // M)
        tensors = (p.mu, p.rot, p.scales, p.opacities, p.colors, p.texel_size, s.textures, bg)
        use_ckpt = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
        outs = []
        for lo in range(0, H * W, step):
            sl = slice(lo, lo + step)
            e = None if err is None else err[sl]

            def run(mu, rot, scales, opac, colors, k, tex, bgc, _sl=sl, _e=e):
                q = _Prims(index=p.index, mu=mu, rot=rot, scales=scales, opacities=opac, colors=colors,
                           texel_size=k, tex_res=p.tex_res, tex_offset=p.tex_offset)
                return _render_chunk(xs[_sl], ys[_sl], _e, q, tex, bgc, camera, with_stats)

            if use_ckpt:
                out = checkpoint(run, *tensors, use_reentrant=False, preserve_rng_state=False)
            else:
                out = run(*tensors)
            outs.append(out[:5])
            if with_stats:
                c, w_sum, e_sum = out[5]
                count.index_add_(0, p.index, c)
                contrib.index_add_(0, p.index, w_sum)
                err_sum.index_add_(0, p.index, e_sum)
        rgb = torch.cat([o[0] for o in outs]) + tie
        trans = torch.cat([o[1] for o in outs])
        depth = torch.cat([o[2] for o in outs])
        median = torch.cat([o[3] for o in outs])
        depth2 = torch.cat([o[4] for o in outs])
    stats = ErrorStats(count=count, contrib=contrib, err=err_sum) if with_stats else None
    return RenderOutput(rgb=rgb.reshape(H, W, 3), alpha=(1.0 - trans + tie).reshape(H, W),
                        depth=(depth + tie).reshape(H, W), stats=stats, median_depth=median.reshape(H, W),
                        depth2=(depth2 + tie).reshape(H, W))
