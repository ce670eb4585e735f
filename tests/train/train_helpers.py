"""Hand-built tiny scenes for the training-routine tests (no scene files, no SfM)."""

from __future__ import annotations

import json
import math
import os

import torch

from ctgs.model.surfels import SurfelModel, jagged_offsets
from ctgs.render import render
from ctgs.render.camera import Camera
from ctgs.train.step.adam import SurfelAdam

W, H, F = 64, 48, 60.0
BACKEND = "cpu"
CLOCK_FIELDS = ("seconds", "wall", "step_routines_s")  # time readings in log.jsonl: the only fields a resumed run may change


def camera(z_shift: float = 0.0) -> Camera:
    """Camera at the origin looking down +z (identity world->camera)."""
    vm = torch.eye(4)
    vm[2, 3] = z_shift
    return Camera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H, viewmat=vm)


def model(means, scales, opacities, tex_res, k_min=None, t2p_exp=None, textures=None, seed=0) -> SurfelModel:
    """Surfels facing the camera (identity rotation), SH DC grey, given textures (raw) or random."""
    g = torch.Generator().manual_seed(seed)
    means = torch.as_tensor(means, dtype=torch.float32)
    n = means.shape[0]
    tex_res = torch.as_tensor(tex_res, dtype=torch.int32).reshape(n, 2)
    sizes = tex_res[:, 0].long() * tex_res[:, 1].long()
    if textures is None:
        textures = torch.randn(int(sizes.sum()), 3, generator=g)
    o = torch.as_tensor(opacities, dtype=torch.float32)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    sh = torch.zeros(n, 1, 3)
    sh[:, 0] = 0.3
    leaf = lambda t: t.clone().contiguous().requires_grad_(True)  # noqa: E731
    return SurfelModel(
        means=leaf(means), log_scales=leaf(torch.log(torch.as_tensor(scales, dtype=torch.float32))),
        quats=leaf(quats), opacity_logits=leaf(torch.log(o / (1 - o))), sh=leaf(sh), textures_raw=leaf(textures),
        k_min=torch.full((n,), 0.05) if k_min is None else torch.as_tensor(k_min, dtype=torch.float32),
        t2p_exp=torch.full((n,), 1, dtype=torch.int32) if t2p_exp is None else torch.as_tensor(t2p_exp, dtype=torch.int32),
        tex_res=tex_res, tex_offset=jagged_offsets(tex_res), texture_mode="content_aware")


def optimiser(m: SurfelModel) -> SurfelAdam:
    """Adam with recognisable moments: texel moments = texel values (so moving them can be checked)."""
    opt = SurfelAdam(m)
    opt.exp_avg["textures_raw"] = m.textures_raw.detach().clone()
    opt.exp_avg_sq["textures_raw"] = m.textures_raw.detach().clone() ** 2
    return opt


@torch.no_grad()
def image(m: SurfelModel, cam: Camera | None = None) -> torch.Tensor:
    return render(m.render_inputs(), cam or camera(), backend=BACKEND, sh_degree=0).rgb


def smooth_texture(res: int, scale_texels: float, amp: float = 1.5) -> torch.Tensor:
    """[res*res, 3] raw texels: a broad bump (low frequency: survives resampling)."""
    c = (torch.arange(res, dtype=torch.float32) - (res - 1) / 2) / scale_texels
    bump = torch.exp(-0.5 * (c[None, :] ** 2 + c[:, None] ** 2))  # [res(v), res(u)]
    cols = torch.tensor([1.0, -0.5, 0.3])
    return (amp * bump.reshape(-1, 1) * cols).contiguous()


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def run_log(run: str) -> list[dict]:
    """A run's log.jsonl without its clock readings."""
    rows = [json.loads(line) for line in open(os.path.join(run, "log.jsonl"))]
    for r in rows:
        for clock in CLOCK_FIELDS:
            r.pop(clock, None)
    return rows
