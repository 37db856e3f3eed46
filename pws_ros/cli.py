"""The ``pws`` command: the pws_ros engine without ROS.

Each subcommand lives in :mod:`pws_ros.commands` and exposes ``register(subparsers)`` and ``run(args)``.
Bad input prints one line naming the problem and exits with status 2 (no traceback). Only the command
that runs is imported (``pws --help`` lists the others from :data:`pws_ros.commands.SUMMARIES`, without
importing torch: it returns at once).
"""
from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .commands import SUMMARIES, module_name
from .core.errors import PwsError

COMMANDS = tuple(module_name(c) for c in SUMMARIES)   # the modules of pws_ros.commands

DESCRIPTION = """\
Certify that an image classifier keeps its prediction under camera motion, with Pixel-wise
Smoothing (PwS, PwS-L, PwS-OF) or the CMS baseline. Clouds are .npz files with `points` (N,3,
metres, camera optical frame: x right, y down, z forward) and `colors` (N,3, uint8 or float in
[0,1]); cameras are ROS camera_info YAML files (as written by camera_calibration).

Axes: tx, ty, tz (metres) and rx, ry, rz (radians), motion of the camera in its own frame."""

EPILOG = """\
examples:
  pws sim view --seed 3 --view 0 --out-dir /tmp/view        # a view of the procedural world
  pws plan --cloud /tmp/view/cloud.npz --camera /tmp/view/camera.yaml --axis tz --radius 0.01 --method pws_of
  pws certify --cloud /tmp/view/cloud.npz --camera /tmp/view/camera.yaml \\
      --model bags/models/classifier_sigma0.50.pt --axis ry --radius 0.0044 --n 256
  pws replay bags/demo --report /tmp/report                 # certify a rosbag2 recording
  pws export-model my_net.py:build --input-size 224x224 --classes classes.txt --imagenet --out my_net.pt
  pws finetune my_recording.mcap --model my_net.pt --sigma 0.25 --out my_net_s025.pt   # noise-robust, no labels
  pws import frames my_clips --out my_recording --intrinsics 615,615,320,240   # RGB-D images + labels -> a recording
run `pws COMMAND --help` for each command."""


def build_parser(command: str | None = "*") -> argparse.ArgumentParser:
    """The ``pws`` parser with the arguments of ``command`` (a CLI name, ``"*"`` every command; the others
    are listed by their one line only, their modules not imported)."""
    parser = argparse.ArgumentParser(prog="pws", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"pws_ros {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in SUMMARIES.items():
        if command not in ("*", name):
            sub.add_parser(name, help=summary)
            continue
        try:
            module = importlib.import_module(f"pws_ros.commands.{module_name(name)}")
        except ModuleNotFoundError as exc:  # an optional command whose module is not installed
            if exc.name != f"pws_ros.commands.{module_name(name)}":
                raise
            continue
        module.register(sub)
    return parser


def command_in(argv: list[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one of ``pws``'s."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in SUMMARIES else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        parser = build_parser(command_in(argv))
        args = parser.parse_args(argv)
    except KeyboardInterrupt:   # while the command's modules load (numpy, torch): before anything was written
        print(" ".join(["pws"] + [w for w in [command_in(argv)] if w]) + ": interrupted", file=sys.stderr)
        return 130
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except PwsError as exc:
        print(f"pws {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pws {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`pws plan ... | head`): stop quietly, as Unix tools do
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


def run() -> None:
    """The ``pws`` executable: :func:`main`, then the exit with its status. A frame that a signal left while its axes
    ran in threads of their own (:func:`pws_ros.bridge.axis_threads.axes_left_running`) has threads still inside torch,
    or only just ending, and the interpreter's teardown would abort under them ("terminate called without an active
    exception": SIGABRT instead of 130 or 143), so the process then ends without that teardown, its output already
    closed and stdio flushed (as a node's process ends: ``pws_ros.nodes._ros``)."""
    code = main()
    threads = sys.modules.get(f"{__package__}.bridge.axis_threads")   # (imported only where axes ran: --help stays fast)
    if threads is not None and threads.axes_left_running():
        import os

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    run()
