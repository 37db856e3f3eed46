"""``pws ceiling``: what a recording's camera allows (the ceiling) next to what a model gets."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..core.errors import PwsError, require
from .common import add_output_args, add_volume_config_args, image_size
from . import SUMMARIES

DESCRIPTION = """\
For each frame of a recording (or of several) and each axis: the certificate CEILING, the radius that a classifier
that never changes its answer gets (every noise sample votes for one class, so every anchor has the
largest p_A bound the sample sizes allow), next to the radius your model gets, as a share of the
requested radius, with the time per axis.

The ceiling is set by the camera and the imaging (input size, render_factor, depth fill, what moves
into view), the requested radius and the anchor budget (n0, n, num_anchors, alpha, sigma): no model
can do better (up to the anchors' placement). A low ceiling says: request a smaller radius, raise
sigma, or use a smaller model input. A high ceiling and a low model radius say: the model's answer
changes under noise of this sigma (pws finetune, a denoiser, or a smaller sigma).

The configuration is read as by `pws replay` (--config, else config/pws.yaml, else defaults); the
options below override it. Nothing is written."""

EPILOG = """\
examples:
  pws ceiling ../shared/data/kinect_organized_cloud --model models/my_net.pt --sigma 0.25
  pws ceiling my_recording --size 90x160 --max-frames 5 --no-model      # the ceiling alone, 160x90 input
  pws ceiling bags/demo --max-frames 2 --json
  pws ceiling rec_a rec_b rec_c --size 90x160 --no-model   # one table, medians over the three"""


def register(subparsers) -> None:
    p = subparsers.add_parser("ceiling", help=SUMMARIES["ceiling"],
                              description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", metavar="bag",
                   help="rosbag2 bag directory, or a bare .mcap / .db3 file; several: one table, the medians over all")
    p.add_argument("--model", default=None, help="your TorchScript classifier (default: config model_path)")
    p.add_argument("--no-model", action="store_true", help="the ceiling alone (needs --size, or a model that declares its input)")
    p.add_argument("--size", type=image_size, default=None, metavar="HxW",
                   help="the classifier input of the ceiling, height first as a model's input_size (default: the "
                        "model's declared input size)")
    p.add_argument("--max-frames", type=int, default=3, metavar="K", help="frames to measure (default 3)")
    add_output_args(p, "print the rows and the advice as JSON", "no progress")
    c = p.add_argument_group("certification (override the config, as in pws replay)")
    c.add_argument("--config", default=None, help="ROS 2 parameter file (default: config/pws.yaml if found, else built-in defaults)")
    c.add_argument("--axes", default=None, help="comma-separated axes (default: config axes, tz,ry)")
    c.add_argument("--radius", default=None, help="requested radius per axis, e.g. tz=0.01,ry=0.25deg")
    for name, kind, text in (("--sigma", float, "pixel noise sigma (default: config sigma, 0.5)"),
                             ("--n0", int, "selection samples (default: config n0, 64)"),
                             ("--n", int, "estimation samples per anchor (default: config n, 256)"),
                             ("--alpha", float, "risk of a frame (default: config alpha, 0.01)"),
                             ("--n-first", int, "samples of the anchors' joint first look (0: n per anchor at alpha / K; "
                                                "default: config n_first, 64)"),
                             ("--anchors", int, "estimation budget per axis in anchors of n samples (default: config num_anchors, 24)"),
                             ("--render-factor", int, "surfel render factor (default: config render_factor, 2)"),
                             ("--seed", int, "random seed (default: config seed, 0)"),
                             ("--batch-size", int, "images per classifier call, the most (default: config batch_size, 256)")):
        c.add_argument(name, type=kind, default=None, help=text)
    add_volume_config_args(c)
    c.add_argument("--device", default=None, help="cpu or cuda:N (default: config device, cpu)")
    i = p.add_argument_group("input (as in pws replay)")
    for name in ("cloud", "depth", "color", "info", "depth-info"):
        i.add_argument(f"--{name}-topic", default=None, help=f"the {name.replace('-', ' ')} topic (default: found in the bag, as pws replay does)")
    p.set_defaults(func=run, truth_topic=None, classes=None, denoiser=None)


def run(args: argparse.Namespace) -> int:
    from ..bridge.config import resolve_path
    from ..core.model import load_model
    from ..replay import ReplayOptions
    from ..replay.ceiling import advice, ceiling, format_rows, stopped
    from ..replay.interrupt import Interrupted
    from .replay import build_config, input_topics

    try:
        require(args.max_frames >= 1, f"--max-frames must be >= 1, got {args.max_frames}")
        cfg = build_config(args)
        model = None
        if not args.no_model:
            model = load_model(resolve_path(cfg.model_path, "model file"), device=cfg.device)
        rows, signame = [], ""
        for bag in args.bags:
            opts = ReplayOptions(bag=Path(bag), config=cfg, write_output=False, topics=input_topics(args),
                                 max_frames=args.max_frames, quiet=args.quiet, progress=False if args.quiet else None,
                                 label="pws ceiling")
            try:
                got, top, theirs = ceiling(opts, model, input_size=args.size)
            except PwsError as exc:
                raise PwsError(f"{bag}: {exc}") from exc
            rows += got
            signame = stopped(top) or (stopped(theirs) if theirs is not None else "")
            if signame:   # Ctrl-C: the table of the frames finished, then the signal's exit status
                break
    except PwsError as exc:
        print(f"pws ceiling: error: {exc}", file=sys.stderr)
        return 2
    tips = advice(rows)
    if args.json:
        print(json.dumps({"rows": [r.to_dict() for r in rows], "advice": tips, "sigma": cfg.sigma, "n0": cfg.n0, "n": cfg.n,
                          "num_anchors": cfg.num_anchors, "alpha": cfg.alpha}, indent=2))
    else:
        who = "ceiling alone" if model is None else f"model {cfg.model_path}"
        print(f"{', '.join(args.bags)}: {who}; sigma {cfg.sigma:g}, n0 {cfg.n0}, n {cfg.n}, {cfg.num_anchors} anchors, alpha {cfg.alpha:g}; "
              "radius as a share of the requested one, seconds per axis")
        print(format_rows(rows))
        for line in tips:
            print(line)
    if signame:
        frames = len({(r.recording, r.frame) for r in rows})
        print(f"pws ceiling: interrupted ({signame}) after {frames} frame(s): the table covers those", file=sys.stderr)
        return Interrupted(signame).exit_code
    return 0
