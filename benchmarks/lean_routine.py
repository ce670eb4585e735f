"""The routine as it runs (lean: downscale first, then upscale cropped as made) against the paper's order (upscale to
2x, downscale, the reallocation crops): same model state, both ways, side by side (ctgs/train/routines.py full_routine,
`lean`).

Trains a run the way `ctgs train` does (Trainer.run's events) up to just before a full routine, then runs that
routine (ctgs.train.routines.full_routine) on two deep copies of the model and optimiser, lean False and True,
and records for each: seconds, the texel count of every texture layout the routine builds (edit.relayout /
edit.replace_blocks; the largest is the routine's transient texture memory: x 3 buffers x 3 channels x 4 bytes in
float32), and whether the two final states are identical (textures, Adam moments, resolutions, exponents). --count-ops adds one
more run of each, untimed, under a dispatch counter: every ATen op (on a GPU, about one kernel launch each) and the
ops that make a CUDA host wait for the device (item/bool/int of a tensor, nonzero, unique, boolean-mask indexing,
repeat_interleave without an output size): what a GPU's routine time follows when each op is short.

    python benchmarks/lean_routine.py SCENE --out DIR [--preset paper] [--images images_4] [--at 1000] [--reps 3]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import tempfile
import time


def op_counter():
    """A TorchDispatchMode (a context manager) that counts ATen ops and host syncs; defined here, on first use, since
    torch is imported lazily."""
    import collections

    import torch
    from torch.utils._python_dispatch import TorchDispatchMode

    always = {"_local_scalar_dense", "nonzero", "_unique2", "unique_dim", "unique_consecutive", "masked_select",
              "equal", "nonzero_static"}

    class Counter(TorchDispatchMode):
        """Counts ATen ops; and those that synchronise a CUDA host with the device (by name; boolean indexing and
        repeat_interleave without output_size too)."""

        def __init__(self):
            super().__init__()
            self.total = 0
            self.syncs = collections.Counter()
            self.sites = collections.Counter()  # the innermost ctgs/ frame of each sync

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.total += 1
            name = func.overloadpacket.__name__
            sync = name in always
            if name in ("index", "index_put", "index_put_"):
                idx = args[1] if len(args) > 1 else []
                sync = any(isinstance(t, torch.Tensor) and t.dtype == torch.bool for t in (idx or []))
                name = f"{name} (bool mask)"
            elif name == "repeat_interleave":
                sync = (kwargs or {}).get("output_size") is None
            if sync:
                self.syncs[name] += 1
                self.sites[_ctgs_site()] += 1
            return func(*args, **(kwargs or {}))

    return Counter()


def _ctgs_site() -> str:
    import traceback

    for fr in reversed(traceback.extract_stack()):
        f = fr.filename.replace(os.sep, "/")
        if "/ctgs/" in f and "/benchmarks/" not in f:
            return f"{f[f.rindex('/ctgs/') + 1:]}:{fr.lineno} {fr.name}"
    return "(outside ctgs)"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--out", required=True)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--images", default="images_4")
    ap.add_argument("--at", type=int, default=1000, help="the full routine's iteration (trained up to it - 1)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--backend", default=None)
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--count-ops", action="store_true", help="also count ATen ops and host syncs of each routine")
    args = ap.parse_args(argv)

    import torch

    from ctgs.stages.train import _load_scene, resolve_config
    from ctgs.train import edit, routines, schedule
    from ctgs.train.events import Step
    from ctgs.train.trainer import Trainer

    run_dir = tempfile.mkdtemp(prefix="ctgs_upcrop_")
    cfg = resolve_config(args.scene, run_dir, None, None, args.sets + ["test_every=0"], args.images, False,
                         args.backend, None, args.preset)
    trainer = Trainer(cfg, _load_scene(cfg), run_dir)
    cfg = trainer.cfg  # (resolved for the images and the run's length)
    if schedule.routine_kind(cfg, args.at, 0.0) != "full":
        raise SystemExit(f"iteration {args.at} is not a full routine of this run's calendar; pick another --at")
    t0 = time.perf_counter()
    for ev in trainer.run():
        if isinstance(ev, Step) and ev.it >= args.at - 1:
            break
    train_s = time.perf_counter() - t0
    model, opt = trainer.model, trainer.opt
    sizes: list[int] = []
    real_relayout, real_replace = edit.relayout, edit.replace_blocks

    def relayout(m, o, new_res):
        sizes.append(int(new_res.long().prod(1).sum()))
        return real_relayout(m, o, new_res)

    def replace_blocks(m, o, new_res, blocks):
        sizes.append(int(new_res.long().prod(1).sum()))
        return real_replace(m, o, new_res, blocks)

    edit.relayout, edit.replace_blocks = relayout, replace_blocks
    rows, finals = {}, {}
    try:
        for rep in range(args.reps):
            for crop in (False, True):
                m, o = copy.deepcopy(model), copy.deepcopy(opt)
                sizes.clear()
                torch.manual_seed(0)
                t = time.perf_counter()
                stats = routines.full_routine(m, o, cfg, args.at, trainer.train_views, trainer.render_fn,
                                              trainer.cameras, trainer._background_mask(), lean=crop)
                sec = time.perf_counter() - t
                r = rows.setdefault(str(crop), {"seconds": [], "layouts_texels": None})
                r["seconds"].append(round(sec, 3))
                r["layouts_texels"] = list(sizes)
                r["upscaled"] = stats["upscaled"]
                finals[crop] = (m, o)
    finally:
        edit.relayout, edit.replace_blocks = real_relayout, real_replace
    if args.count_ops:
        for crop in (False, True):
            m, o = copy.deepcopy(model), copy.deepcopy(opt)
            torch.manual_seed(0)
            with op_counter() as counter:
                routines.full_routine(m, o, cfg, args.at, trainer.train_views, trainer.render_fn, trainer.cameras,
                                      trainer._background_mask(), lean=crop)
            rows[str(crop)]["ops"] = counter.total
            rows[str(crop)]["syncs"] = sum(counter.syncs.values())
            rows[str(crop)]["syncs_by_op"] = dict(counter.syncs.most_common())
            rows[str(crop)]["syncs_by_site"] = dict(counter.sites.most_common())
    (a, oa), (b, ob) = finals[False], finals[True]
    same = (torch.equal(a.tex_res, b.tex_res) and torch.equal(a.t2p_exp, b.t2p_exp)
            and torch.equal(a.textures_raw, b.textures_raw)
            and all(torch.equal(getattr(oa, k)["textures_raw"], getattr(ob, k)["textures_raw"])
                    for k in ("exp_avg", "exp_avg_sq")))
    result = {"scene": args.scene, "preset": args.preset, "images": args.images, "at": args.at,
              "primitives": model.num_primitives, "texels_before": model.num_texels, "texels_after": a.num_texels,
              "train_seconds_to_reach": round(train_s, 1), "device": str(trainer.device),
              "machine": f"{platform.node()} ({os.cpu_count()} cpus)", "torch": torch.__version__,
              "identical_final_state": bool(same), "runs": rows}
    os.makedirs(args.out, exist_ok=True)
    name = os.path.basename(os.path.normpath(args.scene))
    base = os.path.join(args.out, f"lean_routine_{name}_{args.images}_{args.at}")
    with open(base + ".json", "w") as f:
        json.dump(result, f, indent=1)
    med = {k: sorted(v["seconds"])[len(v["seconds"]) // 2] for k, v in rows.items()}
    peak = {k: max(v["layouts_texels"]) for k, v in rows.items()}
    lines = [f"# The lean routine (downscale first, upscale cropped as made) vs the paper's order: {args.scene} "
             f"({args.images}), preset {args.preset}, full routine at iteration {args.at}", "",
             f"{result['machine']}, torch {result['torch']}, device {result['device']}; model before the routine: "
             f"{model.num_primitives:,} primitives, {model.num_texels:,} texels; after: {a.num_texels:,} texels; "
             f"{rows['True']['upscaled']:,} upscaled. Final states identical: **{same}**.", "",
             f"| routine | routine seconds (median of {args.reps}) | largest texture layout in the routine (texels) | "
             "every layout |", "| --- | --- | --- | --- |"]
    for k, name in (("False", "paper's order: upscale 2x, downscale, realloc crops (before)"),
                    ("True", "lean: downscale, upscale cropped as made (now)")):
        lines.append(f"| {name} | {med[k]:.3f} ({', '.join(str(x) for x in rows[k]['seconds'])}) | {peak[k]:,} | "
                     f"{', '.join(f'{x:,}' for x in rows[k]['layouts_texels'])} |")
    if args.count_ops:
        lines += ["", "| routine | ATen ops | host syncs (on a GPU) | most frequent syncs |", "| --- | --- | --- | --- |"]
        for k, name in (("False", "paper's order"), ("True", "lean")):
            top = ", ".join(f"{op} {n}" for op, n in list(rows[k]["syncs_by_op"].items())[:4])
            lines.append(f"| {name} | {rows[k]['ops']:,} | {rows[k]['syncs']:,} | {top} |")
        lines += ["", "Where the lean routine's host syncs are (innermost ctgs frame):", "", "| syncs | site |",
                  "| ---: | --- |"]
        lines += [f"| {n} | `{site}` |" for site, n in list(rows["True"]["syncs_by_site"].items())[:12]]
    ratio = peak["True"] / max(peak["False"], 1)
    lines += ["", f"Largest layout ratio (now / before): {ratio:.3f}; routine time ratio: "
              f"{med['True'] / max(med['False'], 1e-9):.3f}."]
    with open(base + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result


if __name__ == "__main__":
    main()
