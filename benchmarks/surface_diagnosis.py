"""Where a model's rendered depth leaves the true surfaces of the demo scene, and why: every (pixel, surfel, weight)
the renderer blends in every training view, against the exact depth of the surface that pixel sees.

    .venv/bin/python benchmarks/surface_diagnosis.py --run content-aware=runs/demo --run 2dgs=runs/demo_2dgs \\
        --tag demo192x144_fast_2dgs_3000it

Per pixel (alpha >= 0.5 and a true surface behind it, as `ctgs mesh` fuses): the error of the expected depth
(sum w z / sum w, what `ctgs mesh` fuses), of the median depth (the surfel where the transmittance falls below 0.5,
2DGS's other choice), and the spread of the blended depths about their mean (sqrt(sum w (z - mean)^2 / sum w): opacity
smeared along the ray); the share of the blending weight on surfels within 2 cm of the true depth, in front of it
and behind it. The same by the kind of surface the pixel sees (photo: a textured photograph; flat: one colour;
smooth: a slow gradient), since only texture tells a photometric loss where a surface is.
Per surfel (weighted by its blending weight over the views): the distance of its centre to the nearest true surface,
the angle between its normal and that surface's, its size (2 sigma, the larger axis) and whether it carries a texture.
Record: benchmarks/results/surface_diagnosis/<tag>_<commit>.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_train import machine  # noqa: E402
from record import stem, write_record  # noqa: E402

NEAR_CM = 2.0  # a blended surfel "on" the surface: its hit within this of the true depth
KINDS = ("photo", "flat", "smooth")
PARALLEL_EPS = 1e-6  # as the renderer: a hit is valid where |n.d| > eps |d|


def true_depth(meta: dict, cam) -> tuple[np.ndarray, np.ndarray]:
    """([H, W] camera-space depth z of the first demo surface each pixel centre's ray meets (inf: none), [H, W] its
    index in meta["surfaces"] (-1))."""
    vm = cam.viewmat.detach().cpu().double().numpy()
    rot, t = vm[:3, :3], vm[:3, 3]
    origin = -rot.T @ t
    xs = (np.arange(cam.width) + 0.5 - cam.cx) / cam.fx
    ys = (np.arange(cam.height) + 0.5 - cam.cy) / cam.fy
    d_cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((cam.height, cam.width))), -1)
    d = d_cam.reshape(-1, 3) @ rot  # world directions with camera z = 1, so the ray parameter is the depth
    best = np.full(len(d), np.inf)
    idx = np.full(len(d), -1)
    for k, s in enumerate(meta["surfaces"]):
        c, n, u, v = (np.asarray(s[key], float) for key in ("center", "normal", "u", "v"))
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = ((c - origin) @ n) / denom
        hit = origin + tt[:, None] * d
        inside = (np.abs((hit - c) @ u) <= s["half_extents"][0]) & (np.abs((hit - c) @ v) <= s["half_extents"][1])
        ok = np.isfinite(tt) & (tt > 1e-6) & (tt < best) & inside
        best = np.where(ok, tt, best)
        idx = np.where(ok, k, idx)
    return best.reshape(cam.height, cam.width), idx.reshape(cam.height, cam.width)


@torch.no_grad()
def blended(model, cam) -> dict:
    """Every blended (pixel, primitive, w) of one render (the CPU kernel's own list, in blending order per pixel) and
    the camera-space depth z of each pair's hit (ray / surfel-plane intersection; the centre's depth where the ray
    grazes the plane, as the kernel's fallback)."""
    from ctgs.ops.ext import load_cpu
    from ctgs.render.preprocess import to_camera_space

    s = model.render_inputs()
    prims = to_camera_space(s.means, s.quats, s.sh, cam, model.sh_degree)
    k = s.texel_size if s.texel_size.ndim == 2 else s.texel_size[:, None].expand(-1, 2)
    load_cpu()
    rgb, alpha, depth, pix, prim, w = torch.ops.ctgs.rasterize_pairs(
        prims.mu_c.contiguous(), prims.Rc.contiguous(), s.scales.contiguous(), s.opacities.contiguous(),
        prims.colors.contiguous(), k.contiguous(), s.textures.contiguous(), s.tex_res.contiguous(),
        s.tex_offset.contiguous(), torch.zeros(3), float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy),
        int(cam.width), int(cam.height), float(cam.near), 1, False)
    pix, prim = pix.long(), prim.long()
    order = torch.sort(pix, stable=True).indices  # a pixel lies in one tile: its pairs keep their blending order
    pix, prim, w = pix[order], prim[order], w[order].double()
    mu = prims.mu_c.double()[prim]
    n = prims.Rc.double()[prim, :, 2]
    x = (pix % cam.width).double() + 0.5
    y = torch.div(pix, cam.width, rounding_mode="floor").double() + 0.5
    d = torch.stack([(x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, torch.ones_like(x)], 1)
    nd = (n * d).sum(1)
    ok = nd.abs() > PARALLEL_EPS * d.norm(dim=1)
    z = torch.where(ok, (n * mu).sum(1) / torch.where(ok, nd, torch.ones_like(nd)), mu[:, 2])
    return {"pix": pix.numpy(), "prim": prim.numpy(), "w": w.numpy(), "z": z.numpy(),
            "alpha": alpha.double().numpy().reshape(-1), "depth": depth.double().numpy().reshape(-1)}


def per_pixel(b: dict, npix: int) -> dict:
    """[npix] sums and the median depth from a view's pairs."""
    pix, w, z = b["pix"], b["w"], b["z"]
    a = np.bincount(pix, w, npix)
    dz = np.bincount(pix, w * z, npix)
    dz2 = np.bincount(pix, w * z * z, npix)
    cum = np.cumsum(w)
    start = np.searchsorted(pix, np.arange(npix))  # first pair of each pixel
    before = np.where(start > 0, cum[np.maximum(start - 1, 0)], 0.0)[pix]  # cum weight before the pixel's first pair
    own = cum - before  # cumulative weight within the pixel, this pair included
    crossing = (own >= 0.5) & (own - w < 0.5)
    median = np.full(npix, np.nan)
    median[pix[crossing]] = z[crossing]
    return {"a": a, "mean": np.where(a > 0, dz / np.maximum(a, 1e-12), np.nan),
            "var": np.where(a > 0, dz2 / np.maximum(a, 1e-12) - (dz / np.maximum(a, 1e-12)) ** 2, np.nan),
            "median": median}


def diagnose(run_dir: str) -> dict:
    from ctgs.runs import load_run
    from ctgs.scene.loader import load_scene
    from measures.demo_surfaces import load_demo_meta
    from measures.mesh_accuracy import distance_to_surfaces

    run = load_run(run_dir)
    meta = load_demo_meta(run.scene_dir)
    kinds = np.array([s["kind"] for s in meta["surfaces"]])
    views = load_scene(run.scene_dir, images=run.images, holdout=run.holdout, load_images=False).train
    model = run.model
    N = model.num_primitives
    pix_rows = {key: [] for key in ("kind", "e_mean", "e_median", "spread", "near", "front", "behind", "d3")}
    prim_w = np.zeros(N)
    prim_off_w = np.zeros(N)  # weight of its pairs more than NEAR_CM from the true depth
    for view in views:
        cam = view.camera
        zt, sid = true_depth(meta, cam)
        zt, sid = zt.reshape(-1), sid.reshape(-1)
        b = blended(model, cam)
        pp = per_pixel(b, cam.width * cam.height)
        off = np.abs(b["z"] - zt[b["pix"]]) * 100  # cm
        prim_w += np.bincount(b["prim"], b["w"], N)
        prim_off_w += np.bincount(b["prim"], b["w"] * (off > NEAR_CM), N)
        keep = (pp["a"] >= 0.5) & (sid >= 0)
        idx = np.nonzero(keep)[0]
        pix_rows["kind"].append(kinds[sid[idx]])
        pix_rows["e_mean"].append(np.abs(pp["mean"][idx] - zt[idx]) * 100)
        pix_rows["e_median"].append(np.abs(pp["median"][idx] - zt[idx]) * 100)
        pix_rows["spread"].append(np.sqrt(np.maximum(pp["var"][idx], 0)) * 100)
        dzs = (b["z"] - zt[b["pix"]]) * 100
        sel = keep[b["pix"]]
        for name, m in (("near", np.abs(dzs) <= NEAR_CM), ("front", dzs < -NEAR_CM), ("behind", dzs > NEAR_CM)):
            pix_rows[name].append(np.bincount(b["pix"][sel & m], b["w"][sel & m], cam.width * cam.height)[idx])
        # the expected-depth point's 3D distance to the nearest true surface (what the mesh record measured)
        vm = cam.viewmat.double().numpy()
        u = idx % cam.width + 0.5
        v = idx // cam.width + 0.5
        zz = pp["mean"][idx]
        pc = np.stack([(u - cam.cx) / cam.fx * zz, (v - cam.cy) / cam.fy * zz, zz], 1)
        pix_rows["d3"].append(distance_to_surfaces((pc - vm[:3, 3]) @ vm[:3, :3], meta)[0] * 100)
    cols = {k: np.concatenate(v) for k, v in pix_rows.items()}
    tot = cols["near"] + cols["front"] + cols["behind"]

    def summary(m: np.ndarray) -> dict:
        t = tot[m].sum()
        return {"pixels": int(m.sum()), "share": float(m.mean()),
                "expected_depth_error_median_cm": float(np.median(cols["e_mean"][m])),
                "expected_depth_error_mean_cm": float(np.mean(cols["e_mean"][m])),
                "point_distance_median_cm": float(np.median(cols["d3"][m])),
                "median_depth_error_median_cm": float(np.nanmedian(cols["e_median"][m])),
                "spread_median_cm": float(np.median(cols["spread"][m])),
                "spread_mean_cm": float(np.mean(cols["spread"][m])),
                "weight_near": float(cols["near"][m].sum() / t), "weight_front": float(cols["front"][m].sum() / t),
                "weight_behind": float(cols["behind"][m].sum() / t)}

    pixels = {"all": summary(np.ones(len(tot), bool))}
    for kind in KINDS:
        if (cols["kind"] == kind).any():
            pixels[kind] = summary(cols["kind"] == kind)
    # per surfel
    with torch.no_grad():
        means = model.means.double().numpy()
        from ctgs.render.geometry import quat_to_rotmat
        normals = quat_to_rotmat(model.quats.detach().double())[:, :, 2].numpy()
        size = 2 * model.scales.detach().double().max(1).values.numpy() * 100
        textured = (model.tex_res[:, 0].long() * model.tex_res[:, 1].long()).numpy() > 0 if model.num_texels else \
            np.zeros(N, bool)
    dist, n_true = distance_to_surfaces(means, meta)
    dist = dist * 100
    angle = np.degrees(np.arccos(np.clip(np.abs((normals * n_true).sum(1)), 0, 1)))
    wsum = prim_w.sum()

    def wq(x: np.ndarray, q: float) -> float:  # weighted quantile
        o = np.argsort(x)
        c = np.cumsum(prim_w[o]) / wsum
        return float(x[o][np.searchsorted(c, q)])

    surfels = {"count": N, "seen": int((prim_w > 0).sum()),
               "centre_distance_cm_weighted_median": wq(dist, 0.5), "centre_distance_cm_weighted_p90": wq(dist, 0.9),
               "weight_centre_within_2cm": float(prim_w[dist <= 2].sum() / wsum),
               "weight_centre_beyond_10cm": float(prim_w[dist > 10].sum() / wsum),
               "normal_angle_deg_weighted_median": wq(angle, 0.5),
               "weight_normal_over_30deg": float(prim_w[angle > 30].sum() / wsum),
               "size_cm_weighted_median": wq(size, 0.5), "size_cm_weighted_p90": wq(size, 0.9),
               "weight_textured": float(prim_w[textured].sum() / wsum),
               "off_surface_weight_textured": float(prim_off_w[textured].sum() / max(prim_off_w.sum(), 1e-12)),
               "texels": int(model.num_texels)}
    return {"run": run_dir, "views": len(views), "pixels": pixels, "surfels": surfels}


def markdown(r: dict) -> str:
    lines = [f"# Surface diagnosis: {r['tag']}", "", f"{r['date']}, commit {r['commit']}, {r['machine']['cpu']} "
             f"({r['machine']['cores']} cores).", "", f"Command: `{r['command']}`", "",
             "Per pixel (alpha >= 0.5, a true surface behind it; every training view), cm; weight shares: of the "
             f"blending weight, on surfels hit within {NEAR_CM:g} cm of the true depth / in front / behind:", "",
             "| run | pixels seeing | share | expected depth error median (mean) | its point's distance median | "
             "median-depth error median | spread median (mean) | weight near / front / behind |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for label, d in r["runs"].items():
        for kind, p in d["pixels"].items():
            lines.append(f"| {label} | {kind} | {p['share']:.2f} | {p['expected_depth_error_median_cm']:.2f} "
                         f"({p['expected_depth_error_mean_cm']:.2f}) | {p['point_distance_median_cm']:.2f} | "
                         f"{p['median_depth_error_median_cm']:.2f} | {p['spread_median_cm']:.2f} "
                         f"({p['spread_mean_cm']:.2f}) | {p['weight_near']:.3f} / {p['weight_front']:.3f} / "
                         f"{p['weight_behind']:.3f} |")
    lines += ["", "Per surfel, weighted by its blending weight over the training views:", "",
              "| run | surfels (seen) | centre to surface median / p90 (cm) | weight: centre within 2 cm / beyond "
              "10 cm | normal angle median (deg) | weight: normal > 30 deg | size 2 sigma median / p90 (cm) | "
              "weight textured | off-surface weight textured |", "| --- | --- | --- | --- | ---: | ---: | --- | ---: | ---: |"]
    for label, d in r["runs"].items():
        s = d["surfels"]
        lines.append(f"| {label} | {s['count']:,} ({s['seen']:,}) | {s['centre_distance_cm_weighted_median']:.2f} / "
                     f"{s['centre_distance_cm_weighted_p90']:.2f} | {s['weight_centre_within_2cm']:.3f} / "
                     f"{s['weight_centre_beyond_10cm']:.3f} | {s['normal_angle_deg_weighted_median']:.1f} | "
                     f"{s['weight_normal_over_30deg']:.3f} | {s['size_cm_weighted_median']:.1f} / "
                     f"{s['size_cm_weighted_p90']:.1f} | {s['weight_textured']:.3f} | "
                     f"{s['off_surface_weight_textured']:.3f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=RUN_DIR")
    ap.add_argument("--tag", required=True, help="record name (scene, resolution, variant)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    path_stem = stem("surface_diagnosis", args.tag)
    result = {"tag": args.tag, "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "commit": os.path.basename(path_stem).rsplit("_", 1)[1], "machine": machine(),
              "command": shlex.join(["benchmarks/surface_diagnosis.py", *sys.argv[1:]]), "runs": {}}
    for item in args.run:
        label, run_dir = item.split("=", 1)
        result["runs"][label] = diagnose(run_dir)
    write_record(path_stem, result, markdown)


if __name__ == "__main__":
    main()
