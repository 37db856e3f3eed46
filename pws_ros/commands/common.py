"""Arguments shared by several ``pws`` subcommands, and their loading."""
from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from typing import Any, Callable

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.certify import COVERAGES, CertifyConfig
from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.motion import AXES
from ..core.imaging import DEFAULT_RENDER_FACTOR, IMAGING_KINDS, UNCOVERED
from ..core.partition import DEFAULT_DELTA_PX, DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX, PLAN_METHODS


def add_command_group(subparsers, name: str, help: str, description: str, choices: Sequence[str]):
    """``pws NAME`` with required sub-commands ``choices`` (``pws sim record``, ``pws train all`` ...):
    the sub-parsers object, its choice stored in ``args.<name>_command``."""
    p = subparsers.add_parser(name, help=help, description=description)
    sub = p.add_subparsers(dest=f"{name}_command", metavar="{" + ",".join(choices) + "}")
    sub.required = True
    return sub


def _parsed(text: str, cast: Callable[[str], Any], what: str) -> Any:
    try:
        return cast(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None


def positive_float(text: str) -> float:
    v = _parsed(text, float, "a number")
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be positive and finite, got {text}")
    return v


def positive_int(text: str) -> int:
    v = _parsed(text, int, "an integer")
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return v


def nonnegative_int(text: str) -> int:
    v = _parsed(text, int, "an integer")
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def add_scene_args(p: argparse.ArgumentParser, radius: bool = True) -> None:
    p.add_argument("--cloud", required=True, metavar="C.npz",
                   help="cloud .npz (points (N,3) metres in the camera optical frame, colors (N,3)); the entire "
                        "dense cloud for --method pws, the one-frame cloud for pws_of")
    p.add_argument("--camera", required=True, metavar="CAM.yaml", help="ROS camera_info YAML (camera_calibration format)")
    p.add_argument("--axis", required=True, choices=AXES, help="motion axis: tx/ty/tz in metres, rx/ry/rz in radians")
    if radius:
        p.add_argument("--radius", required=True, type=positive_float, metavar="B",
                       help="certify every motion in [-B, B] (metres or radians)")


def add_plan_args(p: argparse.ArgumentParser, methods=PLAN_METHODS, default="pws_of") -> None:
    p.add_argument("--method", choices=methods, default=default,
                   help=f"partition method (default {default}): pws = entire cloud (Thm 1), pws_l = Lipschitz "
                        "(Thm 2), pws_of = one-frame cloud with delta-convexity (Thm 3)" + (", cms = motion-space baseline" if "cms" in methods else ""))
    p.add_argument("--delta", type=positive_float, default=None, metavar="D",
                   help=f"PwS-OF delta-convexity constant in pixels (default {DEFAULT_DELTA_PX})")
    p.add_argument("--max-partitions", type=positive_int, default=DEFAULT_FRAME_BUDGET, metavar="N",
                   help=f"most partitions (frames) per axis: plans needing more are made coarser (fewer frames, "
                        f"looser bounds, maybe a smaller certified radius), never refused (default {DEFAULT_FRAME_BUDGET})")
    p.add_argument("--imaging", choices=IMAGING_KINDS, default="surfel",
                   help="imaging model (default surfel): surfel = each point is the patch its depth pixel saw, rendered at "
                        "the camera's resolution on a centred crop and block-averaged to the model's input (no sampling "
                        "holes); paper = one point paints one pixel at the model's size (the paper's model)")
    p.add_argument("--border", type=int, default=-1, metavar="PX",
                   help="surfel imaging: output pixels masked along the image edges in every frame; -1 = computed "
                        "from the radius (default)")
    add_render_factor_arg(p)
    p.add_argument("--step-px", type=positive_float, default=DEFAULT_STEP_PX, metavar="PX",
                   help=f"surfel imaging: the plan moves no point more than PX rendered pixels per step (default {DEFAULT_STEP_PX})")
    p.add_argument("--min-partitions", type=int, default=0, metavar="N",
                   help="refine the planned grid to at least N partitions (still sound; tighter bounds where the method "
                        "plans only a few frames; default 0 = as planned)")


def image_size(text: str) -> tuple[int, int]:
    """``HxW`` (height first, as a model's ``input_size``) -> (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 90x160, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def add_render_factor_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--render-factor", type=int, default=DEFAULT_RENDER_FACTOR, metavar="K",
                   help=f"surfel imaging: render frames at K times the classifier's input, then block-average to it; "
                        f"below the camera's resolution the camera pixels are binned (default {DEFAULT_RENDER_FACTOR}; "
                        f"0 = the camera's full resolution, slower)")


def add_imaging_size_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size", type=image_size, default=None, metavar="HxW",
                   help="the classifier's input size, height x width like a model's input_size, e.g. 90x160 "
                        "(default: the camera's size); "
                        "`pws certify` takes it from the model")


def add_smoothing_args(p: argparse.ArgumentParser) -> None:
    d = CertifyConfig()
    p.add_argument("--coverage", choices=COVERAGES, default=d.coverage,
                   help="coverage rule: paper = max_i sqrt(B_i/2) < min_i R_i; pairwise = B_i < R_i^2 + R_{i+1}^2 per "
                        f"segment; anchors = p_A at K anchors only (default {d.coverage})")
    p.add_argument("--sigma", type=positive_float, default=d.sigma, help=f"pixel noise std (default {d.sigma})")
    p.add_argument("--n0", type=positive_int, default=d.n0, help=f"selection samples (default {d.n0})")
    p.add_argument("--n", type=positive_int, default=d.n, help=f"estimation samples per partition/anchor, the most (default {d.n})")
    p.add_argument("--n-first", type=nonnegative_int, default=d.n_first, dest="n_first", metavar="M",
                   help=f"anchors coverage, surfel imaging: samples of the anchors' joint first look (docs/certificate.md; "
                        f"0: N samples each at alpha / K; default {d.n_first})")
    p.add_argument("--alpha", type=positive_float, default=d.alpha, help=f"risk of the certificate: the probability that its statement is wrong, split by Bonferroni over every bound used (default {d.alpha})")
    p.add_argument("--seed", type=int, default=d.seed, help=f"noise seed (default {d.seed})")
    p.add_argument("--device", default=d.device, help="torch device: cpu or cuda[:N] (default cpu)")
    p.add_argument("--batch-size", type=positive_int, default=d.batch_size, help=f"classifier batch size (default {d.batch_size})")
    p.add_argument("--anchors", type=positive_int, default=d.num_anchors, dest="num_anchors",
                   help=f"anchors for --coverage anchors; with surfel imaging the estimation budget in anchors of N samples: "
                        f"n0 + ANCHORS * N classifier calls at most, up to ANCHORS * N / M anchors placed from the distance "
                        f"bounds with the joint first look (default {d.num_anchors})")
    p.add_argument("--cms-sigma", type=positive_float, default=None, help="CMS motion-space sigma (default per axis, REFERENCE.md)")
    add_background_arg(p)
    add_drawing_args(p)


def add_output_args(p, json_help: str, quiet_help: str | None = None) -> None:
    """The output flags the commands share: ``--json`` (``json_help`` says what it prints) and, for a command
    that shows progress, ``--quiet`` (``quiet_help`` says what it silences)."""
    p.add_argument("--json", action="store_true", help=json_help)
    if quiet_help is not None:
        p.add_argument("--quiet", action="store_true", help=quiet_help)


def add_drawing_args(p) -> None:
    """What the surfel imaging draws: ``--uncovered`` and ``--working-volume``."""
    p.add_argument("--uncovered", choices=UNCOVERED, default="frame",
                   help="surfel imaging: what a pixel no surfel covers shows: frame = its colour in the alpha = 0 frame "
                        "(default), background = --background")
    add_working_volume_arg(p, "(default: none, every point is drawn)")


VOLUME_KEYS = ("near", "far", "x_min", "x_max", "y_min", "y_max")
VOLUME_METAVAR = "[NEAR,]FAR[,XMIN,XMAX,YMIN,YMAX]"


def add_background_arg(p) -> None:
    p.add_argument("--background", type=float, default=None,
                   help="value of the masked border and of empty pixels (default 0.0; 0.5 with --working-volume)")


def add_working_volume_arg(p, default_text: str) -> None:
    p.add_argument("--working-volume", type=working_volume_limits, default=None, metavar=VOLUME_METAVAR,
                   help="surfel imaging: draw only the points with NEAR <= z <= FAR metres at alpha = 0 (and XMIN <= x <= XMAX, "
                        "YMIN <= y <= YMAX in the camera's optical frame); the rest of the image shows the background. "
                        f"E.g. 1.5 (0 to 1.5 m), 0.3,1.5; 0 = none {default_text}")


def add_volume_config_args(group) -> None:
    """``--working-volume`` and ``--background`` of the commands that read the nodes' config (replay, ceiling,
    finetune): they override ``working_volume.*`` and ``background``."""
    add_working_volume_arg(group, "(default: config working_volume, none)")
    group.add_argument("--window", type=float, default=None, metavar="BAND",
                       help="with a working volume: per frame only BAND metres from its subject (the largest depth-connected "
                            "cluster not spanning the view: a hand and arm, not a wall), in a camera window around it "
                            "(chosen at alpha = 0 from the depth; config working_volume.window; 0 = off)")
    group.add_argument("--background", type=float, default=None, metavar="V",
                       help="value in [0, 1] of the masked border and of what no drawn point covers, e.g. outside the "
                            "working volume (default: config background, -1 = automatic: 0.5 with a working volume, else 0)")


def working_volume_limits(text: str) -> dict[str, float]:
    """``--working-volume`` as ``{near, far, x_min, ...}`` (metres): FAR, NEAR,FAR or all six."""
    parts = [t for t in text.replace(",", " ").split() if t]
    vals = [_parsed(t, float, "a number") for t in parts]
    if len(vals) not in (1, 2, 6) or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected FAR, NEAR,FAR or NEAR,FAR,XMIN,XMAX,YMIN,YMAX (finite metres), got {text!r}")
    if len(vals) == 1:
        vals = [0.0] + vals
    return dict(zip(VOLUME_KEYS, vals))


def working_volume_params(limits: dict[str, float] | None, window: float | None = None) -> dict[str, float]:
    """The ``working_volume.*`` parameters of ``--working-volume`` (every key, so that the option replaces
    the config's volume as a whole) and ``--window``; {} when neither is given."""
    out = {} if limits is None else {f"working_volume.{k}": float(limits.get(k, 0.0)) for k in VOLUME_KEYS}
    if window is not None:
        out["working_volume.window"] = float(window)
    return out


def volume_from_args(args):
    """The :class:`~pws_ros.core.volume.WorkingVolume` of ``--working-volume`` (None: not given, or FAR 0)."""
    from ..core.volume import volume_from_limits

    limits = getattr(args, "working_volume", None)
    return None if limits is None else volume_from_limits(**{k: float(limits.get(k, 0.0)) for k in VOLUME_KEYS})


def background_from_args(args) -> float:
    """``--background``; not given: 0.0, or 0.5 with a working volume (:func:`~pws_ros.core.volume.resolve_background`)."""
    from ..core.volume import resolve_background

    given = getattr(args, "background", None)
    return resolve_background(-1.0 if given is None else float(given), volume_from_args(args))


def config_from_args(args) -> CertifyConfig:
    return CertifyConfig(working_volume=volume_from_args(args), sigma=args.sigma, n0=args.n0, n=args.n, alpha=args.alpha, seed=args.seed, device=args.device,
                         batch_size=args.batch_size, coverage=args.coverage, num_anchors=args.num_anchors, n_first=args.n_first,
                         background=background_from_args(args), uncovered=args.uncovered, max_partitions=args.max_partitions,
                         min_partitions=args.min_partitions, delta=args.delta,
                         cms_sigma=args.cms_sigma, imaging=getattr(args, "imaging", "surfel"),
                         border=getattr(args, "border", -1), step_px=getattr(args, "step_px", DEFAULT_STEP_PX),
                         render_factor=getattr(args, "render_factor", DEFAULT_RENDER_FACTOR)).validate()


ONE_FRAME_WARNING = ("warning: method pws needs the entire scene cloud (every surface that can come into view or be "
                     "uncovered over the motion range), but this cloud looks like a one-frame cloud (every point inside the "
                     "image, at most one per pixel): a plan or certificate is sound only for the entire cloud; use --method pws_of for a "
                     "one-frame cloud")


def looks_like_one_frame(cloud: Cloud, intr: CameraIntrinsics) -> bool:
    """True when ``cloud`` is what one camera frame sees: every point in front of the camera and
    inside its image, at most one per pixel (a cloud back-projected from one depth image). The
    entire scene cloud of method pws also holds what lies outside the image or hidden behind."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    z = pts[:, 2]
    if not np.all(z > 0):
        return False
    col = np.floor(intr.fx * pts[:, 0] / z + intr.cx + 0.5)
    row = np.floor(intr.fy * pts[:, 1] / z + intr.cy + 0.5)
    inside = (col >= 0) & (col < intr.width) & (row >= 0) & (row < intr.height)
    if not np.all(inside):
        return False
    per_pixel = np.bincount((row * intr.width + col).astype(np.int64), minlength=intr.width * intr.height)
    return int(per_pixel.max()) <= 1


def load_scene(args) -> tuple[Cloud, CameraIntrinsics]:
    """The cloud and camera of ``--cloud`` / ``--camera``; warns (stderr) when ``--method pws`` gets a
    one-frame cloud."""
    cloud = Cloud.load(args.cloud).require_nonempty()
    intr = CameraIntrinsics.from_yaml(args.camera)
    if getattr(args, "method", None) == "pws" and looks_like_one_frame(cloud, intr):
        print(f"pws {getattr(args, 'command', '')}: {ONE_FRAME_WARNING}", file=sys.stderr)
    return cloud, intr


def emit(obj: dict, as_json: bool, lines: list[str]) -> None:
    if as_json:
        json.dump(obj, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print("\n".join(lines))


def require_ratio_alpha(alpha: float) -> None:
    require(0 < alpha < 1, f"--alpha must lie in (0, 1), got {alpha}")


__all__ = ["PwsError", "add_plan_args", "add_scene_args", "add_smoothing_args", "config_from_args", "emit", "load_scene",
           "positive_float", "positive_int"]
