"""``pws render``: the frames of a plan and their per-segment bounds."""
from __future__ import annotations

import numpy as np

from ..core.bounds import render_plan
from ..core.errors import require
from ..core.imaging import IMAGING_KINDS, make_imaging, render_plan_surfel
from ..core.partition import Plan
from .common import add_imaging_size_arg, add_output_args, add_render_factor_arg, add_scene_args, add_drawing_args, emit, load_scene, volume_from_args, background_from_args, add_background_arg
from . import SUMMARIES


def register(sub) -> None:
    p = sub.add_parser("render", help=SUMMARIES["render"],
                       description="Render a frame for every motion of PLAN.json (from `pws plan --out`) and write an "
                                   ".npz with frames (N,H,W,3) float32 in [0,1], alphas (N,) and pair_bound_sq (N-1,): "
                                   "for every alpha in segment i, |x(alpha)-x_i|^2 + |x(alpha)-x_{i+1}|^2 <= pair_bound_sq[i].")
    add_scene_args(p, radius=False)
    p.add_argument("--plan", required=True, metavar="PLAN.json", help="plan written by `pws plan --out`")
    add_background_arg(p)
    add_drawing_args(p)
    p.add_argument("--imaging", choices=IMAGING_KINDS, default="surfel", help="imaging model (default surfel; see `pws certify --help`)")
    p.add_argument("--border", type=int, default=-1, metavar="PX", help="surfel imaging: masked border in output pixels (-1 = from the plan's radius)")
    add_render_factor_arg(p)
    add_imaging_size_arg(p)
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--out", required=True, metavar="F.npz", help="output .npz")
    add_output_args(p, "print a JSON summary")
    p.set_defaults(func=run)


def run(args) -> int:
    cloud, intr = load_scene(args)
    plan = Plan.load(args.plan)
    require(plan.axis == args.axis, f"--axis {args.axis} differs from the plan's axis {plan.axis}")
    im = make_imaging(args.imaging, intr, args.size, background=background_from_args(args), border=args.border, cloud=cloud,
                      radii={plan.axis: plan.radius}, render_factor=args.render_factor, uncovered=args.uncovered, volume=volume_from_args(args))
    if im.kind == "surfel":
        rp = render_plan_surfel(cloud, im, plan, device=args.device)
    else:
        rp = render_plan(cloud, im.camera, plan, background=background_from_args(args), device=args.device)
    frames = rp.frames.cpu().numpy()
    np.savez_compressed(args.out, frames=frames, alphas=plan.alphas, pair_bound_sq=rp.pair_bound_sq)
    plain = ((frames[1:].astype(np.float64) - frames[:-1]) ** 2).reshape(len(frames) - 1, -1).sum(1)
    summary = {"out": args.out, "num_frames": int(len(frames)), "height": int(frames.shape[1]), "width": int(frames.shape[2]),
               "max_pair_bound_sq": float(rp.pair_bound_sq.max()) if len(rp.pair_bound_sq) else 0.0,
               "segments_beyond_lemma1": int(np.sum(rp.pair_bound_sq > plain * (1 + 1e-6) + 1e-12)),
               "seconds": rp.seconds}
    emit(summary, args.json, [f"{k:24s}{v}" for k, v in summary.items()])
    return 0
