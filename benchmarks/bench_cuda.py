"""CUDA kernel benchmark: our backend (textures off / on) against gsplat's `rasterization_2dgs`, side by side.

One process, one GPU, identical surfels for both renderers, timed with CUDA events (median of --reps after
--warmup), the renderers interleaved in --rounds rounds so that drift of a shared card shows as the spread
between rounds. Per scene size N (default 200k and 1M at 1920x1080):

  fwd      one full render from world-space inputs (SH degree 3 -> colour, projection, binning and sort,
           rasterization), no autograd graph;
  fwd+bwd  the same with gradients: forward, then backward of sum(rgb * fixed random cotangent) w.r.t.
           means, quats, scales, opacities, SH (and textures);
  memory   peak CUDA memory allocated during one fwd+bwd above what the inputs hold.

Renderers: `ours` (ctgs backend "cuda", tex_res 0: no textures), `ours_torchpre` (--torch-preprocess-too: the same
with the per-primitive preprocessing in PyTorch ops, as before kernels/cuda/dense.cu), `ours_tex` (the same surfels with textures
of the paper's size distribution, 30-450 texels per primitive, log-uniform), `gsplat` (gsplat
rasterization_2dgs, render_mode "RGB+D" so that it also returns alpha and accumulated depth, as ours does;
its 2DGS kernel also renders normals and distortion, which it always does). Variants, each against its default
in the same run: `ours_mbK` / `ours_tex_mbK` (--bwd-min-blocks K: the backward kernel compiled for K blocks per
SM; the default is 3, at most 80 registers; 1 is the uncapped kernel), `ours_tex_noagg` (--tex-agg-off-too: texel gradients with one atomic per lane), `ours_syncval` /
`ours_tex_syncval` (--checks-one-by-one-too: the input checks with one synchronisation each, as before).

The surfels look like a trained scene, not a uniform cloud: depths log-uniform in [2, 20] over a frustum
slightly wider than the view, random orientations, projected standard deviations log-normal (median set
so that the 3-sigma footprints cover each pixel --depth-complexity times on average, as more primitives
in a real scene means smaller ones), opacities bimodal (40% in [0.9, 1], the rest sigmoid(N(-1, 2))).
The script measures and reports what that gives: (tile, primitive) pairs, pairs per pixel, primitives
blended per pixel.

--profile adds a torch.profiler table of the CUDA kernels of 3 fwd+bwd at the largest N, for ours
untextured and textured (the slowest kernels first).

    python benchmarks/bench_cuda.py --out DIR                # needs a CUDA GPU; gsplat optional
    GSPLAT_PREBUILT=/path/gsplat_cuda.so python benchmarks/bench_cuda.py --out DIR
    python benchmarks/bench_cuda.py --out DIR --device cpu --sizes 2000 --width 128 --height 96   # dry run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ctgs.render import Camera, SurfelInputs, render  # noqa: E402

SH_C0 = 0.28209479177387814


def import_gsplat():
    """gsplat's rasterization_2dgs, or None. GSPLAT_PREBUILT names a compiled gsplat_cuda.so to use instead of
    gsplat's JIT build (built elsewhere for this torch/CUDA/Python)."""
    prebuilt = os.environ.get("GSPLAT_PREBUILT")
    if prebuilt:
        import importlib.util

        spec = importlib.util.spec_from_file_location("gsplat_cuda", prebuilt)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        sys.modules["gsplat.csrc"] = mod
    try:
        import gsplat
        from gsplat.rendering import rasterization_2dgs

        return rasterization_2dgs, getattr(gsplat, "__version__", "?")
    except Exception as exc:  # noqa: BLE001 - report why and go on without it
        print(f"bench_cuda: gsplat unavailable ({type(exc).__name__}: {exc})", file=sys.stderr)
        return None, None


def make_scene(n: int, width: int, height: int, *, seed: int, device, depth_complexity: float,
               textured: bool, dtype=torch.float32):
    """World-space surfels in front of an identity camera (see the module docstring) -> (SurfelInputs, Camera,
    description dict). textured=False: tex_res 0 (no textures)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    fx = 0.5 * width / math.tan(math.radians(35.0))  # 70 degree horizontal field of view
    fy = fx
    depth = torch.exp(math.log(2.0) + (math.log(20.0) - math.log(2.0)) * r(n))
    x = (r(n) - 0.5) * 1.15 * depth * width / fx
    y = (r(n) - 0.5) * 1.15 * depth * height / fy
    means = torch.stack([x, y, depth], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    # Projected sigma in pixels: log-normal, s = 0.9; E[sigma^2] = m^2 exp(2 s^2). Median m from
    # n * pi * (3 sigma)^2 = depth_complexity * W * H.
    s_ln = 0.9
    m = math.sqrt(depth_complexity * width * height / (n * math.pi * 9.0 * math.exp(2 * s_ln * s_ln)))
    sigma_px = m * torch.exp(s_ln * torch.randn(n, 2, generator=g, dtype=torch.float64))
    scales = sigma_px * depth[:, None] / fx
    opaque = r(n) < 0.4
    opacities = torch.where(opaque, 0.9 + 0.1 * r(n),
                            torch.sigmoid(-1.0 + 2.0 * torch.randn(n, generator=g, dtype=torch.float64)))
    sh = torch.zeros(n, 16, 3, dtype=torch.float64)
    sh[:, 0] = (r(n, 3) - 0.5) / SH_C0 * 0.8
    sh[:, 1:] = 0.05 * torch.randn(n, 15, 3, generator=g, dtype=torch.float64)
    if textured:
        texels = torch.exp(math.log(30.0) + (math.log(450.0) - math.log(30.0)) * r(n))
        aspect = (scales[:, 0] / scales[:, 1]).clamp(0.25, 4.0)
        res_u = torch.sqrt(texels * aspect).round().clamp(2, 64)
        res_v = (texels / res_u).round().clamp(2, 64)
        res = torch.stack([res_u, res_v], -1).to(torch.int32)
        sizes = res[:, 0].long() * res[:, 1].long()
        offset = torch.cumsum(sizes, 0) - sizes
        textures = 0.3 * (torch.rand(int(sizes.sum()), 3, generator=g, dtype=torch.float32) - 0.5)
        texel = 6.0 * scales / res.to(torch.float64)  # the grid covers +-3 sigma along each axis
    else:
        res = torch.zeros(n, 2, dtype=torch.int32)
        offset = torch.zeros(n, dtype=torch.int64)
        textures = torch.zeros(0, 3, dtype=torch.float32)
        texel = 6.0 * scales / 8.0
        sizes = torch.zeros(n, dtype=torch.int64)
    s = SurfelInputs(means=means.to(dtype), quats=quats.to(dtype), scales=scales.to(dtype),
                     opacities=opacities.to(dtype), sh=sh.to(dtype), texel_size=texel.to(dtype),
                     textures=textures.to(dtype), tex_res=res, tex_offset=offset)
    s = SurfelInputs(**{k: v.to(device) for k, v in vars(s).items()})
    cam = Camera(fx=fx, fy=fy, cx=width / 2, cy=height / 2, width=width, height=height,
                 viewmat=torch.eye(4, dtype=dtype, device=device), near=0.01)
    desc = {"n": n, "width": width, "height": height, "sigma_px_median": m, "depth_complexity_3sigma": depth_complexity,
            "opacity_mean": float(opacities.mean()), "texels": int(sizes.sum()),
            "texels_per_primitive_median": float(sizes.double().median()) if textured else 0.0}
    return s, cam, desc


def with_grad(s: SurfelInputs, textured: bool) -> SurfelInputs:
    names = ["means", "quats", "scales", "opacities", "sh"] + (["textures"] if textured else [])
    d = dict(vars(s))
    for k in names:
        d[k] = d[k].detach().clone().requires_grad_(True)
    return SurfelInputs(**d)


class _TorchPreprocess:
    """Inside: the per-primitive preprocessing (camera space, SH colour) in PyTorch ops instead of the CUDA
    kernels of kernels/cuda/dense.cu: the backend as it was before those kernels (the `ours_torchpre` rows)."""

    def __enter__(self):
        import ctgs.ops.ext_cuda as ec

        self._saved, ec.cuda_fusable = getattr(ec, "cuda_fusable", None), lambda *t: False
        return self

    def __exit__(self, *exc):
        import ctgs.ops.ext_cuda as ec

        if self._saved is not None:
            ec.cuda_fusable = self._saved


class _Variant:
    """Inside: environment variables set (CTGS_CUDA_BWD_MIN_BLOCKS: the register-capped backward kernels) and,
    with checks_one_by_one, the render's value checks synchronising once per check as before
    api._values_ok_device (the `ours_syncval` rows)."""

    def __init__(self, env: dict | None, checks_one_by_one: bool):
        self.env, self.one_by_one = env or {}, checks_one_by_one

    def __enter__(self):
        import ctgs.render.api as api

        self._old_env = {k: os.environ.get(k) for k in self.env}
        os.environ.update(self.env)
        self._saved = api._values_ok_device
        if self.one_by_one:
            api._values_ok_device = lambda *a: False
        return self

    def __exit__(self, *exc):
        import ctgs.render.api as api

        api._values_ok_device = self._saved
        for k, v in self._old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class Ours:
    def __init__(self, s, cam, textured, device, torch_preprocess: bool = False, env: dict | None = None,
                 checks_one_by_one: bool = False):
        self.s, self.cam, self.textured = s, cam, textured
        self.torch_preprocess = torch_preprocess
        self.env, self.one_by_one = env, checks_one_by_one
        self.backend = "cuda" if device.type == "cuda" else "cpu"
        self.sg = with_grad(s, textured)
        g = torch.Generator().manual_seed(123)
        self.cot = torch.rand(cam.height, cam.width, 3, generator=g).to(device) - 0.3
        self.grad_inputs = [getattr(self.sg, k) for k in ("means", "quats", "scales", "opacities", "sh")] + (
            [self.sg.textures] if textured else [])

    def _ctx(self):
        import contextlib

        stack = contextlib.ExitStack()
        if self.torch_preprocess:
            stack.enter_context(_TorchPreprocess())
        if self.env or self.one_by_one:
            stack.enter_context(_Variant(self.env, self.one_by_one))
        return stack

    def fwd(self):
        with torch.no_grad(), self._ctx():
            return render(self.s, self.cam, backend=self.backend, sh_degree=3)

    def fwd_bwd(self):
        with self._ctx():
            out = render(self.sg, self.cam, backend=self.backend, sh_degree=3)
            return torch.autograd.grad((out.rgb * self.cot).sum(), self.grad_inputs)


class Gsplat:
    def __init__(self, fn, s, cam, device):
        self.fn = fn
        # gsplat 2DGS scales are [N, 3]; the third (normal) axis is unused by its 2DGS kernels.
        self.args = dict(means=s.means, quats=s.quats, scales=torch.cat([s.scales, s.scales[:, :1] * 0 + 1e-6], 1),
                         opacities=s.opacities, colors=s.sh)
        self.viewmats = cam.viewmat[None]
        self.Ks = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=s.means.dtype,
                               device=device)[None]
        self.cam = cam
        self.grad_args = {k: v.detach().clone().requires_grad_(True) for k, v in self.args.items()}
        g = torch.Generator().manual_seed(123)
        self.cot = (torch.rand(cam.height, cam.width, 3, generator=g).to(device) - 0.3)

    def _call(self, args):
        return self.fn(**args, viewmats=self.viewmats, Ks=self.Ks, width=self.cam.width, height=self.cam.height,
                       near_plane=0.01, sh_degree=3, render_mode="RGB+D")

    def fwd(self):
        with torch.no_grad():
            return self._call(self.args)

    def fwd_bwd(self):
        out = self._call(self.grad_args)
        rgb = out[0][0, ..., :3]
        return torch.autograd.grad((rgb * self.cot).sum(), list(self.grad_args.values()))


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_ms(fn, device, reps: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        fn()
    sync(device)
    times = []
    for _ in range(reps):
        if device.type == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b))
        else:
            t0 = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - t0))
    return times


def peak_mb(fn, device) -> float | None:
    if device.type != "cuda":
        return None
    sync(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    out = fn()
    sync(device)
    peak = torch.cuda.max_memory_allocated(device) - base
    del out
    return peak / 2**20


def scene_stats(s, cam, device) -> dict:
    """Primitives blended per pixel, mean alpha and primitives rasterized for this scene (ours, textures off)."""
    with torch.no_grad():
        out = render(s, cam, backend="cuda" if device.type == "cuda" else "cpu", sh_degree=3,
                     error_image=torch.zeros(cam.height, cam.width, device=device))
    blended = float(out.stats.count.double().sum()) / (cam.width * cam.height)
    return {"blended_per_pixel": blended, "alpha_mean": float(out.alpha.mean()),
            "primitives_rasterized": int(out.rasterized.sum())}


def tile_pairs(s, cam, device) -> int:
    from ctgs.render.preprocess import to_camera_space

    if device.type != "cuda":
        return -1
    from ctgs.ops.ext_cuda import load_cuda

    load_cuda()
    with torch.no_grad():
        p = to_camera_space(s.means, s.quats, s.sh, cam, 3)
        k = s.texel_size if s.texel_size.ndim == 2 else s.texel_size[:, None].expand(-1, 2)
        outs = torch.ops.ctgs.rasterize_forward(
            p.mu_c.contiguous(), p.Rc.contiguous(), s.scales.contiguous(), s.opacities.contiguous(),
            p.colors.contiguous(), k.contiguous(), s.textures.contiguous(), s.tex_res.contiguous(),
            s.tex_offset.contiguous(), torch.zeros(3, device=device), float(cam.fx), float(cam.fy), float(cam.cx),
            float(cam.cy), int(cam.width), int(cam.height), float(cam.near), None, 0, False)
    return int(outs[6].numel())


def profile_table(fn, device, label: str, out_dir: Path) -> list[dict]:
    from torch.profiler import ProfilerActivity, profile

    fn()
    sync(device)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(3):
            fn()
        sync(device)
    ka = prof.key_averages()
    key = "self_device_time_total" if hasattr(ka[0], "self_device_time_total") else "self_cuda_time_total"
    rows = []
    for e in ka:
        t = getattr(e, key, 0.0)
        if t and t > 0:
            rows.append({"name": e.key, "self_cuda_ms_per_iter": t / 1e3 / 3, "calls_per_iter": e.count / 3})
    rows.sort(key=lambda r: -r["self_cuda_ms_per_iter"])
    (out_dir / f"profile_{label}.txt").write_text(ka.table(sort_by=key, row_limit=25))
    return rows[:15]


def machine_info(device) -> dict:
    info = {"host": platform.node(), "torch": torch.__version__, "cuda": torch.version.cuda,
            "python": platform.python_version()}
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        info.update(gpu=p.name, sms=p.multi_processor_count, memory_gb=round(p.total_memory / 2**30, 1))
        try:
            info["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                            capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            info["driver"] = "?"
    return info


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sizes", default="200000,1000000")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--depth-complexity", type=float, default=20.0)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--tag", default="")
    ap.add_argument("--torch-preprocess-too", action="store_true",
                    help="also time `ours_torchpre`: the per-primitive preprocessing in PyTorch ops (before the "
                         "CUDA kernels of kernels/cuda/dense.cu)")
    ap.add_argument("--bwd-min-blocks", default="",
                    help="also time the backward kernel compiled for these blocks per SM (1: uncapped, 4; the default "
                         "is 3; rows ours_mbK, ours_tex_mbK; CTGS_CUDA_BWD_MIN_BLOCKS)")
    ap.add_argument("--tex-agg-off-too", action="store_true",
                    help="also time `ours_tex_noagg`: texel gradients with one atomic per lane (CTGS_CUDA_TEX_AGG=0)")
    ap.add_argument("--sh-lanes-too", action="store_true",
                    help="also time `ours_shlanes`, `ours_tex_shlanes`: the SH backward with lanes per coefficient "
                         "(CTGS_CUDA_SH_LANES=1)")
    ap.add_argument("--checks-one-by-one-too", action="store_true",
                    help="also time `ours_syncval`: the render's value checks one synchronisation each, as before "
                         "ctgs.render.api._values_ok_device")
    args = ap.parse_args()
    device = torch.device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    gs_fn, gs_version = (None, None) if args.no_gsplat or device.type != "cuda" else import_gsplat()
    result = {"machine": machine_info(device), "args": {k: str(v) for k, v in vars(args).items()},
              "gsplat": gs_version, "command": " ".join(sys.argv), "scenes": []}
    print(json.dumps(result["machine"]), flush=True)
    for n in [int(x) for x in args.sizes.split(",")]:
        s0, cam, desc = make_scene(n, args.width, args.height, seed=0, device=device,
                                   depth_complexity=args.depth_complexity, textured=False)
        st, _, desc_t = make_scene(n, args.width, args.height, seed=0, device=device,
                                   depth_complexity=args.depth_complexity, textured=True)
        desc["texels_textured"] = desc_t["texels"]
        desc["texels_per_primitive_median_textured"] = desc_t["texels_per_primitive_median"]
        desc.update(scene_stats(s0, cam, device))
        desc["pairs"] = tile_pairs(s0, cam, device)
        desc["pairs_per_pixel"] = desc["pairs"] / (args.width * args.height) if desc["pairs"] > 0 else None
        runners = {"ours": Ours(s0, cam, False, device), "ours_tex": Ours(st, cam, True, device)}
        if args.torch_preprocess_too:
            runners["ours_torchpre"] = Ours(s0, cam, False, device, torch_preprocess=True)
        if args.checks_one_by_one_too:
            runners["ours_syncval"] = Ours(s0, cam, False, device, checks_one_by_one=True)
            runners["ours_tex_syncval"] = Ours(st, cam, True, device, checks_one_by_one=True)
        if args.tex_agg_off_too:
            runners["ours_tex_noagg"] = Ours(st, cam, True, device, env={"CTGS_CUDA_TEX_AGG": "0"})
        if args.sh_lanes_too:
            runners["ours_shlanes"] = Ours(s0, cam, False, device, env={"CTGS_CUDA_SH_LANES": "1"})
            runners["ours_tex_shlanes"] = Ours(st, cam, True, device, env={"CTGS_CUDA_SH_LANES": "1"})
        for k in [x for x in args.bwd_min_blocks.split(",") if x.strip()]:
            env = {"CTGS_CUDA_BWD_MIN_BLOCKS": k.strip()}
            runners[f"ours_mb{k.strip()}"] = Ours(s0, cam, False, device, env=env)
            runners[f"ours_tex_mb{k.strip()}"] = Ours(st, cam, True, device, env=env)
        if gs_fn is not None:
            runners["gsplat"] = Gsplat(gs_fn, s0, cam, device)
        times: dict[str, dict[str, list[list[float]]]] = {k: {"fwd": [], "fwd_bwd": []} for k in runners}
        for rnd in range(args.rounds):
            for name, rr in runners.items():
                for what in ("fwd", "fwd_bwd"):
                    try:
                        t = time_ms(getattr(rr, what), device, args.reps, args.warmup)
                    except Exception as exc:  # noqa: BLE001 - record and go on with the others
                        print(f"bench_cuda: {name} {what} N={n} failed: {type(exc).__name__}: {exc}", flush=True)
                        t = []
                    times[name][what].append(t)
                    if t:
                        print(f"N={n} round {rnd} {name:9s} {what:8s} median {statistics.median(t):8.3f} ms",
                              flush=True)
        mem = {}
        for name, rr in runners.items():
            try:
                mem[name] = peak_mb(rr.fwd_bwd, device)
            except Exception as exc:  # noqa: BLE001
                print(f"bench_cuda: memory {name} failed: {exc}", flush=True)
                mem[name] = None
        med = {k: {w: [statistics.median(t) if t else None for t in v[w]] for w in v} for k, v in times.items()}
        entry = {"scene": desc, "median_ms_per_round": med, "peak_mb_fwd_bwd": mem,
                 "raw_ms": times}
        best = {k: {w: (min(x for x in v if x is not None) if any(x is not None for x in v) else None)
                    for w, v in d.items()} for k, d in med.items()}
        ratios = {}
        for w in ("fwd", "fwd_bwd"):
            if "gsplat" in best and best["gsplat"][w] and best["ours"][w]:
                ratios[f"ours/gsplat {w}"] = best["ours"][w] / best["gsplat"][w]
            if best["ours"][w] and best["ours_tex"][w]:
                ratios[f"ours_tex/ours {w}"] = best["ours_tex"][w] / best["ours"][w]
            for k in [k for k in best if k not in ("ours", "ours_tex", "gsplat")]:
                base = "ours_tex" if k.startswith("ours_tex") else "ours"
                if best[k][w] and best[base][w]:
                    ratios[f"{k}/{base} {w}"] = best[k][w] / best[base][w]
                if "gsplat" in best and best["gsplat"][w] and best[k][w] and base == "ours":
                    ratios[f"{k}/gsplat {w}"] = best[k][w] / best["gsplat"][w]
        entry["best_median_ms"] = best
        entry["ratios"] = ratios
        print(f"N={n}: {json.dumps(ratios)}", flush=True)
        if args.profile and n == max(int(x) for x in args.sizes.split(",")) and device.type == "cuda":
            entry["profile"] = {}
            for name in [k for k in ("ours", "ours_tex", "ours_torchpre") if k in runners]:
                try:
                    entry["profile"][name] = profile_table(runners[name].fwd_bwd, device, f"{name}_{n}{args.tag}",
                                                           args.out)
                except Exception as exc:  # noqa: BLE001
                    print(f"bench_cuda: profile {name} failed: {exc}", flush=True)
        result["scenes"].append(entry)
        del runners, s0, st
        if device.type == "cuda":
            torch.cuda.empty_cache()
        (args.out / f"bench_cuda{args.tag}.json").write_text(json.dumps(result, indent=1) + "\n")
    (args.out / f"bench_cuda{args.tag}.md").write_text(to_markdown(result))
    print(to_markdown(result))
    return 0


def to_markdown(result: dict) -> str:
    m = result["machine"]
    lines = ["# CUDA renderer: ours vs gsplat rasterization_2dgs", "",
             f"Machine: {m.get('gpu', m.get('host'))} (driver {m.get('driver', '-')}), torch {m['torch']}, CUDA "
             f"{m['cuda']}, Python {m['python']}; gsplat {result['gsplat']}. Command: `{result['command']}`.", "",
             "Median ms of each round (CUDA events); ratios from the best round of each.", "",
             "| N | image | pairs/pixel | blended/pixel | renderer | fwd ms | fwd+bwd ms | peak MB (fwd+bwd) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for e in result["scenes"]:
        d = e["scene"]
        for name, w in e["median_ms_per_round"].items():
            f = " / ".join(f"{x:.2f}" if x is not None else "fail" for x in w["fwd"])
            fb = " / ".join(f"{x:.2f}" if x is not None else "fail" for x in w["fwd_bwd"])
            mem = e["peak_mb_fwd_bwd"].get(name)
            ppp = f"{d['pairs_per_pixel']:.1f}" if d.get("pairs_per_pixel") else "-"
            lines.append(f"| {d['n']:,} | {d['width']}x{d['height']} | {ppp} | {d['blended_per_pixel']:.1f} | {name} | "
                         f"{f} | {fb} | {mem:.0f} |" if mem is not None else
                         f"| {d['n']:,} | {d['width']}x{d['height']} | {ppp} | {d['blended_per_pixel']:.1f} | {name} | "
                         f"{f} | {fb} | - |")
        lines.append("")
        lines.append(f"N = {d['n']:,}: " + ", ".join(f"{k} {v:.2f}x" for k, v in e["ratios"].items()) +
                     f"; textured: {d['texels_textured']:,} texels (median {d['texels_per_primitive_median_textured']:.0f}"
                     " per primitive)")
        lines.append("")
        if e.get("profile"):
            for name, rows in e["profile"].items():
                lines.append(f"Top CUDA kernels, {name}, N = {d['n']:,}, one fwd+bwd (ms per iteration):")
                lines.append("")
                for r in rows[:8]:
                    lines.append(f"- {r['self_cuda_ms_per_iter']:.3f} ms x{r['calls_per_iter']:.0f}: `{r['name'][:110]}`")
                lines.append("")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
