"""``pws certify``: certify one cloud against motion along one axis."""
from __future__ import annotations

import sys
from dataclasses import replace

from ..core.certify import METHODS, certify
from ..core.model import load_denoiser, load_model
from ..core.render import resolve_device
from ..replay.progress_log import Progress
from .common import add_output_args, add_plan_args, add_scene_args, add_smoothing_args, config_from_args, emit, load_scene
from . import SUMMARIES


def register(sub) -> None:
    p = sub.add_parser("certify", help=SUMMARIES["certify"],
                       description="Plan, render and certify: is the smoothed prediction the same for every camera "
                                   "motion in [-B, B] along AXIS? Prints the label, the certified radius (the largest "
                                   "covered symmetric sub-interval of the grid), the p_A lower bounds and what the "
                                   "certificate rests on (N, n, alpha, M, R, timings).")
    add_scene_args(p)
    p.add_argument("--model", required=True, metavar="M.pt", help="TorchScript classifier: (B,3,H,W) in [0,1] -> logits (B,C)")
    p.add_argument("--classes", metavar="FILE", help="class names, one per line (default: <model>.classes.txt or classes.txt beside it)")
    p.add_argument("--denoiser", metavar="D.pt", help="optional TorchScript denoiser applied after the noise")
    add_plan_args(p, methods=METHODS)
    add_smoothing_args(p)
    add_output_args(p, "print the certificate as JSON", "no progress (a bar on a terminal, else a line every 30 s)")
    p.set_defaults(func=run)


def run(args) -> int:
    cloud, intr = load_scene(args)
    config = config_from_args(args)
    device = resolve_device(config.device)
    model = load_model(args.model, classes=args.classes, device=device)
    if model.input_size is not None and tuple(model.input_size) != intr.shape:
        h, w = model.input_size
        print(f"pws certify: rendering at the model's input size {w}x{h} (camera is {intr.width}x{intr.height})", file=sys.stderr)
        intr = intr.scaled(w, h)
    denoiser = load_denoiser(args.denoiser, device=device) if args.denoiser else None
    if args.method != "cms":   # the size of the frames the classifier gets: the model's, else the camera's
        from ..bridge.sizing import choose_batch_size

        shape = tuple(model.input_size) if model.input_size is not None else intr.shape
        batch_size, _ = choose_batch_size(model, shape, config.batch_size, config.sigma, device=device, denoiser=denoiser,
                                          log=None if args.quiet else lambda level, text: print(f"pws certify: {text}", file=sys.stderr))
        config = replace(config, batch_size=batch_size)
    bar = Progress(label=f"pws certify {args.method} {args.axis}", unit="images", mode="off" if args.quiet else None)
    try:
        cert = certify(cloud, intr, model, args.axis, args.radius, args.method, config, denoiser=denoiser, progress=bar.update_to)
    finally:
        bar.close()
    d = cert.to_dict(full=args.json)
    lines = [cert.summary(), ""]
    for key in ("status", "label", "class_name", "certified", "radius", "unit", "min_p_a_lower", "num_partitions",
                "delta_alpha", "num_bounds", "classifier_calls", "frames_rendered"):
        lines.append(f"{key:18s}{d[key]}")
    lines.append(f"{'bounds':18s}" + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in cert.bounds.items()))
    lines.append(f"{'timings (s)':18s}" + ", ".join(f"{k}={v:.3f}" for k, v in cert.timings.items()))
    emit(d, args.json, lines)
    return 0
