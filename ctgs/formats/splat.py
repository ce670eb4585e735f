"""The `.splat` format of web Gaussian viewers (antimatter15/splat and its descendants): 32 bytes per splat.

Layout, little-endian, no header (the splat count is file size / 32), one record per surfel:

| bytes | type | field |
| --- | --- | --- |
| 0-11 | 3 x float32 | centre x y z, world units |
| 12-23 | 3 x float32 | standard deviations along the rotation's axes (linear, not log) |
| 24-27 | 4 x uint8 | colour R G B = round(255 * clamp(0.5 + C0 * dc, 0, 1)), A = round(255 * opacity) |
| 28-31 | 4 x uint8 | rotation quaternion (w, x, y, z), normalised, each round(128 * q + 128) clamped to 0..255 |

What a surfel keeps: centre and tangent scales exactly (float32), the flat axis as a third scale of
FLAT_SCALE_RATIO x the smaller tangent one (as in the 3DGS PLY), the view-independent colour only (the DC
band plus the texture's Gaussian-weighted mean, as in the 3DGS PLY; higher SH bands are dropped), opacity
and rotation quantised to 8 bits. Records are ordered by tangent area x opacity, largest first (the
converters' convention: a viewer that streams the file shows the big splats first).
"""

from __future__ import annotations

import numpy as np
import torch

from ctgs.errors import UserError
from ctgs.io import atomic
from ctgs.formats.plain_ply import FLAT_SCALE_RATIO, SH_C0, surfels_from_gaussians, texture_means
from ctgs.model.surfels import SurfelModel

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert RECORD.itemsize == 32
# Opacity 0 or 1 has no finite logit: a quantised alpha of 0 or 255 reads back as this far from them.
ALPHA_EPS = 0.5 / 255
ROWS = 1 << 16  # records converted at a time


def splat_records(model: SurfelModel) -> np.ndarray:
    """[N] RECORD array of `model`, in file order (converted ROWS at a time: baked models run to millions)."""
    n = model.num_primitives
    rec = np.zeros(n, RECORD)
    importance = np.zeros(n)
    dc_tex = texture_means(model) / SH_C0  # [N, 3]
    for start in range(0, n, ROWS):
        rows = slice(start, min(n, start + ROWS))
        log_s = model.log_scales.detach().cpu()[rows].double()  # [M, 2]
        scales = torch.cat([log_s, (log_s.min(1).values + np.log(FLAT_SCALE_RATIO))[:, None]], 1).exp()  # [M, 3]
        dc = model.sh.detach().cpu()[rows, 0, :].double() + dc_tex[rows]  # [M, 3]
        rgb = (0.5 + SH_C0 * dc).clamp(0.0, 1.0)
        opacity = torch.sigmoid(model.opacity_logits.detach().cpu()[rows]).double()
        q = torch.nn.functional.normalize(model.quats.detach().cpu()[rows].double(), dim=1)
        out = rec[rows]  # a view
        out["position"] = model.means.detach().cpu()[rows].numpy()
        out["scale"] = scales.numpy()
        out["rgba"][:, :3] = torch.round(255 * rgb).numpy()
        out["rgba"][:, 3] = torch.round(255 * opacity).numpy()
        out["rot"] = torch.round(128 * q + 128).clamp(0, 255).numpy()
        importance[rows] = (scales[:, 0] * scales[:, 1] * opacity).numpy()
    return rec[np.argsort(-importance, kind="stable")]


def write_splat(model: SurfelModel, path: str) -> int:
    """Write `model` as a .splat file (atomically: a temporary name, then renamed). Returns its bytes."""
    data = splat_records(model)
    with atomic.atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(memoryview(data).cast("B"))
    return data.nbytes


def read_splat(path: str) -> SurfelModel:
    """A .splat file as untextured surfels (degree-0 SH); UserError naming the file when it is not one."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise UserError(f"{path}: cannot read .splat file ({exc.strerror}); check the path") from exc
    if len(raw) % RECORD.itemsize:
        raise UserError(f"{path}: {len(raw)} bytes is not a multiple of {RECORD.itemsize}; not a .splat file "
                        "(or truncated): re-export it")
    if not raw:
        raise UserError(f"{path}: empty (no splats); re-export it")
    rec = np.frombuffer(raw, RECORD)
    with np.errstate(invalid="ignore", over="ignore"):  # foreign bytes: NaN or huge scales, refused just below
        scales = rec["scale"].astype(np.float64)
    if len(rec) and not (np.isfinite(scales).all() and (scales > 0).all()):
        raise UserError(f"{path}: non-positive or non-finite scales; not a .splat file")
    alpha = np.clip(rec["rgba"][:, 3] / 255.0, ALPHA_EPS, 1 - ALPHA_EPS)
    dc = (rec["rgba"][:, :3] / 255.0 - 0.5) / SH_C0  # [N, 3]
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return surfels_from_gaussians(t(rec["position"]), t(np.log(scales)), t((rec["rot"] - 128.0) / 128.0),
                                  t(np.log(alpha / (1 - alpha))), t(dc)[:, None, :])
