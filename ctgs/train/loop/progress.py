"""Rich progress display of a Trainer's events (it/s, ETA, loss, PSNR, primitives, texels)."""

from __future__ import annotations

import sys
import time

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ctgs.train.components.budget import estimate_line, few_passes_note, short_plan_warning
from ctgs.train.events import Checkpoint, Done, Estimated, Eval, Planned, Routine, Step


def run_with_progress(trainer, quiet: bool = False) -> dict:
    """Drive trainer.run(); return the summary dict of the Done event."""
    summary: dict = {}
    if quiet:
        for ev in trainer.run():
            if isinstance(ev, Done):
                summary = ev.summary
            elif isinstance(ev, Planned) and ev.it == 0:
                for line in _plan_notes(trainer, ev):
                    print(line, file=sys.stderr)
        return summary
    console = Console(stderr=True)
    # Time left: the cost model's (budget.py) where the run has one, which counts the growth of the step cost
    # still ahead and the routines; a --time-budget run's is its budget's end. Otherwise rich's (recent speed).
    modelled = trainer.time.clock is not None
    columns = [TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[speed]:>6.1f} it/s"), TimeElapsedColumn(), TextColumn("ETA"),
               TextColumn("{task.fields[left]}") if modelled else TimeRemainingColumn(),
               TextColumn("{task.fields[info]}")]
    test = "-"
    planned_once = False
    estimates_shown = 0
    end_at = None  # time.monotonic() at which the run is expected to end
    with Progress(*columns, console=console, refresh_per_second=4) as progress:
        task = progress.add_task("train", total=trainer.cfg.iterations, completed=trainer.it, speed=0.0, info="",
                                 left="-:--:--")
        start_it, start_s = trainer.it, trainer.train_seconds
        for ev in trainer.run():
            if isinstance(ev, Step):
                dt = ev.seconds - start_s
                speed = (ev.it - start_it) / dt if dt > 0 else 0.0
                info = (f"loss {ev.loss:.4f}  PSNR {ev.psnr:5.2f}  test {test}  prims {ev.num_primitives}  "
                        f"texels {ev.num_texels}")
                left = "-:--:--" if end_at is None else _clock(end_at - time.monotonic())
                progress.update(task, completed=ev.it, speed=speed, info=info, left=left)
            elif isinstance(ev, Eval):
                test = f"{ev.test_psnr:.2f}"
            elif isinstance(ev, Routine) and ev.kind in ("texture_start", "full", "trim"):
                progress.console.log(f"it {ev.it} {ev.kind}: " + ", ".join(
                    f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in ev.stats.items()))
            elif isinstance(ev, Planned):
                progress.update(task, total=ev.iterations)
                end_at = trainer.time.planner.start + ev.budget_s
                if ev.it == trainer.it and not planned_once:
                    planned_once = True
                    progress.console.log(f"time budget {ev.budget_s / 60:.1f} min: planned {ev.iterations} iterations "
                                         f"(re-planned as the model grows)")
                    if ev.it == 0:
                        for line in _plan_notes(trainer, ev):
                            progress.console.print(line, markup=False, highlight=False, soft_wrap=True)
            elif isinstance(ev, Estimated):
                end_at = trainer.time.estimator.start + ev.wall_s
                if estimates_shown < 2:  # the calibration's and the first from measured steps; later ones: the ETA
                    estimates_shown += 1
                    progress.console.print("ctgs train: " + estimate_line(ev.it, ev.iterations, ev.wall_s),
                                           markup=False, highlight=False, soft_wrap=True)
                    if ev.it == 0 and (line := _passes_note(trainer, ev.iterations)):
                        progress.console.print(line, markup=False, highlight=False, soft_wrap=True)
            elif isinstance(ev, Checkpoint):
                pass
            elif isinstance(ev, Done):
                summary = ev.summary
    return summary


def _plan_notes(trainer, ev: Planned) -> list[str]:
    """What a fresh budgeted run is told of its first plan (shown quiet or not): a plan shorter than any measured
    run, and a content-aware plan of few passes over the training views."""
    lines = [short_plan_warning(ev.iterations, ev.budget_s, trainer.time.planner.plan.calib_step_s, trainer.pixels),
             _passes_note(trainer, ev.iterations)]
    return [line for line in lines if line]


def _passes_note(trainer, iterations: int) -> str | None:
    # The runs behind the figure are CPU runs; on a GPU the paper's 30k iterations are the measure.
    if trainer.device.type != "cpu":
        return None
    return few_passes_note(trainer.cfg.method, iterations, len(trainer.train_views))


def _clock(seconds: float) -> str:
    """h:mm:ss, as rich's own time columns."""
    seconds = max(int(round(seconds)), 0)
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"
