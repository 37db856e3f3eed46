"""``pws train``: rebuild the demo classifier(s) and denoiser from the procedural world (seeded, CPU)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..core.errors import PwsError, require
from . import SUMMARIES
from .common import add_command_group


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=("full", "tiny"), default="full", help="full: the shipped recipe (about 5 min on 2 idle CPU cores, longer on a busy machine); tiny: seconds, for tests")
    p.add_argument("--seed", type=int, default=0, help="seed of the training views, initial weights and noise (default 0)")
    p.add_argument("--workers", type=int, default=2, help="processes generating training views (default 2)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--cache-dir", default=None, help="cache of generated views (default $PWS_SIM_CACHE or <tmp>/pws_sim_cache; '' disables)")


def register(subparsers) -> None:
    sub = add_command_group(subparsers, "train", SUMMARIES["train"],
                            "Seeded, CPU-only training on views of pws_ros.sim.", ("all", "classifier", "denoiser"))

    text = "classifiers for sigma 0.25 and 0.5, the sigma-0.5 denoiser, classes.txt, training_report.json"
    a = sub.add_parser("all", help=text, description=f"pws train all: {text}.")
    a.add_argument("--out", required=True, help="output folder (e.g. bags/models)")
    a.add_argument("--no-denoiser", action="store_true", help="the classifiers only")
    _common(a)
    a.set_defaults(func=run)

    for name, what, out in (("classifier", "one classifier trained with Gaussian noise of --sigma",
                             "model file to write (.pt, TorchScript + pws.json + <stem>.classes.txt)"),
                            ("denoiser", "a DnCNN-like denoiser for --sigma", "denoiser file to write (.pt, TorchScript)")):
        one = sub.add_parser(name, help=what, description=f"pws train {name}: {what}.")
        one.add_argument("--out", required=True, help=out)
        one.add_argument("--sigma", type=float, default=0.5, help="Gaussian noise sigma of the training (images in [0, 1]; default 0.5)")
        one.add_argument("--epochs", type=int, default=None, help="default: the preset's")
        _common(one)
        one.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..sim import train as T
    from ..sim.dataset import default_cache_dir, training_set

    cmd = getattr(args, "train_command", None)
    require(args.workers >= 1, f"--workers must be >= 1, got {args.workers}")
    require(args.threads >= 1, f"--threads must be >= 1, got {args.threads}")
    cache = default_cache_dir() if args.cache_dir is None else (None if args.cache_dir == "" else Path(args.cache_dir))
    if cmd == "all":
        report = T.build_models(args.out, preset=args.preset, seed=args.seed, workers=args.workers, cache_dir="" if cache is None else cache,
                                threads=args.threads, skip_denoiser=args.no_denoiser)
        print(json.dumps(report.get("heldout", {}), indent=2))
        print(f"wrote models to {args.out} ({report['total_seconds']:.0f}s)")
        return 0
    if cmd not in ("classifier", "denoiser"):
        raise PwsError(f"unknown train command {cmd!r}")
    require(args.sigma >= 0, f"--sigma must be >= 0, got {args.sigma}")
    require(args.epochs is None or args.epochs >= 1, f"--epochs must be >= 1, got {args.epochs}")
    import torch

    torch.set_num_threads(args.threads)
    p = T.PRESETS[args.preset]
    X, Y = training_set(p.train_scenes, p.views_per_scene, seed=args.seed, width=p.width, height=p.height, move_prob=p.move_prob,
                        workers=args.workers, cache_dir=cache)
    out = Path(args.out)
    if cmd == "classifier":
        from ..core.model import save_model
        from ..sim import CLASS_NAMES

        model = T.train_classifier(X, Y, args.sigma, epochs=args.epochs or p.epochs_05, seed=args.seed, width=p.net_width, log=print)
        save_model(model, out, CLASS_NAMES, input_size=(p.height, p.width), meta={"sigma": args.sigma, "preset": args.preset, "seed": args.seed})
    else:
        den = T.train_denoiser(X, args.sigma, epochs=args.epochs or p.denoiser_epochs, seed=args.seed, channels=p.denoiser_channels,
                               depth=p.denoiser_depth, log=print)
        T.save_denoiser(den, out, args.sigma, (p.height, p.width), meta={"preset": args.preset, "seed": args.seed})
    print(f"wrote {out}")
    return 0
