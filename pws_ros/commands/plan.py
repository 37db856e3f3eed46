"""``pws plan``: the uniform partition of the motion range (PwS / PwS-L / PwS-OF)."""
from __future__ import annotations

from ..core.imaging import make_imaging, plan_for
from .common import (add_imaging_size_arg, add_output_args, add_plan_args, add_scene_args, add_working_volume_arg, emit, load_scene,
                     volume_from_args)
from . import SUMMARIES


def register(sub) -> None:
    p = sub.add_parser("plan", help=SUMMARIES["plan"],
                       description="Compute delta_alpha and the grid of camera motions (from -B to +B, containing 0) "
                                   "that PwS, PwS-L or PwS-OF needs for a cloud, camera, axis and radius.")
    add_scene_args(p)
    add_plan_args(p)
    add_imaging_size_arg(p)
    p.add_argument("--out", metavar="PLAN.json", help="also write the plan as JSON (input of `pws render --plan`)")
    add_working_volume_arg(p, "(default: none, every point is drawn)")
    add_output_args(p, "print the plan as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    cloud, intr = load_scene(args)
    im = make_imaging(args.imaging, intr, args.size, border=args.border, cloud=cloud, radii={args.axis: args.radius},
                      render_factor=args.render_factor, volume=volume_from_args(args))
    plan = plan_for(cloud, im, args.axis, args.radius, args.method, step_px=args.step_px, delta=args.delta,
                    max_partitions=args.max_partitions, min_partitions=args.min_partitions)
    if args.out:
        plan.to_json(args.out, indent=1)
    d = plan.to_dict()
    emit(d, args.json, [
        f"method          {plan.method}",
        f"axis            {plan.axis} ({plan.unit})",
        f"radius          {plan.radius:g}",
        f"delta_alpha     {plan.delta_alpha:.6g}",
        f"num_partitions  {plan.num_partitions}",
        f"alphas          {plan.alphas[0]:g} .. {plan.alphas[-1]:g} (step {plan.alphas[1] - plan.alphas[0]:.6g}, contains 0)",
        "details         " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in plan.details.items()),
    ] + ([f"written         {args.out}"] if args.out else []))
    return 0
