"""`ctgs` command-line entry point.

Each subcommand only parses its options and calls a stage in `ctgs.stages`; stages are imported
lazily so `ctgs --help` stays fast and never touches torch or the compiled extension.
"""

from __future__ import annotations

import errno
import importlib
import os
import signal
import sys
import threading

import click

from ctgs import __version__
from ctgs.errors import OS_ERROR_EXIT, Terminated, UserError, describe_os_error

# name -> (module, one-line help). Each module defines `command`, a click.Command.
STAGES: dict[str, tuple[str, str]] = {
    "sfm": ("ctgs.stages.sfm", "Structure from motion (pycolmap): images -> undistorted COLMAP scene."),
    "train": ("ctgs.stages.train", "Train a content-aware textured 2DGS model on a scene."),
    "export": ("ctgs.stages.export", "Export a trained run: ctgs model folder, 3DGS PLY, .splat, .spz or .glb."),
    "compress": ("ctgs.stages.compress", "Compress an exported model (texel codebook, quantised attributes, xz)."),
    "eval": ("ctgs.stages.eval", "Quality, size and speed figures of a run or model; aggregate tables."),
    "demo-scene": ("ctgs.stages.demo_scene", "Generate the built-in synthetic demo scene (COLMAP layout)."),
    "convert": ("ctgs.stages.convert", "Write a scene in another layout: nerfstudio transforms.json or COLMAP."),
    "fetch": ("ctgs.stages.fetch", "Download and extract a benchmark dataset listed in data_manifests/."),
    "render": ("ctgs.stages.render", "Render a scene's cameras with a model (or demo primitives)."),
    "mesh": ("ctgs.stages.mesh", "A coloured triangle mesh of a trained run (TSDF fusion of its rendered depth)."),
    "view": ("ctgs.stages.view", "Web viewer (WebGL2) of a model on 127.0.0.1, textures included."),
}


def _terminate(signum, frame) -> None:
    # An exception raised while a module is being imported can be lost by the extension being initialised (raised
    # during numpy.random's import it ended the process with exit 0): while an import is in progress, deliver the
    # signal again in 50 ms instead.
    f = frame
    while f is not None:
        if f.f_code.co_filename.startswith("<frozen importlib"):
            again = threading.Timer(0.05, os.kill, (os.getpid(), signum))
            again.daemon = True
            again.start()
            return
        f = f.f_back
    raise Terminated(signum)


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(STAGES)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in STAGES:
            return None
        return importlib.import_module(STAGES[name][0]).command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Help text from the table: listing commands must not import torch-heavy stage modules.
        with formatter.section("Commands"):
            formatter.write_dl([(name, help_text) for name, (_, help_text) in STAGES.items()])

    def invoke(self, ctx: click.Context):
        # `kill`, `timeout` and a cluster's time limit stop a stage as Ctrl-C does: Python unwinds, so a stage removes
        # what it had half-made, and the exit code is 143 (ctgs.errors.Terminated). (ctgs.scene.colmap.import_pycolmap
        # keeps this handler when pycolmap's glog would take SIGTERM over.)
        signal.signal(signal.SIGTERM, _terminate)
        try:
            return super().invoke(ctx)
        except UserError as exc:
            click.secho(f"error: {exc}", fg="red", err=True)
            sys.exit(exc.exit_code)
        except OSError as exc:
            # A fault of the machine (full disk, read-only or unreadable folder, a device gone): one line naming
            # the path and the fix, whichever stage hit it (CTGS_TRACEBACK=1 shows where, for a bug report).
            if os.environ.get("CTGS_TRACEBACK") == "1" or exc.errno == errno.EPIPE:  # EPIPE: click's own handling
                raise
            click.secho(f"error: {describe_os_error(exc)}", fg="red", err=True)
            sys.exit(OS_ERROR_EXIT)
        finally:
            # The stage is over: a TERM from now on (a cluster sends a second one at its time limit) ends the process
            # as the signal does, not as a Terminated raised inside the interpreter's exit handlers (a traceback).
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ctgs")
def main() -> None:
    """ctgs: photographs -> compact, fast content-aware textured 2D Gaussian Splatting.

    Stages read and write on-disk artifacts and can be run independently:
    sfm -> train -> export -> compress -> eval.
    """


if __name__ == "__main__":
    main()
