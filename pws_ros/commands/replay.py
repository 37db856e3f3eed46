"""``pws replay``: certify a rosbag2 recording offline and write the results as a bag."""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from ..core.errors import PwsError, require, require_creatable
from .common import add_output_args, add_volume_config_args, working_volume_params
from . import SUMMARIES

DESCRIPTION = """\
Certify every camera frame of a rosbag2 recording against camera motion, offline, with exactly the
logic of the live `pipeline` node, and write the results as a new bag.

Input: a bag directory (with metadata.yaml) or a bare .mcap / .db3 file; MCAP or sqlite3, split
bags, zstd compression. The camera input is found by message type: an organized
sensor_msgs/PointCloud2, or a depth Image (16UC1/mono16 mm or 32FC1 m) registered to a colour Image
(rgb8/bgr8/rgba8/bgra8/mono8) plus the colour CameraInfo; --cloud-topic / --depth-topic /
--color-topic / --info-topic choose topics explicitly. Frames are processed in header-stamp order,
as fast as the CPU/GPU allows. Service-event topics and types whose definition does not parse are
skipped with a warning; a truncated MCAP file is read up to the damage.

Output (OUT, default <bag>_pws next to the bag; a rosbag2 MCAP bag, log time = source stamp, so
`ros2 bag play OUT` replays the results as the live nodes published them; opens in Foxglove,
PlotJuggler, rosbags, the mcap tools):
  certification          diagnostic_msgs/DiagnosticArray, one per processed input frame; header =
                         the source header; one status `pws/<axis>` per axis (level OK certified,
                         WARN not certified / abstained, ERROR could not certify) with the keys
                         label class_name certified radius unit p_a_lower sigma n alpha
                         num_partitions classifier_calls latency_ms compute_ms, then status
                         requested_radius method coverage n0 delta_alpha num_bounds
                         frames_rendered reason node
  certification/markers  visualization_msgs/MarkerArray (text per axis; --no-markers to omit)
  plan/poses/<axis>      geometry_msgs/PoseArray, the partition camera poses (--no-poses to omit)
  cloud, cloud/camera_info   the one-frame cloud and its camera (--write-cloud)
  certified_label        diagnostic_msgs/DiagnosticArray, only for a frame certified on every axis
                         with one label: one status `pws/certified_label`, message = the class name
  rendered/preview       every --preview-every-th rendered frame, rgb8 (--preview)
  the input topics       copied unchanged, at their recorded log time (--copy-inputs)

--video FILE.mp4 (or .avi, or a folder for one PNG per frame) writes, for every frame, the picture the
nodes publish on certification/overlay: what the classifier saw at the recorded pose, its label and
p_A, and one bar per axis, the certified share of the requested radius (green certified, orange not,
red error); written under a temporary name and renamed when the replay ends (also when stopped).

It shows progress on stderr (a bar with ETA on a terminal; else a plain line every --progress-interval
seconds with frames done, rate, ETA and the last results; --quiet hides it) and prints a summary: frames seen,
certified, abstained, errors, certified radius per axis (mean / median), time per certificate,
and, when the bag holds ground truth (/pws/ground_truth, written by `pws sim record`), clean
accuracy, certified accuracy and certified accuracy vs radius.

latency_ms is the time from the source stamp to publication: by default the processing time of the
frame (as if it were certified the moment it arrived); with --realtime the simulated publication
time (queueing included) minus the stamp. compute_ms is the measured time of each axis. The status
`node` key is "pws_replay" (the live nodes write their own name).

Parameters come from --config (default config/pws.yaml when present; the ROS parameter file of the
nodes) and the options below override them. Same bag + same seed = identical certificates
(latency_ms and compute_ms are measured times).

Exit status: 0 when at least one certificate could be computed (frames that failed are written as
ERROR statuses and counted); 2 when nothing could be done (bad arguments, unreadable or empty bag,
no camera input, a model that does not load, or every frame failed), with one line naming why;
130 (SIGINT, Ctrl-C) or 143 (SIGTERM) when stopped: the frame in flight is dropped, OUT is closed
and complete up to the last finished frame, and the summary/report (marked "interrupted") cover
the frames done. The bag is flushed after every frame, so even after SIGKILL or an out-of-memory
kill the .mcap holds every finished frame (no footer nor metadata.yaml then: `pws replay` and the
mcap stream reader read it; rosbags and `ros2 bag` need a copy repaired with `mcap recover`)."""

EPILOG = """\
examples:
  pws replay bags/demo                                   # writes bags/demo_pws, prints the summary
  pws replay bags/demo --out /tmp/demo_out --overwrite --report /tmp/demo_report
  pws replay bags/demo --axes tz --radius tz=5mm --n0 32 --n 128 --max-frames 5
  pws replay my_robot.mcap --depth-topic /camera/aligned_depth_to_color/image_raw \\
      --color-topic /camera/color/image_raw --info-topic /camera/color/camera_info --realtime
  pws replay bags/demo --method pws          # the entire cloud, regenerated from the ground truth
  pws replay bags/demo --json --quiet > summary.json
  pws replay bags/demo --no-output --video /tmp/demo.mp4          # the overlay of every frame, to watch
  pws replay bags/demo --workers 2 --out /tmp/demo_out --overwrite   # frames as Ray tasks (pip install 'pws_ros[ray]')"""

_UNIT_SCALE = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "rad": 1.0, "deg": math.pi / 180.0, "°": math.pi / 180.0}


def parse_radius(text: str, axes: list[str] | tuple[str, ...]) -> dict[str, float]:
    """``"tz=0.01,ry=0.25deg"`` -> ``{"tz": 0.01, "ry": 0.00436...}``; a bare value needs one axis.

    Units: m, mm, cm for translations; rad, deg for rotations (default: m / rad)."""
    from ..core.motion import UNITS, parse_axis

    out: dict[str, float] = {}
    items = [s.strip() for s in str(text).split(",") if s.strip()]
    require(bool(items), "--radius is empty")
    for item in items:
        if "=" in item:
            name, value = (s.strip() for s in item.split("=", 1))
            axis = parse_axis(name)
        else:
            require(len(axes) == 1, f"--radius {text!r}: give axis=value pairs (e.g. tz=0.01,ry=0.0044) when certifying several axes")
            axis, value = axes[0], item
        m = re.fullmatch(r"([-+0-9.eE]+)\s*([a-z°]*)", value)
        require(m is not None, f"--radius {item!r}: expected a number with an optional unit (m, mm, cm, rad, deg)")
        num, unit = m.group(1), m.group(2) or UNITS[axis]
        try:
            v = float(num)
        except ValueError:
            raise PwsError(f"--radius {item!r}: {num!r} is not a number") from None
        require(unit in _UNIT_SCALE, f"--radius {item!r}: unknown unit {unit!r} (m, mm, cm, rad, deg)")
        linear = unit in ("m", "mm", "cm")
        require(linear == (UNITS[axis] == "m"), f"--radius {item!r}: axis {axis} is measured in {UNITS[axis]}, not {unit}")
        v *= _UNIT_SCALE[unit]
        require(math.isfinite(v) and v > 0, f"--radius {item!r}: the radius must be positive and finite")
        require(axis not in out, f"--radius {text!r}: axis {axis} is given twice")
        require(axis in axes, f"--radius {item!r}: axis {axis} is not certified (axes: {', '.join(axes)}): "
                              f"add it to --axes, or leave its radius out")
        out[axis] = v
    return out


def axes_radius_params(args: argparse.Namespace, cfg) -> dict[str, Any]:
    """The parameters ``--axes`` and ``--radius`` set over the configuration ``cfg`` (a bare radius needs
    one axis: of ``--axes`` when given, else of ``cfg``); ``pws finetune`` reads them the same way."""
    from ..bridge.params import validate_param

    params: dict[str, Any] = {}
    if args.axes is not None:
        require(bool(str(args.axes).strip(" ,")), "--axes is empty: name the axes to certify, e.g. tz,ry")
        params["axes"] = validate_param("axes", args.axes)
    axes = params.get("axes", cfg.axes)
    if args.radius:
        for axis, v in parse_radius(args.radius, axes).items():
            params[f"radius.{axis}"] = v
    return params


def input_topics(args: argparse.Namespace) -> dict[str, str]:
    """The input topics named by the ``--*-topic`` options (``--depth-info-topic ""`` is kept: no check)."""
    topics = {"cloud": args.cloud_topic, "depth": args.depth_topic, "color": args.color_topic, "info": args.info_topic,
              "depth_info": args.depth_info_topic, "truth": args.truth_topic}
    return {k: v for k, v in topics.items() if v or (k == "depth_info" and v == "")}


def progress_interval(args: argparse.Namespace) -> dict[str, float]:
    """``{"progress_interval_s": s}`` when ``--progress-interval`` is given (checked), else nothing."""
    interval = {}
    if args.progress_interval is not None:
        require(math.isfinite(args.progress_interval) and args.progress_interval >= 0,
                f"--progress-interval must be >= 0 seconds, got {args.progress_interval}")
        interval["progress_interval_s"] = args.progress_interval
    return interval


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help=SUMMARIES["replay"],
                              description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="rosbag2 bag directory, or a bare .mcap / .db3 file")
    o = p.add_argument_group("output")
    o.add_argument("--out", default=None, help="output bag directory (default: <bag>_pws next to the bag); must not exist unless --overwrite")
    o.add_argument("--overwrite", action="store_true", help="replace OUT if it is an existing bag directory (never any other folder), and a --video file "
                   "or folder of PNGs")
    o.add_argument("--no-output", action="store_true", help="write no bag: only the summary (and --report)")
    o.add_argument("--copy-inputs", action="store_true", help="copy the input topics (and the ground truth) into OUT unchanged")
    o.add_argument("--write-cloud", action="store_true", help="write the one-frame cloud on 'cloud' (+ 'cloud/camera_info')")
    o.add_argument("--preview", action="store_true", help="write rendered frames on 'rendered/preview' (rgb8)")
    o.add_argument("--preview-every", type=int, default=None, help="with --preview: every k-th frame of a plan (and alpha = 0); default: config preview_every")
    o.add_argument("--no-markers", action="store_true", help="omit 'certification/markers'")
    o.add_argument("--no-poses", action="store_true", help="omit 'plan/poses/<axis>'")
    o.add_argument("--namespace", default="", help="prefix of the output topics, as the nodes' namespace (default: none, /certification ...)")
    o.add_argument("--no-compression", action="store_true", help="MCAP chunks without zstd")
    o.add_argument("--report", default=None, metavar="DIR", help="write DIR/frames.csv (per frame and axis), DIR/summary.json, "
                   "DIR/certified_accuracy_vs_radius.png and DIR/frames.png (radius and latency over time); in an existing "
                   "folder, files of these names are replaced")
    o.add_argument("--video", default=None, metavar="PATH",
                   help="write the overlay picture of every frame (the view, label, p_A and a bar per axis; as the nodes' "
                        "certification/overlay) to PATH: a .mp4 or .avi video, or a folder (no suffix) of PNGs")
    o.add_argument("--video-fps", type=float, default=None, metavar="F", help="frames per second of the --video file (default 10)")
    add_output_args(o, "print the summary as JSON on stdout instead of the table", "no progress (bar or lines) and no info lines (warnings and the summary still print)")
    o.add_argument("--progress-interval", type=float, default=None, metavar="S",
                   help="when stderr is not a terminal: one progress line (frames done, rate, ETA, last results) every S seconds "
                        "(default 30; 0 = after every frame)")

    c = p.add_argument_group("certification (override the config)")
    c.add_argument("--config", default=None, help="ROS 2 parameter file (default: config/pws.yaml if found, else built-in defaults)")
    c.add_argument("--axes", default=None, help="comma-separated axes among tx,ty,tz,rx,ry,rz (default: config axes, tz,ry)")
    c.add_argument("--radius", default=None, help="requested radius per axis, e.g. tz=0.01,ry=0.25deg (units m, mm, cm, rad, deg; "
                   "a bare number when one axis); default: config radius.<axis>")
    c.add_argument("--method", default=None, choices=("pws_of", "pws", "pws_l", "cms"),
                   help="pws_of (one-frame cloud, default), pws_l (Lipschitz), pws (the entire scene cloud: dense_cloud_path, or "
                        "regenerated from the ground truth of a pws sim recording), cms (baseline)")
    c.add_argument("--coverage", default=None, choices=("pairwise", "paper", "anchors"), help="coverage rule (default: config coverage, anchors)")
    c.add_argument("--n0", type=int, default=None, help="noise samples selecting the top class (default: config n0, 64)")
    c.add_argument("--n", type=int, default=None, help="noise samples per bound estimating p_A, the most (default: config n, 256)")
    c.add_argument("--n-first", type=int, default=None, metavar="M",
                   help="samples of the anchors' joint first look (default: config n_first, 64; 0: n samples each at alpha / K)")
    c.add_argument("--sigma", type=float, default=None, help="pixel noise sigma of the smoothed classifier (images in [0, 1]; default: config sigma, 0.5)")
    c.add_argument("--alpha", type=float, default=None,
                   help="risk of each frame's certificate, all its axes together (split over the axes, then by Bonferroni "
                        "over every bound; default: config alpha, 0.01)")
    c.add_argument("--seed", type=int, default=None, help="random seed (same bag + seed = same certificates; default: config seed, 0)")
    c.add_argument("--device", default=None, help="cpu or cuda:N (falls back to cpu with a warning; default: config device, cpu)")
    c.add_argument("--batch-size", type=int, default=None, help="images per classifier call, the most (default: config batch_size, 256)")
    c.add_argument("--max-partitions", type=int, default=None,
                   help="the cap on the cost per frame: plans needing more partitions are made coarser (fewer frames, "
                        "looser bounds, maybe a smaller certified radius), never refused (default: config max_partitions, 257)")
    c.add_argument("--imaging", default=None, choices=("surfel", "paper"),
                   help="imaging model (default: config imaging, surfel; --method pws implies paper): surfel renders each "
                        "point as the patch its depth pixel saw at the camera's resolution and block-averages a centred "
                        "crop to the model's input; paper paints one pixel per point at the model's size")
    c.add_argument("--border", type=int, default=None, help="surfel imaging: masked border in output pixels (-1 = from the radii)")
    c.add_argument("--render-factor", type=int, default=None, metavar="K",
                   help="surfel imaging: render at K times the model's input, camera pixels binned to it (default: config "
                        "render_factor, 2; 0 = the camera's full resolution, slower)")
    add_volume_config_args(c)
    c.add_argument("--anchors", type=int, default=None,
                   help="estimation budget per axis in anchors of n samples (n0 + anchors * n classifier calls at most; "
                        "up to anchors * n / n_first anchors with the joint first look; default: config num_anchors, 24)")
    c.add_argument("--time-budget", type=float, default=None, metavar="S",
                   help="seconds per frame; each axis gets what is left of it, shared evenly over the axes still to run: "
                        "n0, num_anchors, n and max_partitions of each axis are "
                        "sized from the measured cost of a classifier call and of the geometry before any sample is drawn; "
                        "a frame that needs more gets a smaller radius (default: config time_budget_s, 0 = off)")
    c.add_argument("--audit-every", type=int, default=None,
                   help="self-audit every k-th frame: re-render poses in every segment and check every bound; a "
                        "violation turns the axis to ERROR (default: config audit_every, 0 = off)")
    c.add_argument("--min-partitions", type=int, default=None,
                   help="refine each plan to at least this many partitions (still sound; tightens the bounds where the method "
                        "plans only a few frames; default: config min_partitions)")
    c.add_argument("--model", default=None, help="TorchScript classifier (default: config model_path, bags/models/classifier_sigma0.50.pt)")
    c.add_argument("--classes", default=None, help="class-names file (default: beside the model)")
    c.add_argument("--denoiser", default=None, help="optional TorchScript denoiser")
    c.add_argument("--dense-cloud", default=None, help="method pws: the entire scene cloud (.npz) of a static scene")

    i = p.add_argument_group("input")
    i.add_argument("--cloud-topic", default=None, help="organized PointCloud2 topic (implies point-cloud input)")
    i.add_argument("--depth-topic", default=None, help="depth Image topic registered to the colour camera (implies RGB-D input)")
    i.add_argument("--color-topic", default=None, help="colour Image topic")
    i.add_argument("--info-topic", default=None, help="CameraInfo of the colour camera")
    i.add_argument("--depth-info-topic", default=None, help="CameraInfo of the depth stream (depth whose intrinsics differ is refused); "
                   "default: the config's depth_camera_info_topic, else found beside the depth topic; \"\" = no such check")
    i.add_argument("--truth-topic", default=None, help="ground-truth DiagnosticArray topic (default: /pws/ground_truth when present)")
    i.add_argument("--sync-tolerance", type=float, default=None, help="depth/colour stamps at most this far apart are one frame, "
                   "matched immediately, s (default: config, 0.02)")
    i.add_argument("--sync-max-skew", type=float, default=None, help="unsynchronised drivers: a depth/colour pair farther apart than "
                   "--sync-tolerance but within this is matched when neither has a nearer partner (or at the end of the "
                   "recording), with a warning naming the skew, s (default: config, 0.2; 0 = off)")
    i.add_argument("--max-frames", type=int, default=None, metavar="K", help="stop after K input frames")
    r = p.add_argument_group("distributed (the optional extra: pip install 'pws_ros[ray]')")
    r.add_argument("--workers", type=int, default=None, metavar="N",
                   help="certify the frames as Ray tasks on N CPUs of a local Ray instance (or of --ray-address): the "
                        "driver writes the output in stamp order, at most 2N frames in flight, a frame whose worker dies "
                        "is re-run; certificates equal the serial run's (default: serial, one process)")
    r.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --workers: an existing Ray cluster (e.g. auto or ray://host:10001) instead of a local instance; "
                        "pws_ros and the model file must be available on its nodes")
    i.add_argument("--realtime", action="store_true", help="the live node's online policy: a frame arriving (recorded stamps) while a "
                   "certification would still run waits in a one-frame slot and is dropped if a newer one comes (drops are counted); "
                   "default: certify every frame")
    p.set_defaults(func=run)


def build_config(args: argparse.Namespace):
    """The PwsConfig of the command line: --config (or config/pws.yaml) then the options."""
    from ..replay.options import load_replay_config, override_config

    cfg = load_replay_config(args.config)
    params = axes_radius_params(args, cfg)
    simple = {"method": "method", "coverage": "coverage", "n0": "n0", "n": "n", "sigma": "sigma", "alpha": "alpha", "seed": "seed",
              "device": "device", "batch_size": "batch_size", "model": "model_path", "classes": "classes_path",
              "denoiser": "denoiser_path", "dense_cloud": "dense_cloud_path", "sync_tolerance": "sync_tolerance_s",
              "sync_max_skew": "sync_max_skew_s",
              "preview_every": "preview_every", "max_partitions": "max_partitions",
              "min_partitions": "min_partitions", "imaging": "imaging", "border": "border", "render_factor": "render_factor", "anchors": "num_anchors", "n_first": "n_first",
              "audit_every": "audit_every", "time_budget": "time_budget_s"}
    for attr, name in simple.items():
        v = getattr(args, attr, None)
        if v is not None:
            params[name] = str(Path(v).expanduser().resolve()) if attr in ("model", "classes", "denoiser", "dense_cloud") else v
    params.update(working_volume_params(getattr(args, "working_volume", None), getattr(args, "window", None)))
    if getattr(args, "background", None) is not None:
        params["background"] = args.background
    if params.get("method") == "pws" and getattr(args, "imaging", None) is None:
        params["imaging"] = "paper"  # the entire scene cloud has no depth pixels to make surfels of
    return override_config(cfg, params)


def video_options(args: argparse.Namespace) -> dict[str, Any]:
    """``video`` and ``video_fps`` of ReplayOptions from ``--video`` / ``--video-fps``."""
    require(args.video_fps is None or args.video, "--video-fps needs --video PATH")
    out: dict[str, Any] = {"video": Path(args.video).expanduser()} if args.video else {}
    if args.video_fps is not None:
        out["video_fps"] = args.video_fps
    return out


def options_from_args(args: argparse.Namespace):
    from ..replay import ReplayOptions

    cfg = build_config(args)
    topics = input_topics(args)
    require(args.max_frames is None or args.max_frames >= 1, f"--max-frames must be >= 1, got {args.max_frames}")
    interval = progress_interval(args)
    if args.report:   # checked before the frames, so that a long run's report is not lost at its end
        report = Path(args.report)
        require(not report.exists() or report.is_dir(), f"--report {report}: it exists and is not a folder")
        require_creatable(report, "--report")
    return ReplayOptions(
        bag=Path(args.bag), config=cfg, out=Path(args.out) if args.out else None, overwrite=args.overwrite,
        write_output=not args.no_output, topics=topics,
        max_frames=args.max_frames,
        realtime=args.realtime, copy_inputs=args.copy_inputs, write_cloud=args.write_cloud, preview=args.preview,
        markers=not args.no_markers, poses=not args.no_poses, namespace=args.namespace, compress=not args.no_compression,
        report_dir=Path(args.report) if args.report else None, quiet=args.quiet, **interval, **video_options(args))


def run(args: argparse.Namespace) -> int:
    from ..replay import replay

    try:
        opts = options_from_args(args)
        require(args.ray_address is None or args.workers is not None, "--ray-address needs --workers N")
        if args.workers is not None:
            from ..replay.distributed import replay_ray

            result = replay_ray(opts, args.workers, args.ray_address)
        else:
            result = replay(opts)
    except PwsError as exc:
        print(f"pws replay: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result.summary, indent=2))
    else:
        print(result.table())
        if result.report_files:
            print(f"report: {', '.join(str(p) for p in result.report_files)}")
        video = result.summary.get("video") or {}
        if video.get("path"):
            print(f"video: {video['path']} ({video['frames']} frames)")
    if result.exit_code != 0 and result.message:
        kind = "interrupted" if result.summary.get("interrupted") else "error"
        print(f"pws replay: {kind}: {result.message}", file=sys.stderr)
    return result.exit_code


__all__ = ["build_config", "options_from_args", "parse_radius", "register", "run"]
