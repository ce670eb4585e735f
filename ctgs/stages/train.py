"""`ctgs train SCENE_DIR -o RUN_DIR`: train a content-aware textured 2DGS model (or a baseline)."""

from __future__ import annotations

import contextlib
import os
import shutil
import sys

import click

from ctgs.errors import Terminated, UserError
from ctgs.io import lock, owner
from ctgs.io.signals import signals_deferred


# Without --preset/--config: the authors' recipe where a GPU is present; on a CPU, the preset that measured
# best for the time (docs/results.md).
CPU_DEFAULT_PRESET = "fast"
GPU_DEFAULT_PRESET = "paper"


def default_preset() -> str:
    import torch

    return GPU_DEFAULT_PRESET if torch.cuda.is_available() else CPU_DEFAULT_PRESET


# --background: what the run renders over, and transparent photos are composited over (ctgs.scene.photos)
BACKGROUNDS = {"white": {"background": [1.0, 1.0, 1.0]}, "black": {"background": [0.0, 0.0, 0.0]},
               "random": {"random_background": True}}


def scene_background(scene_dir, background, sets):
    """The --background a run takes: as given; for a Blender synthetic scene without one (nor --set background),
    white, as those scenes are evaluated (random: over white as well), said on stderr."""
    from ctgs.scene.transforms import scene_layout

    if any(s.split("=", 1)[0].strip() == "background" for s in sets) or background == "black" or \
            scene_layout(scene_dir) != "blender":
        return [background] if background else []
    print("ctgs train: a Blender synthetic scene: rendered over white, as it is evaluated (--background black for "
          "another)", file=sys.stderr)
    return ["white"] + ([background] if background == "random" else [])


def resolve_config(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed, preset=None,
                   time_budget=None, max_params=None, backgrounds=()):
    """The run's config. backgrounds: BACKGROUNDS names to apply (`ctgs train`: scene_background's)."""
    from ctgs.train.config import load_config, parse_set

    overrides = parse_set(list(sets))
    for name in backgrounds:
        overrides.update(BACKGROUNDS[name])
    for key, value in (("iterations", iterations), ("images", images), ("backend", backend), ("seed", seed),
                       ("time_budget", time_budget), ("max_params", max_params)):
        if value is not None:
            overrides[key] = value
    saved = os.path.join(run_dir, "config.toml")
    if resume and config is None and preset is None and os.path.exists(saved):
        cfg = load_config(saved, overrides)  # the run's own config
    else:
        cfg = load_config(config, overrides, preset=preset)
    cfg.scene_dir = os.path.abspath(scene_dir)
    return cfg


# Without --preset/--config, a --time-budget run on a CPU whose first plan makes fewer passes over the training views
# than budget.FEW_PASSES trains this config instead, on the default preset (`fast`'s baseline: its densification
# every 2500 paper-scale iterations, the baseline every equal-time comparison measured; the bare 2dgs overlay would take
# the paper's 30k schedule, compressed into the budget): in every CPU run measured at equal time (bonsai252 and
# herzjesu25, 25 to 100 passes) the 2DGS baseline ended ahead of the content-aware presets; at 230 passes (herzjesu25,
# 20 minutes) `fast` led (docs/results.md).
BUDGET_FALLBACK = "2dgs"


def _pays_better(trainer) -> str | None:
    """For a fresh content-aware --time-budget run on a CPU: its first plan (made now, on a copy of the model), and if
    that plan makes fewer than budget.FEW_PASSES passes over the training views, the line that says the baseline is
    trained instead (None otherwise: the run goes on as planned)."""
    from ctgs.train.components import budget

    if trainer.device.type != "cpu" or trainer.cfg.method != "content_aware" or trainer.time.planner is None:
        return None
    iterations = trainer.plan_now()
    views = len(trainer.train_views)
    if iterations is None or iterations >= budget.FEW_PASSES * views:
        return None
    passes = iterations / views
    return (f"ctgs train: {trainer.user_cfg.time_budget:g} min buy about {iterations} iterations here, "
            f"{passes:.{0 if passes >= 10 else 1}f} passes over the {views} training views; below "
            f"{budget.FEW_PASSES} the {BUDGET_FALLBACK} baseline trained the better model in every CPU run measured at "
            f"equal time, so it is trained instead (--preset fast to train textures anyway; docs/guide/training.md, "
            f"\"When textures pay\")")


# `ctgs train`'s marker kind (ctgs.io.owner), and the names it (or a Slurm job, slurm.log) writes in a run folder
RUN_KIND = "run"
RUN_NAMES = frozenset({"config.toml", "log.jsonl", "checkpoints", "model.pt", "train_summary.json", "slurm.log",
                       lock.LOCK_NAME})


def _earlier_run(names: list[str]) -> bool:
    """A run folder written before folders were marked: only a training's names, or a training's config and log
    (with the exports and evaluations made in it since)."""
    return set(names) <= RUN_NAMES or {"config.toml", "log.jsonl"} <= set(names)


def train_main(scene_dir, run_dir, config=None, iterations=None, sets=(), images=None, resume=False,
               backend=None, seed=None, quiet=False, preset=None, time_budget=None, start_time=None,
               max_params=None, background=None) -> dict:
    """Train; returns the summary. Without preset and config the machine's default preset is used (said on
    stderr unless quiet). A failure before the first checkpoint leaves no run folder behind."""
    import time

    from ctgs.runs import training_scene, write_config
    from ctgs.train.loop.progress import run_with_progress
    from ctgs.train.loop.trainer import Trainer

    start_time = time.monotonic() if start_time is None else start_time
    if not os.path.isdir(scene_dir):
        raise UserError(f"{scene_dir}: scene folder not found; pass a folder made by `ctgs sfm` or `ctgs demo-scene`")
    if time_budget is not None and time_budget <= 0:
        raise UserError(f"--time-budget {time_budget:g}: a budget is a number of minutes above 0; leave the option out "
                        "to train the preset's fixed length")
    owner.check_ours(run_dir, RUN_KIND, "a ctgs run folder", legacy=_earlier_run)
    if not resume and os.path.exists(os.path.join(run_dir, "model.pt")):
        raise UserError(f"{run_dir}: already holds a finished run; choose another -o folder or delete it")
    own_config = resume and os.path.exists(os.path.join(run_dir, "config.toml"))  # a resumed run keeps its own
    chosen = preset is not None or config is not None or own_config
    if not chosen:
        preset = default_preset()
        if not quiet:
            import torch

            where = "a CUDA GPU is present" if torch.cuda.is_available() else "no GPU: CPU training"
            print(f"ctgs train: preset '{preset}' ({where}; --preset preview|fast|balanced|paper to choose, "
                  f"--time-budget MINUTES to fit a time)", file=sys.stderr)
    backgrounds = scene_background(scene_dir, background, sets)
    cfg = resolve_config(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed, preset,
                         time_budget, max_params, backgrounds=backgrounds)
    created = not os.path.exists(run_dir)
    held = trainer = None
    try:
        scene = training_scene(cfg)
        for note in ("points_note", "split"):  # random initial points; a transforms file's own train/test split
            if scene.meta.get(note):
                print(f"ctgs train: {'views: ' if note == 'split' else ''}{scene.meta[note]}", file=sys.stderr)
        # the folder appears only now: a TERM while the scene loads (pycolmap's import, where glog's handler ends the
        # process at once) leaves nothing behind
        with signals_deferred():  # a stop while the lock is taken lands once it is held (and is cleaned up)
            held = lock.RunLock(run_dir, "ctgs train")  # one writer: a second training or --resume here is refused
        owner.mark(run_dir, RUN_KIND)
        trainer = Trainer(cfg, scene, run_dir, resume=resume, start_time=start_time)
        if not chosen and not resume and (line := _pays_better(trainer)):
            # the machine's default preset, planned where its textures have not paid: the baseline that did
            print(line, file=sys.stderr)
            trainer = None
            cfg = resolve_config(scene_dir, run_dir, BUDGET_FALLBACK, iterations, sets, images, resume, backend, seed,
                                 preset, time_budget, max_params, backgrounds=backgrounds)
            trainer = Trainer(cfg, scene, run_dir, resume=resume, start_time=start_time)
        if not quiet and cfg.max_params == 0 and trainer.cfg.max_params > 0:
            print(f"ctgs train: size budget {trainer.cfg.max_params} params ({cfg.max_params_per_value:g} per observed "
                  "value; --set max_params_per_value=0 for none, --max-params N for another)", file=sys.stderr)
        if trainer.cfg.test_lpips:
            from ctgs.metrics.lpips import load_lpips

            if load_lpips()[0] is None:  # never a made-up number: the curves go without LPIPS, said once here
                print(f"ctgs train: warning: test_lpips: LPIPS {load_lpips()[1].detail}; the test evaluations score PSNR "
                      "and SSIM only", file=sys.stderr)
        write_config(run_dir, cfg.to_dict())
        return run_with_progress(trainer, quiet=quiet)
    except BaseException as exc:
        # Nothing half-written: a run folder this invocation created goes if no checkpoint made it resumable (only
        # once it holds the folder's lock: before, the folder is not there yet, or is another process's).
        from ctgs.runs.checkpoint import has_checkpoint

        if isinstance(exc, (KeyboardInterrupt, Terminated)) and trainer is not None:
            trainer.checkpoint_on_stop()
        resumable = held is not None and has_checkpoint(run_dir)
        removed = held is not None and created and not resumable
        if removed:
            shutil.rmtree(run_dir, ignore_errors=True)
        elif held is not None and not resumable:  # a folder made before (a Slurm job's): no empty checkpoints/
            with contextlib.suppress(OSError):
                os.rmdir(os.path.join(run_dir, "checkpoints"))
        if isinstance(exc, (KeyboardInterrupt, Terminated)):  # Ctrl-C, or SIGTERM through the CLI
            if resumable:
                print(f"ctgs train: stopped; {run_dir}/checkpoints/last.pt holds the last checkpoint: continue with "
                      f"`ctgs train {scene_dir} -o {run_dir} --resume`", file=sys.stderr)
            else:
                print("ctgs train: stopped before the first checkpoint" + (f"; {run_dir} removed" if removed else ""),
                      file=sys.stderr)
        raise
    finally:
        if held is not None:
            held.release()


# `ctgs train` says so when the last evaluation ends this far below the run's best one.
OVERFIT_NOTE_DB = 0.5


def list_keys() -> str:
    """Every config key with its default and help, and the methods whose strategy reads it (its Settings)."""
    from ctgs.train.config import describe_keys
    from ctgs.train.strategies import STRATEGIES

    lines = []
    for key, default, help_text in describe_keys():
        users = [method for method, strategy in STRATEGIES.items() if key in strategy.KEYS]
        lines.append(f"{key} = {default!r}" + (f"    [{', '.join(users)}]" if users else "") + f"\n    {help_text}")
    return "\n".join(lines)


def _list_keys(ctx, _param, value):
    if value and not ctx.resilient_parsing:
        click.echo(list_keys())
        ctx.exit()


@click.command(name="train")
@click.argument("scene_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "run_dir", required=True, type=click.Path(file_okay=False), help="Run folder.")
@click.option("--preset", type=click.Choice(["preview", "fast", "balanced", "paper"]), default=None,
              help="Recipe: paper = the authors' exactly (default with a GPU); fast (default on a CPU; with "
                   "--time-budget, the 2dgs baseline where the plan makes under 150 passes over the views), "
                   "preview and balanced trade time for quality (docs/guide/training.md).")
@click.option("--time-budget", "time_budget", type=float, default=None, metavar="MINUTES",
              help="Plan the iteration count so the whole run ends within MINUTES (> 0) on this machine (without it, "
                   "the run says how long its fixed length will take).")
@click.option("--max-params", "max_params", type=click.IntRange(min=1), default=None, metavar="N",
              help="Size budget: the model ends with at most N parameters (textures coarsened where that loses "
                   "least, splits stopped where needed; docs/guide/training.md).")
@click.option("--config", default=None, help="Config overlay: a TOML file or a shipped name (default, 2dgs, ...).")
@click.option("--iterations", type=int, default=None, help="Override the number of iterations.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Override one config key (repeatable).")
@click.option("--images", default=None, help="Image sub-folder (images, images_2, images_4, ...).")
@click.option("--resume", is_flag=True, help="Continue from RUN_DIR/checkpoints (after a crash or kill -9).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default=None,
              help="Renderer backend.")
@click.option("--seed", type=int, default=None, help="Random seed.")
@click.option("--background", type=click.Choice(["white", "black", "random"]), default=None,
              help="What the model is rendered over and transparent photos composited over (default: black; white "
                   "for a Blender synthetic scene); random: a new colour each step (docs/guide/masks.md).")
@click.option("-q", "--quiet", is_flag=True, help="No progress display.")
@click.option("--list-keys", is_flag=True, expose_value=False, is_eager=True, callback=_list_keys,
              help="Print every config key with its default and help, then exit.")
def command(scene_dir, run_dir, preset, time_budget, max_params, config, iterations, sets, images, resume, backend, seed,
            background, quiet):
    """Train on SCENE_DIR, writing model.pt, config.toml, log.jsonl and train_summary.json to RUN_DIR."""
    import time

    start = time.monotonic()
    summary = train_main(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed, quiet,
                         preset=preset, time_budget=time_budget, start_time=start, max_params=max_params,
                         background=background)
    click.echo(f"done: {summary['iterations']} iterations in {summary['train_seconds']:.0f} s, "
               f"test PSNR {summary['final_test_psnr']:.2f} dB, {summary['num_primitives']} primitives, "
               f"{summary['num_texels']} texels, {summary['num_params']} params -> {run_dir}")
    if summary.get("estimated_wall_s"):
        est = summary["estimated_wall_s"]
        at = summary["estimated_at_it"]
        click.echo(f"wall {summary['wall_seconds'] / 60:.2f} min (estimated {est[0] / 60:.2f} at the start"
                   + (f", {est[1] / 60:.2f} at iteration {at[1]}" if len(est) > 1 else "") + ")")
    peak = summary.get("eval_peak")
    if (peak and peak["views"] != "training" and peak["psnr"] - summary["final_test_psnr"] > OVERFIT_NOTE_DB
            and peak["it"] < summary["iterations"]):
        click.echo(f"{peak['views']} PSNR peaked at {peak['psnr']:.2f} dB at iteration {peak['it']} "
                   f"({peak['psnr'] - summary['final_test_psnr']:.2f} dB above the end): the run fits its training "
                   f"photos past what carries to new views"
                   + ("; to choose a length, compare runs on validation views (--set validation_holdout=8), "
                      "not on these test views" if peak["views"] == "test" else ""))
    missed = None
    if summary.get("max_params"):
        over = summary["num_params"] - summary["max_params"]
        per = summary.get("max_params_per_value")
        said = (f"size budget {summary['max_params']} params" + (f" ({per:g} per observed value)" if per else "")
                + ": " + ("held" if over <= 0 else
                f"missed by {over} (what is left cannot be coarsened: textures 2 texels wide; "
                f"the 'budget' lines of {run_dir}/log.jsonl)"))
        if over > 0 and not per:  # the budget asked for (--max-params) was not met: not a success
            missed = (f"{run_dir}/model.pt: {said}; the model is kept; for a budget it meets, pass --max-params "
                      f"{summary['num_params']} or more")
        else:
            click.echo(said)
    if "time_budget_s" in summary:
        click.echo(f"time budget {summary['time_budget_s'] / 60:.1f} min: planned {summary['planned_iterations_initial']} "
                   f"iterations at start, ran {summary['iterations']} ({summary['replans']} re-plans), wall "
                   f"{summary['wall_seconds'] / 60:.2f} min")
        tex_at, frac = summary.get("texture_start_it"), summary.get("texture_start_scheduled_fraction")
        if tex_at is not None and frac and summary["iterations"]:
            click.echo(f"textures started after iteration {tex_at}: {100 * tex_at / summary['iterations']:.2f}% of the "
                       f"run (the schedule's {100 * frac:.2f}%, placed from the speed measured in the first steps)")
    if missed:
        raise SizeBudgetMissed(missed)


class SizeBudgetMissed(UserError):
    """The run finished above the --max-params it was given (its model.pt is written): an error line and exit 3."""

    exit_code = 3
