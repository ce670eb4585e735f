"""`ctgs train SCENE_DIR -o RUN_DIR`: train a content-aware textured 2DGS model (or a baseline)."""

from __future__ import annotations

import os

import click

from ctgs.errors import UserError


def _load_scene(cfg):
    try:
        from ctgs.scene import load_scene
    except ImportError:
        from ctgs.scene.loader import load_scene
    holdout = cfg.holdout if cfg.holdout > 0 else None
    return load_scene(cfg.scene_dir, images=cfg.images, holdout=holdout)


def resolve_config(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed):
    from ctgs.resources import resolve_config as config_path
    from ctgs.train.config import load_config, parse_set

    overrides = parse_set(list(sets))
    for key, value in (("iterations", iterations), ("images", images), ("backend", backend), ("seed", seed)):
        if value is not None:
            overrides[key] = value
    saved = os.path.join(run_dir, "config.toml")
    if resume and config is None and os.path.exists(saved):
        cfg = load_config(saved, overrides)  # the run's own resolved config
    else:
        cfg = load_config(config and config_path(config), overrides)  # a shipped name (`demo`) or a file
    cfg.scene_dir = os.path.abspath(scene_dir)
    return cfg


def train_main(scene_dir, run_dir, config=None, iterations=None, sets=(), images=None, resume=False,
               backend=None, seed=None, quiet=False) -> dict:
    from ctgs.train.progress import run_with_progress
    from ctgs.train.run import write_config
    from ctgs.train.trainer import Trainer

    if not os.path.isdir(scene_dir):
        raise UserError(f"{scene_dir}: scene folder not found; pass a folder made by `ctgs sfm` or `ctgs demo-scene`")
    if not resume and os.path.exists(os.path.join(run_dir, "model.pt")):
        raise UserError(f"{run_dir}: already holds a finished run; choose another -o folder or delete it")
    cfg = resolve_config(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed)
    scene = _load_scene(cfg)
    trainer = Trainer(cfg, scene, run_dir, resume=resume)
    write_config(run_dir, cfg.to_dict())
    return run_with_progress(trainer, quiet=quiet)


@click.command(name="train")
@click.argument("scene_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "run_dir", required=True, type=click.Path(file_okay=False), help="Run folder.")
@click.option("--config", type=click.Path(dir_okay=False), default=None,
              help="TOML config file, or the name of a shipped one (default, demo, 2dgs, ...).")
@click.option("--iterations", type=int, default=None, help="Override the number of iterations.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help="Override one config key (repeatable).")
@click.option("--images", default=None, help="Image sub-folder (images, images_2, images_4, ...).")
@click.option("--resume", is_flag=True, help="Continue from RUN_DIR/checkpoints (after a crash or kill -9).")
@click.option("--backend", type=click.Choice(["auto", "cpu", "cuda", "reference"]), default=None,
              help="Renderer backend.")
@click.option("--seed", type=int, default=None, help="Random seed.")
@click.option("-q", "--quiet", is_flag=True, help="No progress display.")
def command(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed, quiet):
    """Train on SCENE_DIR, writing model.pt, config.toml, log.jsonl and train_summary.json to RUN_DIR."""
    summary = train_main(scene_dir, run_dir, config, iterations, sets, images, resume, backend, seed, quiet)
    click.echo(f"done: {summary['iterations']} iterations in {summary['train_seconds']:.0f} s, "
               f"test PSNR {summary['final_test_psnr']:.2f} dB, {summary['num_primitives']} primitives, "
               f"{summary['num_texels']} texels, {summary['num_params']} params -> {run_dir}")
