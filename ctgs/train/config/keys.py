"""Training configuration: one dataclass whose defaults are the paper's recipe; a preset (configs/<name>.toml),
then a config file, then `--set key=value` override them.

Values are written at the paper's scale (about 1 Mpx images, 30k iterations) and resolved for the run by
ctgs/train/config/rules.py (pixels, texels) and ctgs/train/config/schedule.py (iterations: a schedule is a fraction of
the run), so no config needs retuning when the image size or the iteration count changes.
"""

from __future__ import annotations

import ast
import difflib
import os
import tomllib
from dataclasses import asdict, dataclass, field, fields

from ctgs.errors import UserError
from ctgs.resources import resolve_config

METHODS = ("content_aware", "2dgs", "fixed_texture")


def _f(default, help_text: str):
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata={"help": help_text})
    return field(default=default, metadata={"help": help_text})


@dataclass
class TrainConfig:
    # ---- run / data ----
    scene_dir: str = _f("", "scene folder (COLMAP layout); set by the CLI")
    images: str = _f("images", "image sub-folder to train on (e.g. images_4)")
    holdout: int = _f(8, "every holdout-th image (sorted by name, idx % holdout == 0) is a test view; 0 = none")
    validation_holdout: int = _f(0, "> 0: tuning mode: the test views are left out entirely and every "
                                 "validation_holdout-th remaining view (offset by half) is held out and evaluated "
                                 "instead; choose settings this way, never on test views")
    backend: str = _f("auto", "renderer backend: auto | cpu | cuda | reference")
    device: str = _f("auto", "torch device: auto (cuda if available) | cpu | cuda")
    seed: int = _f(0, "seed of every random number generator")
    threads: int = _f(0, "CPU threads for torch and the CPU backend (0 = torch's default; 1 on a shared machine)")
    method: str = _f("content_aware", "content_aware (the paper) | 2dgs | fixed_texture (baselines)")
    iterations: int = _f(30000, "training iterations")
    schedule_scale: float = _f(0.0, "0: every iteration count below is a fraction of the run (x iterations / 30000); "
                               "> 0: expert override, multiply them by this instead")
    scale_rules: bool = _f(True, "resolve pixel/texel settings for the training image size "
                           "(ctgs/train/config/rules.py); false: use them as written (the paper preset)")
    time_budget: float = _f(0.0, "> 0: plan (and re-plan) the iteration count so `ctgs train` ends within this "
                            "many minutes on this machine (overrides iterations)")
    max_params: int = _f(0, "> 0: a size budget: the model never ends with more parameters (SurfelModel.num_params) "
                         "than this; textures are coarsened where that loses least (texels.fit_texels) and splits "
                         "/ densification stop where even 2x2 textures would not fit (0 = none, the paper)")
    max_params_per_value: float = _f(0.0, "> 0 and max_params = 0: the size budget relative to the data, max_params "
                                     "= this x the observed values (RGB of every training pixel; rules."
                                     "with_size_budget); 0 = none (the paper)")
    preset: str = _f("", "the preset this config was built on (set by `ctgs train --preset`; informational)")
    # ---- initialisation ----
    max_init_points: int = _f(0, "farthest-point subsample SfM points above this count (0 = keep all)")
    primitives_per_pixel: float = _f(0.0, "> 0: at most this many primitives per pixel of a training image, at "
                                     "initialisation and through splits (caps max_primitives; 0 = no cap, the paper)")
    baseline_primitives_per_pixel: float = _f(0.0, "the baselines' (2dgs, fixed_texture) primitives_per_pixel: > 0, "
                                              "their densification stops at this many primitives per pixel of a "
                                              "training image (x the capture's view coverage) and their initial "
                                              "points are subsampled to it (0 = no cap, the paper)")
    init_opacity: float = _f(0.1, "initial opacity")
    random_rotation: bool = _f(True, "random initial rotations (else identity)")
    init_shell: int = _f(0, "> 0: add up to this many initial points on a far shell, in directions the training "
                            "views see past the SfM points (sky), coloured by those pixels; never split or upscaled, "
                            "and shown in training renders only where the view sees past the SfM points "
                            "(ctgs.train.components.shell; off: -0.14..-0.19 dB on herzjesu25 384 px validation views)")
    init_fill: bool = _f(False, "add initial points in the 16-px cells of the training views that no SfM point "
                         "reaches, at the median depth of the 16 SfM points projecting nearest, coloured by the cell "
                         "(ctgs.train.start.fill; off: -0.21 dB on herzjesu25 384 px validation views)")
    init_normals: bool = _f(False, "orient initial surfels in the PCA plane of their 16 nearest SfM points "
                            "(overrides random_rotation; the paper starts from random rotations)")
    max_sh_degree: int = _f(3, "highest SH degree")
    sh_every: int = _f(1000, "iterations between SH degree increments (paper scale)")
    background: list = _f([0.0, 0.0, 0.0], "background colour [3]")
    random_background: bool = _f(False, "training renders over a random uniform colour each step (for scenes "
                                 "that cover every pixel; E, evaluation and exports use background)")
    # ---- optimiser ----
    lr_position_init: float = _f(1.6e-4, "position lr at the start, times scene extent")
    lr_position_final: float = _f(1.6e-6, "position lr at the end, times scene extent (exponential decay)")
    lr_sh_dc: float = _f(2.5e-3, "lr of the SH DC band")
    lr_sh_rest: float = _f(1.25e-4, "lr of the higher SH bands")
    lr_opacity: float = _f(0.05, "lr of opacity logits")
    lr_scale: float = _f(0.005, "lr of log scales")
    lr_scale_final: float = _f(0.0, "> 0: the log-scale lr decays exponentially from lr_scale at iteration 0 to this "
                               "at the last iteration (0 = constant lr_scale, the paper)")
    lr_rotation: float = _f(0.001, "lr of quaternions")
    lr_texture: float = _f(7e-4, "lr of raw texels (0 until texture_start)")
    lr_texture_final: float = _f(0.0, "> 0: the texel lr decays exponentially from lr_texture at texture_start "
                                 "to this at the last iteration (0 = constant lr_texture, the paper)")
    adam_eps: float = _f(1e-15, "Adam epsilon")
    # ---- loss ----
    lambda_ssim: float = _f(0.2, "weight of 1 - SSIM (L1 gets 1 - this)")
    lambda_opacity: float = _f(0.01, "opacity regulariser weight on mean(opacity)")
    opacity_reg_visible: bool = _f(True, "apply the opacity regulariser to the primitives the view rasterizes only "
                                   "(their opacities summed / N), as the authors' code does ((opacity x visibility)."
                                   "mean()); false = the mean over all primitives, which under Adam moves a primitive "
                                   "no view shows at the full learning rate and, with hundreds of training views, sinks "
                                   "the primitives of the views not drawn lately below the pruning threshold")
    lambda_texture: float = _f(1e-8, "texture sparsity weight on sum |texel| of visible primitives")
    texture_reg_transmittance: bool = _f(False, "weight each primitive's texel L1 by 1 - its mean transmittance in "
                                        "the view (the authors' README variant; the paper and their code use plain L1)")
    virtual_coverage: float = _f(0.0, "> 0: weight of a coverage term on virtual views half a camera step from each "
                                 "training camera: mean (1 - alpha) over the pixels the training cameras hold at every "
                                 "depth (ctgs.train.components.virtual; 0 = off, the paper)")
    virtual_every: int = _f(4, "steps between virtual-view coverage terms (each one more render and backward)")
    virtual_pixels: str = _f("held", "pixels of a virtual view the coverage term covers: held (some training image "
                             "holds them at every sampled depth) | few (of those, the ones some depth of which only "
                             "one or two training images hold)")
    lambda_normal: float = _f(0.0, "> 0: weight of 2DGS's depth-normal consistency term "
                              "(ctgs.train.components.normal: one more render per step; 2DGS uses 0.05; 0 = off, the paper)")
    normal_from: int = _f(7000, "first iteration of the depth-normal term (paper scale; 2DGS's)")
    lambda_dist: float = _f(0.0, "> 0: weight of 2DGS's depth-distortion term, the blending weights' spread along each "
                            "ray: mean over pixels of sum_i<j w_i w_j (z_i - z_j)^2 / z^2, z the expected depth "
                            "(ctgs.train.components.normal; the same extra render as lambda_normal; 0 = off, the paper)")
    dist_from: int = _f(3000, "first iteration of the depth-distortion term (paper scale; 2DGS's)")
    exposure_comp: bool = _f(False, "learn a per-channel gain per training image, applied to its training renders "
                             "before the loss (ctgs.train.components.exposure; evaluation and exports use none; "
                             "false = the paper)")
    lr_exposure: float = _f(5e-3, "lr of the exposure log-gains (Adam)")
    exposure_in_E: bool = _f(False, "scale each training view's render by its gain in the routines' error E too (as "
                             "in its loss), so that E does not hold the photos' exposures")
    exposure_check: float = _f(0.0, "> 0: at this fraction of the run, freeze the gains at 1 if none is more than "
                               "exposure_min_gain from 1 (a capture of one exposure); 0 = never")
    exposure_min_gain: float = _f(0.05, "relative gain below which exposure_check takes the photos for one exposure")
    exposure_channels: int = _f(3, "3: a gain per colour channel (exposure and white balance); 1: one gain per image "
                                "(exposure only)")
    # ---- content-aware texturing (paper sections 3.2-3.4) ----
    texture_start: int = _f(500, "iteration at which textures are allocated and optimised (paper scale)")
    start_texels: float = _f(8.0, "texels across the active extent when textures start")
    texture_steps_from_start: bool = _f(True, "the textures' Adam step count runs from the first iteration, as torch's "
                                        "Adam in the authors' code counts the steps of a learning rate of 0 before "
                                        "the texture start: no bias correction afterwards, so texels whose moments "
                                        "restart at zero move by up to several times the learning rate at first; "
                                        "false = counted from the texture start")
    start_exp_ceil: bool = _f(True, "texture start: the texel-size exponent is rounded up (coarser texels, the "
                              "authors' code); false = to the nearest")
    routine_every: int = _f(250, "iterations between routines (E, split, up/downscale, prune, k_min)")
    routine_until: int = _f(25000, "last full routine iteration (also capped at iterations - routine_margin)")
    routine_margin: int = _f(3000, "no full routines during the last this many iterations (paper scale)")
    late_downscale_every: int = _f(1000, "after routine_until: downscale + light prune only, this often")
    late_prune_every: int = _f(250, "after routine_until: a light prune (prune_opacity_late) and k_min this often "
                               "between the late downscales, as the authors' code does (paper scale); 0 = none")
    realloc_every: int = _f(100, "iterations between jagged texture reallocations")
    error_views: int = _f(0, "> 0: E from at most this many training views per full routine, drawn at random "
                          "without replacement, a new draw at every routine (an unbiased estimate of the paper's sums "
                          "at a fraction of the renders); 0 = every training view (the paper)")
    error_pixels: float = _f(0.0, "> 0: E from at most this many pixels per full routine (views x training image "
                             "size): error_views becomes at most error_pixels / HW views, at least 1 (rules.py), so a "
                             "routine costs the same renders at any image size; 0 = error_views as written")
    error_from_steps: bool = _f(False, "CPU backend: E from the training steps since the last full routine instead of "
                                "renders of training views at the routine: each step's backward also sums the "
                                "statistics of its loss's error image (with the step's exposure gain and "
                                "background), so a routine renders nothing; the model of each step is the one "
                                "it saw, not the routine's. Other backends, init_shell runs and a routine with "
                                "no step since the last one render E as error_views says; false = the paper")
    top_fraction: float = _f(0.1, "fraction of primitives with the largest E eligible for split/upscale")
    upscale_split_children: bool = _f(False, "a routine may upscale the children of its own splits (they inherit the "
                                      "parent's E); false = the authors' code, which zeroes the E of the primitives a "
                                      "split adds, so they are not upscaled in that routine and may be downscaled")
    upscale_after_split: bool = _f(True, "the upscale set is chosen after the split, as the authors' code does: E "
                                   "above its (1 - top_fraction) quantile over every primitive, E taken as 0 where "
                                   "the texel size is at its smallest (and for the split's children unless "
                                   "upscale_split_children); false = the split's candidates (the top fraction of E "
                                   "before it) that are left and can be upscaled")
    split_fresh_moments: bool = _f(True, "a split's children start with zero Adam moments, as the authors' code does "
                                   "(it appends them as new parameters); false = they inherit the parent's")
    texture_fresh_moments: bool = _f(True, "a texture a routine or reallocation resizes (upscale, downscale, a new "
                                     "needed size) restarts its Adam moments at zero, as the authors' code does; "
                                     "false = they are resampled with it")
    split_offset_truncated: bool = _f(True, "a split child's offset, 1/6 of the active extent, is truncated to whole "
                                      "texels, as the authors' code does; false = rounded")
    split_scale_cap: bool = _f(True, "a split child's scale on the split axis is at most tau_tr texels / 3, besides "
                               "halved, as the authors' code does; false = halved only")
    tau_ds: float = _f(0.02, "downscale threshold on the Gaussian-weighted reconstruction error E_d")
    downscale_thin: bool = _f(True, "downscale a texture 2 texels wide on one axis when the other is wider, as the "
                              "authors' code does (any axis above 2); false = only textures above 2 texels on both "
                              "axes")
    downscale_corners: bool = _f(True, "the downscale round trip (E_d and the texture kept) resamples with "
                                 "align_corners=True, as the authors' code does (a downscaled texture's content "
                                 "shrinks slightly towards its centre); false = texel centres kept")
    tau_tr_start: float = _f(64.0, "split threshold on active texture resolution at iteration 0")
    tau_tr_end: float = _f(32.0, "split threshold reached at tau_tr_iters")
    tau_tr_pixel_exponent: float = _f(0.0, "tau_tr_start/end x (HW / 1e6) ** this (rules.py): 0 keeps the paper's "
                                      "texel counts at every image size, 0.5 keeps split decisions at the same "
                                      "fraction of the image")
    tau_tr_iters: int = _f(7000, "iterations of the linear tau_tr decay (paper scale)")
    prune_opacity: float = _f(10.0 / 255.0, "prune below this opacity during routines")
    prune_opacity_late: float = _f(1.0 / 255.0, "prune threshold after routine_until")
    prune_opacity_final: float = _f(1.0 / 255.0, "after the last iteration, before the model is evaluated and "
                                    "saved, prune below this opacity (the authors' save does); 0 = none")
    content_opacity_reset: bool = _f(False, "content-aware runs: at the first full routine at or past each multiple "
                                     "of opacity_reset_every (up to densify_until), after the routine, clamp "
                                     "opacities to <= 2 x prune_opacity (3DGS's ratio of reset value to prune "
                                     "threshold, 0.01 / 0.005; at least 0.01) and zero their Adam moments; the next "
                                     "full routine prunes what the training views did not bring back (false = the "
                                     "paper: no reset)")
    max_primitives: int = _f(0, "primitive budget: no splits beyond it (0 = unlimited)")
    max_texture_res: int = _f(256, "hard cap on texels per axis")
    texture_alloc: str = _f("pow2", "texture allocation rounding: pow2 (authors' code) | mult4 (a multiple of 4: "
                            "fewer padding texels, every downscaled size still even)")
    texture_sigma: float = _f(3.0, "textures cover at most +-this many standard deviations (the renderer's cutoff "
                              "is 3; beyond the texture a surfel shows its SH colour)")
    texture_trim: float = _f(0.0, "> 0: after the last iteration, crop every texture symmetrically to the texels "
                             "whose activated offset reaches this in some channel, dropping textures with none "
                             "(rendered colours move by less than this; 0 = off, the paper)")
    min_t2p_exp: int = _f(1, "smallest texel-size exponent: texel >= 2**this pixels of the closest camera")
    # ---- baselines (2dgs, fixed_texture): 3DGS-style densification ----
    fixed_texture_res: int = _f(16, "texels per axis of the fixed_texture baseline")
    densify_from: int = _f(500, "first densification iteration (paper scale)")
    densify_until: int = _f(15000, "last densification iteration (paper scale)")
    densify_every: int = _f(100, "iterations between densifications (paper scale)")
    densify_grad_threshold: float = _f(0.0002, "view-space positional gradient threshold (3DGS NDC units)")
    percent_dense: float = _f(0.01, "clone if max scale <= this * extent, else split")
    opacity_reset_every: int = _f(3000, "iterations between opacity resets (paper scale)")
    densify_min_steps: int = _f(100, "fewest training steps between densifications, however short the run: a "
                                "shorter scaled period stretches densify_every and opacity_reset_every alike, so the "
                                "gradient statistic spans as many views and the model as many steps to answer as in "
                                "the paper's 30k (100: its own period; 0 = a pure fraction of the run)")
    prune_opacity_2dgs: float = _f(0.05, "baseline prune threshold (2DGS's opacity_cull, also gsplat's 2DGS "
                                   "trainer; 3DGS prunes at 0.005)")
    # ---- logging / checkpoints ----
    log_every: int = _f(10, "iterations between JSON-lines step records")
    test_every: int = _f(1000, "iterations between test-view PSNR evaluations (0 = only at the end)")
    test_lpips: bool = _f(False, "also score LPIPS (VGG) at each periodic test evaluation, for curves over iterations "
                                 "(about 0.1 s per 200x133 view on a CPU core; the final evaluation of `ctgs eval` always has it)")
    checkpoint_every: int = _f(1000, "iterations between atomic checkpoints (0 = only at the end)")
    checkpoint_first_s: float = _f(60.0, "wall seconds of training (from the first step, the start-up not "
                                   "counted) after which a run without any checkpoint yet writes one, whatever "
                                   "checkpoint_every says (0 = off)")
    checkpoint_every_s: float = _f(600.0, "wall seconds at most between checkpoints: one is written when this long "
                                   "has passed since the last, so a kill -9 loses at most this much (0 = off)")
    debug_nan_at: int = _f(0, "testing hook: poison the loss with NaN at this iteration (0 = off)")

    def validate(self) -> None:
        """Raise UserError naming the first key whose value is out of range."""
        if self.method not in METHODS:
            raise UserError(f"config method={self.method!r}: use one of {', '.join(METHODS)}")
        if self.backend not in ("auto", "cpu", "cuda", "reference"):
            raise UserError(f"config backend={self.backend!r}: use auto, cpu, cuda or reference")
        if self.device not in ("auto", "cpu", "cuda"):
            raise UserError(f"config device={self.device!r}: use auto, cpu or cuda")
        if self.texture_alloc not in ("pow2", "mult4"):
            raise UserError(f"config texture_alloc={self.texture_alloc!r}: use pow2 or mult4")
        if self.virtual_pixels not in ("held", "few"):
            raise UserError(f"config virtual_pixels={self.virtual_pixels!r}: use held or few")
        if len(self.background) != 3:
            raise UserError("config background must be a list of 3 numbers")
        for key, ok, what in _RANGES:
            value = getattr(self, key)
            if not ok(value):
                raise UserError(f"config {key}={value!r}: must be {what}")

    def to_dict(self) -> dict:
        return asdict(self)


# (key, check, what the value must be): every numeric key has a range.
def _ge(lo):
    return lambda v: v >= lo


def _gt(lo):
    return lambda v: v > lo


def _unit_open_closed(v):
    return 0 < v <= 1


def _prob(v):
    return 0 <= v < 1


_RANGES = [
    ("iterations", _ge(1), ">= 1"), ("schedule_scale", _ge(0), ">= 0 (0 = iterations / 30000)"),
    ("time_budget", _ge(0), ">= 0 minutes (0 = none)"), ("holdout", _ge(0), ">= 0"), ("validation_holdout", _ge(0), ">= 0"), ("init_shell", _ge(0), ">= 0"), ("threads", _ge(0), ">= 0"),
    ("max_init_points", _ge(0), ">= 0"), ("primitives_per_pixel", _ge(0), ">= 0 (0 = no cap)"), ("baseline_primitives_per_pixel", _ge(0), ">= 0 (0 = no cap)"), ("init_opacity", lambda v: 0 < v < 1, "in (0, 1)"),
    ("max_sh_degree", lambda v: 0 <= v <= 3, "in 0..3"), ("sh_every", _gt(0), "> 0"),
    ("lr_position_init", _ge(0), ">= 0"), ("lr_position_final", _gt(0), "> 0 (exponential decay)"),
    ("lr_sh_dc", _ge(0), ">= 0"), ("lr_sh_rest", _ge(0), ">= 0"), ("lr_opacity", _ge(0), ">= 0"),
    ("lr_scale", _ge(0), ">= 0"), ("lr_rotation", _ge(0), ">= 0"), ("lr_texture", _gt(0), "> 0"),
    ("lr_texture_final", _ge(0), ">= 0 (0 = constant lr_texture)"),
    ("lr_scale_final", _ge(0), ">= 0 (0 = constant lr_scale)"), ("adam_eps", _gt(0), "> 0"),
    ("lambda_ssim", lambda v: 0 <= v <= 1, "in [0, 1]"), ("lambda_opacity", _ge(0), ">= 0"),
    ("error_views", _ge(0), ">= 0 (0 = every view)"),
    ("error_pixels", _ge(0), ">= 0 (0 = off)"),
    ("lambda_texture", _ge(0), ">= 0"), ("lambda_normal", _ge(0), ">= 0"),
    ("normal_from", _ge(0), ">= 0"), ("lambda_dist", _ge(0), ">= 0"), ("dist_from", _ge(0), ">= 0"),
    ("lr_exposure", _ge(0), ">= 0"),
    ("exposure_channels", lambda v: v in (1, 3), "1 or 3"), ("exposure_check", lambda v: 0 <= v < 1, "in [0, 1)"),
    ("exposure_min_gain", _ge(0), ">= 0"), ("virtual_coverage", _ge(0), ">= 0 (0 = off)"),
    ("virtual_every", _ge(1), ">= 1"), ("texture_start", _ge(0), ">= 0"), ("start_texels", _gt(0), "> 0"),
    ("routine_every", _gt(0), "> 0"), ("routine_until", _ge(0), ">= 0"), ("routine_margin", _ge(0), ">= 0"),
    ("late_downscale_every", _gt(0), "> 0"), ("late_prune_every", _ge(0), ">= 0 (0 = none)"),
    ("realloc_every", _gt(0), "> 0"),
    ("top_fraction", _unit_open_closed, "in (0, 1]"), ("tau_ds", _gt(0), "> 0"),
    ("tau_tr_start", _gt(0), "> 0 texels"), ("tau_tr_end", _gt(0), "> 0 texels"), ("tau_tr_iters", _gt(0), "> 0"),
    ("tau_tr_pixel_exponent", lambda v: 0 <= v <= 1, "in [0, 1]"),
    ("prune_opacity", _prob, "in [0, 1)"), ("prune_opacity_late", _prob, "in [0, 1)"),
    ("prune_opacity_final", _prob, "in [0, 1)"),
    ("max_primitives", _ge(0), ">= 0 (0 = unlimited)"), ("max_params", _ge(0), ">= 0 (0 = no budget)"),
    ("max_params_per_value", _ge(0), ">= 0 (0 = no budget)"),
    ("max_texture_res", lambda v: v >= 2 and (v & (v - 1)) == 0, "a power of two >= 2"),
    ("min_t2p_exp", lambda v: 0 <= v <= 30, "in 0..30"),
    ("texture_sigma", lambda v: 0 < v <= 3, "in (0, 3] standard deviations"), ("fixed_texture_res", _ge(1), ">= 1"),
    ("texture_trim", lambda v: 0 <= v < 1, "in [0, 1) (activated texel units)"),
    ("densify_from", _ge(0), ">= 0"), ("densify_until", _ge(0), ">= 0"), ("densify_every", _gt(0), "> 0"),
    ("densify_grad_threshold", _gt(0), "> 0"), ("percent_dense", _gt(0), "> 0"),
    ("opacity_reset_every", _gt(0), "> 0"), ("densify_min_steps", _ge(0), ">= 0"), ("prune_opacity_2dgs", _prob, "in [0, 1)"),
    ("log_every", _ge(1), ">= 1"), ("test_every", _ge(0), ">= 0 (0 = only at the end)"),
    ("checkpoint_every", _ge(0), ">= 0 (0 = only at the end)"), ("checkpoint_first_s", _ge(0), ">= 0 (0 = off)"),
    ("checkpoint_every_s", _ge(0), ">= 0 (0 = off)"), ("debug_nan_at", _ge(0), ">= 0"),
]


def field_names() -> dict[str, object]:
    return {f.name: f for f in fields(TrainConfig)}


def describe_keys() -> list[tuple[str, object, str]]:
    """(key, default, help) for every config key, in declaration order (`ctgs train --list-keys`)."""
    d = TrainConfig()
    return [(f.name, getattr(d, f.name), f.metadata.get("help", "")) for f in fields(TrainConfig)
            if f.name not in ("scene_dir", "debug_nan_at")]


def _unknown_key(key: str, source: str) -> UserError:
    close = difflib.get_close_matches(key, list(field_names()), n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return UserError(f"{source}: unknown config key {key!r}{hint} (`ctgs train --list-keys` lists every key)")


def apply_overrides(cfg: TrainConfig, values: dict, source: str) -> TrainConfig:
    """Set `values` on `cfg`; an unknown key or a value of the wrong type is a UserError naming it."""
    known = field_names()
    for key, value in values.items():
        if key not in known:
            raise _unknown_key(key, source)
        current = getattr(cfg, key)
        setattr(cfg, key, _coerce(key, value, current, source))
    return cfg


def _coerce(key: str, value, current, source: str):
    if isinstance(current, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(current, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif isinstance(current, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif isinstance(current, str):
        if isinstance(value, str):
            return value
    elif isinstance(current, list):
        if isinstance(value, list):
            return [float(v) for v in value]
    raise UserError(f"{source}: config key {key!r} expects {type(current).__name__}, got {value!r}")


def parse_set(items: list[str]) -> dict:
    """`["lr_scale=0.01", "method=2dgs"]` -> dict; values are parsed as Python/TOML literals, else strings."""
    out = {}
    for item in items:
        if "=" not in item:
            raise UserError(f"--set {item!r}: expected key=value")
        key, raw = item.split("=", 1)
        raw = raw.strip()
        low = raw.lower()
        if low in ("true", "false"):
            value = low == "true"
        else:
            try:
                value = ast.literal_eval(raw)
            except (ValueError, SyntaxError):
                value = raw
        out[key.strip()] = value
    return out


def load_toml(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise UserError(f"{path}: config file not found; pass an existing file (see configs/)") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:  # a damaged file may not even be UTF-8
        raise UserError(f"{path}: invalid TOML ({exc}); fix the file") from None
    # `base = "default.toml"` lets an experiment name only what it changes.
    return data


PRESETS = ("preview", "fast", "balanced", "paper")


def config_path(name_or_path: str) -> str:
    """A path stays a path; a bare name (`default`, `2dgs`, `fast`) is the shipped configs/<name>.toml."""
    return resolve_config(name_or_path)


def _apply_file(cfg: TrainConfig, path: str) -> None:
    """Apply a TOML file and the chain of `base` files it names (relative to the file), base first."""
    chain = []
    p = path
    while p:
        data = load_toml(p)
        chain.append((p, data))
        base = data.pop("base", None)
        p = os.path.join(os.path.dirname(p), base) if base else None
        if len(chain) > 8:
            raise UserError(f"{path}: config `base` chain too deep (a cycle?)")
    for src, data in reversed(chain):
        apply_overrides(cfg, data, src)


def load_config(path: str | None = None, overrides: dict | None = None, preset: str | None = None) -> TrainConfig:
    """Defaults (the paper) <- preset configs/<preset>.toml <- config file (with optional `base`) <- overrides."""
    cfg = TrainConfig()
    if preset:
        if preset not in PRESETS:
            raise UserError(f"--preset {preset}: use one of {', '.join(PRESETS)}")
        _apply_file(cfg, config_path(preset))
        cfg.preset = preset
    if path:
        _apply_file(cfg, config_path(path))
    if overrides:
        apply_overrides(cfg, overrides, "--set")
    cfg.validate()
    return cfg
