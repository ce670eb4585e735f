"""Scene-relative settings: every value written in pixels, texels or iterations is resolved from the
training images' size and the run's length, so one recipe fits any scene size and any run length.

Configs hold every value at the paper's scale: images of about PAPER_PIXELS (1 Mpx, Mip-NeRF 360 images_4,
Deep Blending) and PAPER_ITERATIONS (30k). At that scale every rule below is the identity, so the paper's
recipe is reproduced exactly; elsewhere:

- iterations (texture start, routine cadence and window, tau_tr decay, SH bands, reallocation,
  densification, logging): x iterations / 30000 - a schedule is a fraction of the run (ctgs/train/config/schedule.py),
  which is also what lets `--time-budget` re-plan the run length while it runs;
- the texture cap (max_texture_res, texels per axis, a memory guard): x sqrt(pixels / 1e6), next power of
  two, at least MIN_TEXTURE_CAP: the widest texture stays the same fraction of the image;
- the split threshold (tau_tr_start, tau_tr_end, texels across a primitive): no rule, deliberately. A texel
  is at least 2**min_t2p_exp pixels of the closest camera, so tau_tr is already a size in pixels: a primitive
  splits when its texture needs more than tau_tr texels of >= 2 px, at any image size. Geometric detail is
  visible only down to a pixel, so primitives should shrink with the pixels: the model's size then follows
  the observed values. Scaling tau_tr with sqrt(pixels) instead (keeping split decisions at the same world
  size) was measured on 192x128 real photos: 3000 primitives became 24,652 by 50% of a 1000-iteration run
  (tau_tr 5 texels: 13% of the primitives split at every routine), against 3,185 at the end with the paper's
  32 texels; on the 96x72 demo (400 fast iterations, validation views) tau x (HW/1e6)**e gave 21.96 dB at
  e = 0, 17.6 at 0.25, 11.84 at 0.5 (1k, 3.7k, 21k primitives): `tau_tr_pixel_exponent` (default 0) keeps
  the option, measured in docs/studies.md;
- lambda_texture (texture sparsity, summed over texels): x 1e6 / pixels. The photometric loss is a mean
  over pixels, so its gradient on one texel shrinks as 1 / pixels while the sparsity term's does not;
- the primitive count (primitives_per_pixel, off in the paper): at most this many primitives per pixel of a
  typical training view, at initialisation (farthest-point subsample of the SfM points) and through splits
  (max_primitives): primitives_per_pixel x pixels x coverage, where coverage (routines.kmin.view_coverage) is how
  many views' worth of scene the capture holds, the SfM points over the median number one view sees. A
  facade photographed from the front is about 1 view's worth (every view sees most of it); a capture all around
  an object is more (Mip-NeRF 360 bonsai: 2.4), and a cap per pixel of one view would leave each view with a
  fraction of the density (bonsai at 200x133: 10.6k primitives for the whole room, open pixels in test views).
  SfM points are found at the photos' full resolution: on downsampled images they are far denser than a pixel
  (herzjesu25: 18.5k points, 0.75 per pixel of a 192x128 image; the paper's Mip-NeRF 360 models hold 0.1-0.3
  primitives per pixel). The baselines take baseline_primitives_per_pixel instead: 2DGS densifies by a gradient
  threshold in NDC units, blind to the image size, so on downsampled images it grows towards the count it would
  reach at full size;
- the views E is computed from (error_views, a random subset of the training views per full routine): at most
  error_pixels / pixels views (at least 1), when error_pixels > 0. E renders every view it uses, so the routines'
  cost grows with the image size while the step's budget does not: with 64 views at 399x266 (bonsai252, `fast`,
  30 min) the routines took 40-46% of the run's time. `fast`'s 1.75 Mpx is 64 views at 200x133 (where 64 was
  chosen) and below, 16 at 399x266;
- settings already relative to the scene need no rule: opacities, fractions (top_fraction), thresholds on
  texel values (tau_ds, texture_trim), learning rates (x scene extent for positions), the 2DGS baseline's densification
  threshold (3DGS NDC units: for content of a given angular size the NDC gradient does not depend on the
  image size), start_texels (texels across the primitive itself).

`scale_rules = false` (the `paper` preset) keeps the pixel rules off and uses every value as written: the
authors' recipe exactly, whatever the image size. The iteration rule always applies (at 30k it is exact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ctgs.model import surfels
from ctgs.train.config import TrainConfig

PAPER_PIXELS = 1.0e6  # "about 1 Mpx": M360 images_4 1237x822 (1.02 Mpx), Deep Blending 1332x876 (1.17 Mpx)
PAPER_ITERATIONS = 30000

# Keys holding an iteration count at the paper's scale (ctgs/train/config/schedule.py scales them).
ITERATION_KEYS = ("texture_start", "sh_every", "routine_every", "routine_until", "routine_margin",
                  "late_downscale_every", "late_prune_every", "realloc_every", "tau_tr_iters", "densify_from",
                  "densify_until", "densify_every", "opacity_reset_every", "test_every", "checkpoint_every")
# Smallest texture cap the rule may produce (texels per axis): above the split threshold (tau_tr_end = 32), so
# a primitive always splits before its texture reaches the cap.
MIN_TEXTURE_CAP = 64


@dataclass(frozen=True)
class Scale:
    """How this run relates to the paper's scale."""

    pixels: float  # training image size, H*W (median over training views)
    linear: float  # sqrt(pixels / PAPER_PIXELS), 1 when the pixel rules are off
    area: float  # pixels / PAPER_PIXELS, 1 when the pixel rules are off


def primitives_per_pixel(cfg: TrainConfig) -> float:
    """The cap per pixel (x coverage) this run's method takes: primitives_per_pixel for the content-aware method,
    baseline_primitives_per_pixel for the densifying baselines (0 = none)."""
    return cfg.primitives_per_pixel if cfg.method == "content_aware" else cfg.baseline_primitives_per_pixel


def scale_of(cfg: TrainConfig, pixels: float) -> Scale:
    if not cfg.scale_rules:
        return Scale(pixels=pixels, linear=1.0, area=1.0)
    area = pixels / PAPER_PIXELS
    return Scale(pixels=pixels, linear=math.sqrt(area), area=area)


def _pow2_at_least(x: float, floor: int) -> int:
    return max(floor, 2 ** math.ceil(math.log2(max(x, 1.0))))


def resolve(cfg: TrainConfig, pixels: float, coverage: float = 1.0) -> TrainConfig:
    """A copy of `cfg` whose pixel- and texel-based values are resolved for images of `pixels` (H*W) of a capture
    holding `coverage` views' worth of scene (ctgs.train.routines.kmin.view_coverage; the primitive cap).

    Iteration counts stay at the paper's scale: the schedule scales them by the planned run length
    (which `--time-budget` may change while training).
    """
    s = scale_of(cfg, pixels)
    ppp = primitives_per_pixel(cfg)
    cap = int(round(ppp * pixels * coverage)) if ppp > 0 else 0
    # --max-params: no more primitives than the budget holds with the smallest textures (size_budget)
    budget_cap = primitive_cap(cfg.method, cfg.max_sh_degree, cfg.max_params, cfg.fixed_texture_res)
    caps = [c for c in (cfg.max_primitives, cap, budget_cap) if c > 0]
    cfg = replace(cfg, max_primitives=min(caps) if caps else 0)
    if cfg.error_pixels > 0:
        by_pixels = max(1, int(cfg.error_pixels // max(pixels, 1.0)))
        cfg = replace(cfg, error_views=min(cfg.error_views, by_pixels) if cfg.error_views > 0 else by_pixels)
    if not cfg.scale_rules:
        return cfg
    return replace(
        cfg,
        max_texture_res=min(cfg.max_texture_res, _pow2_at_least(cfg.max_texture_res * s.linear, MIN_TEXTURE_CAP)),
        lambda_texture=cfg.lambda_texture / s.area,
        tau_tr_start=cfg.tau_tr_start * s.area ** cfg.tau_tr_pixel_exponent,
        tau_tr_end=cfg.tau_tr_end * s.area ** cfg.tau_tr_pixel_exponent,
    )


def with_size_budget(cfg: TrainConfig, observed_values: int) -> TrainConfig:
    """max_params from max_params_per_value x the observed values (RGB of every training pixel) when no explicit
    max_params is given: a budget relative to the data, like the images it is fitted to (same image size and view
    count -> same budget). Unchanged otherwise."""
    if cfg.max_params > 0 or cfg.max_params_per_value <= 0:
        return cfg
    return replace(cfg, max_params=max(1, int(round(cfg.max_params_per_value * observed_values))))


def for_scene(cfg: TrainConfig, observed_values: int, pixels: float, coverage: float = 1.0) -> tuple[TrainConfig, int]:
    """What a run on a scene's training views takes of the rules, in one call: the config resolved for them (its size
    budget from their observed values, `with_size_budget`; then `resolve` at their typical pixel count and
    coverage), and the cap on its initial points (`init_point_cap` of the budgeted config)."""
    budgeted = with_size_budget(cfg, observed_values)
    return resolve(budgeted, pixels, coverage), init_point_cap(budgeted, pixels, coverage)


def init_point_cap(cfg: TrainConfig, pixels: float, coverage: float = 1.0) -> int:
    """Initial primitives: max_init_points, at most primitives_per_pixel per pixel of a typical view (x coverage, as
    in `resolve`), and no more than a --max-params budget holds (primitive_cap); 0 = all."""
    caps = [c for c in (cfg.max_init_points, int(round(primitives_per_pixel(cfg) * pixels * coverage)),
                        primitive_cap(cfg.method, cfg.max_sh_degree, cfg.max_params, cfg.fixed_texture_res)) if c > 0]
    return min(caps) if caps else 0


# --max-params: primitives capped where even the smallest textures would fill the budget (the texels are kept within
# it by ctgs.train.routines.size_budget)
MIN_TEXELS = 4  # 2x2: the smallest texture a content-aware reallocation gives


def params_per_primitive(method: str, max_sh_degree: int) -> int:
    """SurfelModel.num_params per primitive of a `method` model (the 2dgs baseline has no texel size)."""
    return surfels.params_per_primitive(max_sh_degree, textured=method != "2dgs")


def primitive_cap(method: str, max_sh_degree: int, max_params: int, fixed_texture_res: int = 16) -> int:
    """Most primitives a budget of max_params can hold (0 = no budget): each with its own parameters and the
    smallest texture it can have."""
    if max_params <= 0:
        return 0
    tex = {"2dgs": 0, "fixed_texture": fixed_texture_res ** 2}.get(method, MIN_TEXELS)
    return max(1, max_params // (params_per_primitive(method, max_sh_degree) + 3 * tex))
