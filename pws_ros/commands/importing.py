"""``pws import``: RGB-D frames, TUM sequences and labels in, as recordings ``pws replay`` and ``pws finetune`` read."""
from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

from ..core.errors import require
from .common import add_command_group, add_output_args, positive_float

DESCRIPTION = """\
Bring your own RGB-D data in: write it as a rosbag2 (MCAP) recording with the topics `pws replay`,
`pws finetune`, `pws ceiling` and the nodes read by default (config/pws.yaml):
/camera/color/image_raw (rgb8), /camera/aligned_depth_to_color/image_raw (16UC1 millimetres,
0 = no depth), /camera/color/camera_info, and the labels on /pws/ground_truth (docs/import.md).
The recording appears only when complete: on an error or Ctrl-C nothing is left at OUT."""

FRAMES_DESCRIPTION = """\
A folder of RGB-D clips with a label per frame -> a recording.

Every folder under FOLDER holding a colour sub-folder (rgb/, --color-dir) is a clip, named by its
path under FOLDER (e.g. G01_call/clip04). Its colour images (.png, .jpg) are its frames, in file-name
order; each pairs with the depth file of the same stem in depth_raw/ or depth/ (--depth-dir): a .npy
array or a 16-bit PNG / TIFF, registered to the colour image (same size, same pixels).

Labels: from the clip's name by --label-regex (default: the first folder, the layout
LABEL/CLIP/rgb/...), or from --labels CSV (rows file,label: a colour image or a folder above it,
relative to FOLDER). Each frame's label and clip go on /pws/ground_truth (class_name, clip,
clip_index, frame_index, file; with --classes also label, the class index), for pws replay --report
and pws finetune. Clips are laid end to end in time: frames 1/--rate apart, --gap seconds between clips.

Depth in metres = stored value x depth scale: --depth-scale, else depth_metadata.json
({"depth_scale": 0.001}) in the clip folder or in FOLDER. Intrinsics of the colour camera:
--intrinsics fx,fy,cx,cy or --camera-info CAM.yaml (a ROS camera_info YAML, which fixes the size too).

Refused with the file named, before OUT exists: a frame without a label or without a depth file,
colour and depth of different sizes, an unreadable image, a depth scale of 0 or below, a label
outside --classes."""

FRAMES_EPILOG = """\
examples:
  # the hand-gesture data (G01_call/clip04/rgb/frame_008.png ...): label 'call', clip 'G01_call/clip04';
  # no intrinsics come with it: a RealSense D435 colour camera at 640x480 is assumed (fx = fy = 615, cx 320, cy 240)
  pws import frames gestures/dataset/25081046_Zhang --out gestures.bag --intrinsics 615,615,320,240 \\
      --label-regex '^G[0-9]+_(?P<label>[^/]+)/'
  pws import frames gestures/dataset/25081046_Zhang --out clip04_f8.bag --intrinsics 615,615,320,240 \\
      --label-regex '^G[0-9]+_(?P<label>[^/]+)/' --clips '*/clip04' --frames 8     # frame 8 of each clip04: 10 frames
  pws import frames my_data --out my.bag --camera-info camera.yaml --labels labels.csv --depth-scale 0.001
then: pws replay gestures.bag --model my_net.pt --report /tmp/r   (the report scores each frame against its label)"""

LABELS_DESCRIPTION = """\
Labels for a recording made without them (e.g. with `ros2 bag record`, labelled later): a copy of
BAG at OUT with /pws/ground_truth added, from a CSV of stamps:
  stamp,label          the frame nearest to the stamp (within --tolerance) gets the label
  start,end,label      every frame from start to end (both included) gets the label
Stamps are the frames' header stamps in seconds (a header row may name them stamp_ns, start_ns,
end_ns for nanoseconds, e.g. the stamp_ns of pws replay's frames.csv; and a column clip), or with
--relative seconds since the first frame. Frames no row covers keep no label. Refused with the CSV
line: a row that labels no frame, two rows giving one frame different labels, a label outside --classes."""

LABELS_EPILOG = """\
example:
  printf 'start,end,label\\n0,4.5,cup\\n5,9.9,bottle\\n' > labels.csv
  pws import labels my_recording --csv labels.csv --relative --out my_recording_labelled"""

TUM_EPILOG = """\
A TUM RGB-D benchmark folder: rgb/ and depth/ PNGs (depth in 1/5000 m) and associations.txt, or
rgb.txt + depth.txt (each colour image takes the depth image nearest in time); stamped with the
colour times, no labels. Intrinsics: --calibration tum1/tum2/tum3 (freiburg1/2/3) or the TUM
default 525/525/319.5/239.5.
example:
  pws import tum rgbd_dataset_freiburg1_desk --out desk.bag --calibration tum1"""


def register(subparsers) -> None:
    sub = add_command_group(subparsers, "import", "RGB-D frames, TUM sequences, labels -> recordings pws replay / finetune read",
                            DESCRIPTION, ("frames", "labels", "tum"))
    f = sub.add_parser("frames", help="a folder of labelled RGB-D clips -> a recording (labels on /pws/ground_truth)",
                       description=FRAMES_DESCRIPTION, epilog=FRAMES_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    f.add_argument("folder", type=Path, help="the folder of clips")
    f.add_argument("--out", type=Path, required=True, help="the recording to write (a rosbag2 directory; must not exist)")
    cam = f.add_mutually_exclusive_group(required=True)
    cam.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="the colour camera's pinhole intrinsics in pixels, e.g. 615,615,320,240")
    cam.add_argument("--camera-info", type=Path, metavar="CAM.yaml", help="a ROS camera_info YAML (camera_calibration's format)")
    f.add_argument("--depth-scale", type=float, default=None, metavar="M",
                   help="metres per stored depth unit (0.001: millimetres; TUM PNGs 0.0002); default: depth_metadata.json")
    f.add_argument("--color-dir", default="rgb", help="the colour sub-folder of a clip (default rgb)")
    f.add_argument("--depth-dir", default="depth_raw,depth", help="the depth sub-folder(s), the first a clip has (default depth_raw,depth)")
    lab = f.add_mutually_exclusive_group()
    lab.add_argument("--label-regex", default=None, metavar="REGEX",
                     help="the label from the clip's path under FOLDER: the group 'label', else the first group, else the match; "
                          "frames of clips it does not match have no label (refused) (default '^(?P<label>[^/]+)': the first folder)")
    lab.add_argument("--labels", type=Path, default=None, metavar="CSV", help="rows file,label (a colour image or a folder above it)")
    f.add_argument("--classes", default=None, metavar="FILE",
                   help="the model's classes (a class file, or a model file with one beside it): a label outside them is "
                        "refused, and each frame also gets its class index; leave out when training a new head")
    f.add_argument("--frames", default=None, metavar="LIST",
                   help="import only the frames whose file-name number is listed, e.g. 8 or 1-5,9 (frame_008.png is 8)")
    f.add_argument("--clips", default=None, metavar="GLOB", help="import only the clips whose name matches, e.g. '*/clip04'")
    f.add_argument("--rate", type=positive_float, default=30.0, help="frames per second within a clip (default 30)")
    f.add_argument("--gap", type=float, default=1.0, help="seconds between the last frame of a clip and the next clip (default 1)")
    f.add_argument("--start", type=float, default=None, metavar="S", help="stamp of the first frame in seconds (default 1700000000)")
    f.add_argument("--overwrite", action="store_true", help="replace OUT if it is a bag")
    add_output_args(f, "print what was written as JSON", "no progress")
    f.set_defaults(func=run)

    la = sub.add_parser("labels", help="attach labels from a CSV of stamps to a recording (a labelled copy)",
                        description=LABELS_DESCRIPTION, epilog=LABELS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    la.add_argument("bag", type=Path, help="the recording (rosbag2 directory, or a bare .mcap / .db3)")
    la.add_argument("--csv", type=Path, required=True, help="stamp,label or start,end,label rows")
    la.add_argument("--out", type=Path, required=True, help="the labelled copy to write (must not exist)")
    la.add_argument("--relative", action="store_true", help="stamps are seconds since the first frame")
    la.add_argument("--tolerance", type=float, default=0.02, metavar="S",
                    help="a stamp row labels the nearest frame within S seconds (default 0.02)")
    la.add_argument("--replace", action="store_true", help="drop the recording's ground truth (else a recording that has some is refused)")
    la.add_argument("--classes", default=None, metavar="FILE", help="as in `pws import frames`")
    la.add_argument("--color-topic", default=None, help="the frames' topic (default: the colour image pws replay would read)")
    la.add_argument("--overwrite", action="store_true", help="replace OUT if it is a bag")
    add_output_args(la, "print what was written as JSON", "no progress")
    la.set_defaults(func=run)

    t = sub.add_parser("tum", help="a TUM-format RGB-D sequence -> a recording", epilog=TUM_EPILOG,
                       description="pws import tum: a TUM-format RGB-D sequence (the TUM RGB-D benchmark's folders: rgb/,\n"
                                   "depth/ and their lists) -> a recording pws replay and pws finetune read",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    t.add_argument("src", type=Path, help="TUM-format folder (rgb/, depth/, associations.txt or rgb.txt + depth.txt)")
    t.add_argument("--out", type=Path, required=True, help="the recording to write (must not exist)")
    t.add_argument("--max-frames", type=int, default=None, metavar="N", help="the first N pairs only")
    t.add_argument("--calibration", choices=("default", "tum1", "tum2", "tum3"), default="default",
                   help="intrinsics: TUM freiburg1/2/3 or the TUM default 525/525/319.5/239.5 (default)")
    t.add_argument("--overwrite", action="store_true", help="replace OUT if it is a bag")
    add_output_args(t, "print what was written as JSON", "no progress")
    t.set_defaults(func=run)


def _classes(spec: str | None) -> tuple[list[str] | None, str]:
    if spec is None:
        return None, ""
    from ..importing.folder import load_classes

    return load_classes(spec)


def run(args: argparse.Namespace) -> int:
    from ..replay.progress_log import Progress

    t0 = time.perf_counter()
    cmd = args.import_command
    bar = lambda n: Progress(n, label=f"pws import {cmd}", mode="off" if args.quiet else None)  # noqa: E731
    if cmd == "frames":
        summary = _frames(args, bar)
    elif cmd == "labels":
        from ..importing import attach_labels

        classes, source = _classes(args.classes)
        with bar(None) as progress:
            summary = attach_labels(args.bag, args.csv, args.out, classes=classes, classes_source=source, relative=args.relative,
                                    tolerance_s=args.tolerance, replace=args.replace,
                                    topics={"color": args.color_topic} if args.color_topic else None,
                                    overwrite=args.overwrite, progress=progress)
    else:
        from ..importing.tum import convert, pairs

        require(args.max_frames is None or args.max_frames >= 1, f"--max-frames must be >= 1, got {args.max_frames}")
        n = min(len(pairs(args.src)), args.max_frames or 10**12)
        with bar(n) as progress:
            n = convert(args.src, args.out, frames=args.max_frames, calibration=args.calibration, overwrite=args.overwrite,
                        progress=progress)
        summary = {"out": str(args.out), "frames": n}
    summary["seconds"] = round(time.perf_counter() - t0, 2)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_describe(summary))
    return 0


def _frames(args: argparse.Namespace, bar) -> dict:
    from ..importing import FolderLayout, Pinhole, plan_frames, write_frames
    from ..importing.folder import DEFAULT_LABEL_REGEX, START_S, parse_frame_numbers

    pinhole = Pinhole.from_yaml(args.camera_info) if args.camera_info else Pinhole.parse(args.intrinsics)
    classes, source = _classes(args.classes)
    layout = FolderLayout(color_dir=args.color_dir, depth_dirs=tuple(d for d in args.depth_dir.split(",") if d),
                          label_regex=args.label_regex or DEFAULT_LABEL_REGEX, labels_csv=args.labels, classes=classes,
                          classes_source=source, depth_scale=args.depth_scale,
                          frames=parse_frame_numbers(args.frames) if args.frames else None, clips=args.clips,
                          rate_hz=args.rate, gap_s=args.gap, start_s=START_S if args.start is None else args.start)
    frames = plan_frames(args.folder, layout)
    with bar(len(frames)) as progress:
        summary = write_frames(frames, args.out, pinhole, overwrite=args.overwrite, progress=progress)
    summary["clips"] = len({f.truth["clip"] for f in frames})
    summary["depth_scale"] = sorted({f.depth_scale for f in frames})
    return summary


def _describe(s: dict) -> str:
    head = f"wrote {s['out']}: {s['frames']} frame(s)"
    if "clips" in s:
        head += f" from {s['clips']} clip(s) ({', '.join(s['sizes'])}), depth scale {', '.join(f'{v:g}' for v in s['depth_scale'])} m/unit"
    if "labelled" in s:
        head += f", {s['labelled']} labelled from {s['rows']} row(s)"
        if s["replaced"]:
            head += f" (the old ground truth on {', '.join(s['replaced'])} dropped)"
    lines = [head]
    labels = Counter(s.get("labels", {}))
    if labels:
        lines.append("labels on /pws/ground_truth: " + ", ".join(f"{k} {v}" for k, v in sorted(labels.items())))
    if "intrinsics" in s:
        lines.append(f"intrinsics: {s['intrinsics']}; {s['bytes'] / 1e6:.1f} MB")
    if s.get("left_out"):
        lines.append(f"left out (cannot be decoded): {', '.join(s['left_out'])}")
    lines.append(f"{s['seconds']:g} s")
    return "\n".join(lines)
