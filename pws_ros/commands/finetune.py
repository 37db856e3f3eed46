"""``pws finetune``: make a model file robust to Gaussian noise of a chosen sigma on your own
recordings, without labels (the library: :mod:`pws_ros.finetune`)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .common import add_output_args, add_volume_config_args, working_volume_params
from . import SUMMARIES

DESCRIPTION = """\
Randomized smoothing certifies a classifier that keeps its answer under Gaussian noise of the sigma
it is smoothed with; one trained without that noise mostly abstains. This command tunes a model file
(the contract of `pws export-model`) for a chosen --sigma on your own recordings, without labels:

  teacher  the original model on the clean frames;
  student  learns to give the teacher's answer on noisy copies of the frames (KL to the teacher's
           probabilities, --targets soft, or cross-entropy to its top class, --targets hard); where
           the recording has ground truth (/pws/ground_truth, or --truth-topic) its label is the
           target instead (--no-truth: never).

The frames are exactly what the certifier feeds the classifier: the reduced alpha = 0 frame of the
imaging model (surfel: centred crop, --render-factor, border from the radii) and --views renders of
the same one-frame cloud at random camera motions within the configured radii (--axes, --radius),
read from the recordings as `pws replay` reads them (MCAP / sqlite3, depth + colour + CameraInfo or
an organized PointCloud2; topics found by type unless given).

--mode classifier (default; measured better on the demo recording, see docs/finetune.md) fine-tunes
the model itself. --mode denoiser trains a small residual denoiser placed before the frozen classifier
(KL + --mse-weight x MSE to the clean frame) and writes both the combined model (OUT) and the
denoiser alone (OUT stem + .denoiser.pt, for `pws replay --model ORIGINAL --denoiser ...`).

Labelled recordings (`pws import frames`): --backbone efficientnet_lite0 or small_cnn (or --model M
--new-head) builds a new head for the label set of the recordings' ground truth and trains it on noisy copies,
cross-entropy to each frame's label (--consistency W adds the consistency regulariser, --clean-share
and --augment keep the base classifier good on clean frames and other clips); every frame
needs a label. --holdout-clips holds whole clips out (frames of a clip are near duplicates). With
the ground truth used, a label outside the model's classes is an error naming the frame.

Held out: the last --holdout of each recording by time is never trained on; the report measures on
those frames, before and after, how often the smoothed prediction (--eval-samples noisy copies at
sigma) agrees with the teacher's clean prediction, and the p_A distribution.

Output: OUT (TorchScript model file with pws.json recording sigma and what it was tuned on, and
OUT stem + .classes.txt), ready for `pws replay --model OUT --sigma SIGMA` and the nodes' model_path;
OUT stem + .finetune.json, the report.

Long runs: a progress bar on a terminal, else a plain line every --progress-interval seconds. The
frames are cached on disk (the work folder, OUT + .work; one frame in memory at a time, uint8) and
the training checkpoint is written atomically every --checkpoint-every seconds, at every epoch end
and on Ctrl-C (SIGINT) or SIGTERM: rerun the same command with --resume to continue; the same seed
gives the same weights as an uninterrupted run. The work folder is removed after a finished run
unless --keep-work."""

EPILOG = """\
examples:
  pws finetune gestures --backbone efficientnet_lite0 --input-size 120x160 --holdout-clips clip04 --sigma 0.25 \\
      --working-volume 1.5 --out gestures.pt        # labelled clips: a new head, supervised, held out by clip
  pws finetune bags/demo --model bags/models/classifier_sigma0.25.pt --sigma 1.0 --out /tmp/tuned.pt --holdout 0.5
  pws replay bags/demo --model /tmp/tuned.pt --sigma 1.0 --out /tmp/tuned_replay --overwrite
  pws finetune run1.mcap run2.mcap --model models/my_net.pt --sigma 0.25 --out models/my_net_s025.pt \\
      --stride 5 --epochs 3 --device cuda
  pws finetune run1.mcap --model models/my_net.pt --sigma 0.25 --out models/my_net_s025.pt --resume   # after Ctrl-C

exit status: 0 done; 2 bad input (a model file that does not load, sigma <= 0, a recording with no
camera input, too few frames to hold any out, ...), one line naming the problem; 130 / 143 stopped by
SIGINT / SIGTERM (the work folder keeps the cache and the checkpoint: --resume)."""


def register(subparsers) -> None:
    from ..finetune.options import DEFAULT_MODE, MODES, TARGETS

    p = subparsers.add_parser("finetune", help=SUMMARIES["finetune"],
                              description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+", metavar="RECORDING", help="rosbag2 recordings (bag directories or bare .mcap / .db3 files)")
    p.add_argument("--model", default=None, help="the model file to tune (TorchScript, the contract of `pws export-model`)")
    p.add_argument("--out", required=True, metavar="OUT.pt", help="the tuned model file to write")
    p.add_argument("--sigma", type=float, default=None, help="the noise sigma to tune for (images in [0, 1]; default: config sigma, 0.5)")
    p.add_argument("--classes", default=None, help="class-names file (default: beside the model)")

    h = p.add_argument_group("labels: a new head, held out by clip")
    h.add_argument("--backbone", default=None, choices=("efficientnet_lite0", "small_cnn"),
                   help="instead of --model: efficientnet_lite0 (ImageNet weights, the .[efficientnet] extra) with a new head "
                        "for the recordings' label set, or small_cnn (a small grey-level CNN trained from scratch, for small "
                        "inputs such as an 80x60 camera window; docs/real_task.md)")
    h.add_argument("--new-head", action="store_true", help="with --model: a new linear head for the recordings' label set on its outputs")
    h.add_argument("--input-size", default=None, metavar="HxW", help="new head: its input size, e.g. 120x160 (default: the model's, else 120x160)")
    h.add_argument("--holdout-clips", default=None, metavar="GLOBS",
                   help="hold these clips out whole (comma-separated globs on the ground truth's clip, e.g. clip04 or "
                        "'G0*/clip04'); replaces --holdout")
    h.add_argument("--consistency", type=float, default=0.0, metavar="W",
                   help="consistency regularisation: two noisy copies per image, + W x KL of each to their mean (default 0: off)")
    h.add_argument("--clean-share", type=float, default=0.0, metavar="F",
                   help="this share of each batch is trained without noise, so the base classifier is good on clean images "
                        "too (default 0: every image noisy)")
    h.add_argument("--augment", action="store_true",
                   help="random colour gains (x0.6-1.4 per channel, x0.8-1.2 overall) on the drawn pixels (not the "
                        "background), shifts of up to 12 input pixels and scales of x0.6-1.4 about the centre, per image")

    t = p.add_argument_group("training")
    t.add_argument("--mode", choices=MODES, default=DEFAULT_MODE,
                   help=f"classifier: fine-tune the model; denoiser: train a denoiser before the frozen model (default {DEFAULT_MODE})")
    t.add_argument("--targets", choices=TARGETS, default="soft", help="the teacher's probabilities (soft, KL) or top class (hard); default soft")
    t.add_argument("--no-truth", action="store_true", help="ignore ground-truth labels in the recordings (always the teacher)")
    t.add_argument("--holdout", type=float, default=0.2, help="the last part of each recording, by time, held out (default 0.2)")
    t.add_argument("--views", type=int, default=4, help="renders at random motions within the radii per frame, besides alpha = 0 (default 4)")
    t.add_argument("--stride", type=int, default=1, help="use every K-th input frame (consecutive frames are near duplicates; default 1)")
    t.add_argument("--max-frames", type=int, default=None, metavar="K", help="at most K frames per recording (after --stride)")
    t.add_argument("--epochs", type=int, default=5, help="passes over the training images (default 5)")
    t.add_argument("--noise-warmup", type=int, default=0, metavar="E", help="the noise rises linearly from 0 to sigma over E epochs (default 0)")
    t.add_argument("--batch-size", type=int, default=32, help="images per training step and per evaluation call (default 32)")
    t.add_argument("--lr", type=float, default=None, help="AdamW learning rate, warm-up then cosine decay (default 5e-5 classifier, 1e-4 denoiser or new head)")
    t.add_argument("--weight-decay", type=float, default=0.0, help="AdamW weight decay (default 0)")
    t.add_argument("--mse-weight", type=float, default=1.0, help="denoiser: weight of the MSE to the clean frame (default 1)")
    t.add_argument("--denoiser-channels", type=int, default=32, help="denoiser: channels (default 32)")
    t.add_argument("--denoiser-depth", type=int, default=5, help="denoiser: convolution layers (default 5)")
    t.add_argument("--init-denoiser", default=None, metavar="DEN.pt", help="denoiser: start from this TorchScript denoiser")
    t.add_argument("--eval-samples", type=int, default=100, metavar="N", help="noise samples per held-out frame in the report (default 100)")
    t.add_argument("--seed", type=int, default=0, help="seed of the motions, batches and noise (default 0)")
    t.add_argument("--device", default="cpu", help="cpu or cuda[:N] (default cpu; an unavailable GPU is an error)")

    r = p.add_argument_group("run")
    r.add_argument("--work-dir", default=None, help="frame cache and checkpoint folder (default OUT + .work)")
    r.add_argument("--resume", action="store_true", help="continue an interrupted run from its work folder (same command)")
    r.add_argument("--overwrite", action="store_true", help="replace OUT and start over in an existing work folder")
    r.add_argument("--keep-work", action="store_true", help="keep the work folder (frame cache, checkpoint) after a finished run")
    r.add_argument("--checkpoint-every", type=float, default=60.0, metavar="S", help="seconds between checkpoints (default 60; 0 = epoch ends only)")
    add_output_args(r, "print the report as JSON on stdout instead of the summary", "no progress and no info lines")
    r.add_argument("--progress-interval", type=float, default=None, metavar="S",
                   help="when stderr is not a terminal: one progress line every S seconds (default 30; 0 = every step)")

    c = p.add_argument_group("frames (override the config, as in `pws replay`)")
    c.add_argument("--config", default=None, help="ROS 2 parameter file (default: config/pws.yaml if found, else built-in defaults)")
    c.add_argument("--axes", default=None, help="motion axes of the views, e.g. tz,ry (default: config axes)")
    c.add_argument("--radius", default=None, help="motion radius per axis, e.g. tz=0.01,ry=0.25deg (default: config radius.<axis>)")
    c.add_argument("--imaging", default=None, choices=("surfel", "paper"), help="imaging model (default: config imaging, surfel)")
    c.add_argument("--render-factor", type=int, default=None, metavar="K", help="surfel imaging: render at K times the model's input (default: config, 2)")
    c.add_argument("--border", type=int, default=None, help="surfel imaging: masked border in output pixels (-1 = from the radii)")
    add_volume_config_args(c)

    i = p.add_argument_group("input (as in `pws replay`)")
    i.add_argument("--cloud-topic", default=None, help="organized PointCloud2 topic")
    i.add_argument("--depth-topic", default=None, help="depth Image topic registered to the colour camera")
    i.add_argument("--color-topic", default=None, help="colour Image topic")
    i.add_argument("--info-topic", default=None, help="CameraInfo of the colour camera")
    i.add_argument("--depth-info-topic", default=None, help="CameraInfo of the depth stream (\"\" = none)")
    i.add_argument("--truth-topic", default=None, help="ground-truth DiagnosticArray topic (default: /pws/ground_truth when present)")
    i.add_argument("--sync-tolerance", type=float, default=None, help="depth/colour pairing tolerance, s (default: config)")
    i.add_argument("--sync-max-skew", type=float, default=None, help="unsynchronised drivers: largest pairing skew, s (default: config)")
    p.set_defaults(func=run)


def options_from_args(args: argparse.Namespace):
    from ..finetune import FinetuneOptions
    from ..replay.options import load_replay_config, override_config
    from .replay import axes_radius_params, input_topics, progress_interval

    cfg = load_replay_config(args.config)
    params = axes_radius_params(args, cfg)
    for attr, name in (("imaging", "imaging"), ("render_factor", "render_factor"), ("border", "border"),
                       ("sync_tolerance", "sync_tolerance_s"), ("sync_max_skew", "sync_max_skew_s"), ("background", "background")):
        v = getattr(args, attr)
        if v is not None:
            params[name] = v
    params.update(working_volume_params(args.working_volume, args.window))
    cfg = override_config(cfg, params)
    topics = input_topics(args)
    interval = progress_interval(args)
    from ..finetune.heads import parse_input_size

    clips = [c.strip() for c in args.holdout_clips.split(",") if c.strip()] if args.holdout_clips is not None else None
    return FinetuneOptions(
        bags=[Path(b) for b in args.bags], model=Path(args.model) if args.model else None, out=Path(args.out),
        backbone=args.backbone, new_head=args.new_head, holdout_clips=clips, consistency=args.consistency, noise_warmup=args.noise_warmup,
        clean_share=args.clean_share, augment=args.augment,
        input_size=parse_input_size(args.input_size) if args.input_size else None, config=cfg, sigma=args.sigma,
        mode=args.mode, targets=args.targets, use_truth=not args.no_truth, holdout=args.holdout, views=args.views,
        stride=args.stride, max_frames=args.max_frames, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
        weight_decay=args.weight_decay, mse_weight=args.mse_weight, denoiser_channels=args.denoiser_channels,
        denoiser_depth=args.denoiser_depth, init_denoiser=Path(args.init_denoiser) if args.init_denoiser else None,
        eval_samples=args.eval_samples, seed=args.seed, device=args.device,
        topics=topics,
        classes=Path(args.classes) if args.classes else None, work_dir=Path(args.work_dir) if args.work_dir else None,
        resume=args.resume, overwrite=args.overwrite, checkpoint_every_s=args.checkpoint_every, keep_work=args.keep_work,
        quiet=args.quiet, **interval)


def run(args: argparse.Namespace) -> int:
    from ..core.jsonable import jsonable
    from ..finetune import finetune, summary_lines

    result = finetune(options_from_args(args))
    if result.interrupted:
        print(f"pws finetune: {result.message}", file=sys.stderr)
        return result.exit_code
    if args.json:
        print(json.dumps(jsonable(result.report), indent=1))
    else:
        print("\n".join(summary_lines(result)))
    return result.exit_code


__all__ = ["options_from_args", "register", "run"]
