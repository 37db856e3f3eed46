"""``pws bench``: measure PwS / PwS-L / PwS-OF against CMS on the procedural world and check the paper's claims."""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ..core.errors import require
from . import SUMMARIES

DEFAULT_MODELS = Path(__file__).resolve().parents[2] / "bags" / "models"

DESCRIPTION = """\
Certify held-out scenes of the procedural world (pws_ros.sim) with PwS, PwS-L and PwS-OF (paper,
pairwise and anchors coverage) and with the CMS baseline, using the same classifier, and measure
frames, classifier calls, seconds (plan / render / inference / statistics), certified accuracy
against the radius, the ablations (sigma 0.25/0.5/0.75, number of partitions, empirical robust vs
benign accuracy, denoiser) and scaling (partitions, image size, cloud size; time and peak memory).
Writes OUT/report.md (tables, and the paper's claims one by one), OUT/bench.json (every record,
machine info, versions, seeds) and PNG plots. Progress goes to stderr."""

EPILOG = """\
presets:
  --quick  6 planned scenes (6 axes), 3 certified scenes (tz, ry), n=64 per partition frame, grids
           capped at 33 partitions, CMS n=256, smaller ablations: about 4-6 min on 2 idle CPU cores
           (fills every table; the report states its reduced settings).
  (none)   the full run: 48 planned scenes, 24 certified scenes (2 per class), n=1000 per partition
           frame, grids capped at 129 partitions, CMS n0=100 n=1000, all ablations at full size:
           about 6 h on 2 idle CPU cores, about 1 h with --device cuda (planning stays on the CPU);
           the quick report extrapolates the full run's duration from its own measurements.
models (--models, default bags/models): classifier_sigma0.50.pt (required), classifier_sigma0.25.pt,
classifier_sigma0.75.pt (else the sigma-0.5 classifier is smoothed at 0.75, as the report says),
denoiser_sigma0.50.pt; build them with `pws train all --out bags/models`.
example:
  pws bench --quick --out docs/bench      # refresh the committed quick report"""


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help=SUMMARIES["bench"],
                              description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="reduced settings (<= 10 min on 2 CPU cores), stated in the report")
    p.add_argument("--out", default="bench_out", help="output folder (default bench_out)")
    p.add_argument("--device", default="cpu", help="cpu or cuda[:i] for rendering and inference (default cpu)")
    p.add_argument("--models", default=None, help=f"folder with the demo models (default {DEFAULT_MODELS})")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: on the shared 2-core development machine one thread classified "
                        "3-10x faster than two; raise it on a dedicated many-core machine)")
    p.add_argument("--seed", type=int, default=0, help="seed of every noise and motion sample (default 0)")
    p.add_argument("--preset", choices=("quick", "full", "smoke"), default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..bench import PRESETS, run_bench, stderr_log

    preset = args.preset or ("quick" if args.quick else "full")
    require(args.threads is None or args.threads >= 1, f"--threads must be >= 1, got {args.threads}")
    require(str(args.device).split(":")[0] in ("cpu", "cuda"), f"--device must be cpu or cuda[:i], got {args.device!r}")
    previous = torch.get_num_threads()
    if args.threads is not None:
        torch.set_num_threads(int(args.threads))
    try:
        settings = replace(PRESETS[preset], seed=int(args.seed))
        models = Path(args.models) if args.models else DEFAULT_MODELS
        paths = run_bench(settings, models, args.out, device=args.device, log=stderr_log)
    finally:
        torch.set_num_threads(previous)
    print(f"wrote {paths['report']} and {paths['json']}")
    return 0
