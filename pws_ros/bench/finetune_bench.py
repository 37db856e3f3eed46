"""Benchmark of ``pws finetune`` on a public RGB-D sequence (issue 23): a classifier not trained with
noise (default: EfficientNet-Lite0 with its ImageNet weights, the optional extra ``.[efficientnet]``)
tuned at each sigma on the frames of a TUM-format sequence, evaluated on the held-out end of that
sequence and on other recordings (e.g. the Kinect and RealSense recordings), printed side by side:
agreement of the smoothed prediction with the original model's clean prediction (and on the frames where
that prediction is stable, the agreement's ceiling: :func:`pws_ros.finetune.evaluate.teacher_stability`), the p_A median,
the training time and the peak memory; then, per evaluated frame (``--certify-heldout K`` frames of
the held-out end, every frame of the ``--eval`` recordings) and axis, the tuned model's certified
radius next to the ceiling (the radius of a classifier that never changes its answer,
:mod:`pws_ros.replay.ceiling`, the code of ``pws ceiling``) and the median of their ratio.

    python -m pws_ros.bench.finetune_bench SRC --work DIR [--sigmas 0.25,0.5] [--frames 300] \\
        [--eval BAG ...] [--certify-heldout 3] [--model lite0|MODEL.pt] [--device cpu|cuda] [--resume] [--json]

``SRC``: a TUM-format folder (converted with :mod:`pws_ros.importing.tum`, the code of ``pws import tum``, into ``DIR/sequence``)
or a rosbag2 recording. The data stays outside the repository (fetch a sequence from the TUM RGB-D
benchmark yourself, e.g. freiburg1_desk). Everything is written under ``DIR``: the exported original
model, one tuned model and report per sigma, ``bench.json``.

``DIR/bench.json`` is written after every stage (tuning, evaluation, each certified recording);
``--resume`` keeps what it holds and runs the rest: a tuned model is reused only when the settings
recorded in it (sigma, epochs, views, hold-out, stride, seed, render factor, the sequence, the
original model's SHA-256) and its report's noise samples match this command.
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..core.errors import PwsError, require


def export_lite0(path: Path) -> Path:
    """EfficientNet-Lite0 with its ImageNet weights as a model file (the README's example)."""
    from ..core.model import IMAGENET_MEAN, IMAGENET_STD, export_model
    from ..finetune.heads import efficientnet_lite0

    net = efficientnet_lite0()
    return export_model(net.eval(), path, (224, 224), [f"imagenet_{i}" for i in range(1000)], mean=IMAGENET_MEAN, std=IMAGENET_STD)


def sequence_bag(src: Path, work: Path, frames: int | None) -> Path:
    """``src`` itself when it is a recording, else its conversion into ``work/sequence``."""
    src = Path(src)
    require(src.exists(), f"sequence not found: {src}")
    if src.is_file() or (src / "metadata.yaml").exists() or any(src.glob("*.mcap")) or any(src.glob("*.db3")):
        return src
    from ..importing.tum import convert

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
    from ..finetune.evaluate import smoothed_counts, stability_summary, summarize, teacher_stability
    from ..replay.interrupt import StopSignals

    device = resolve_device(opts.device)
    teacher = load_model(original, device=device)
    eopts = replace(opts, views=0, max_frames=None)
    engine = FrameCertifier(replace(eopts.config, sigma=sigma, device=str(device), batch_size=opts.batch_size), model=teacher, load=False,
                            log=lambda _l, _m: None)
    import hashlib

    folder = work / ("eval_" + hashlib.sha256(str(Path(bag).resolve()).encode()).hexdigest()[:12])
    folder.mkdir(parents=True, exist_ok=True)
    with StopSignals() as stop:
        cache = FramePreparer(eopts, teacher, engine, folder, device=device, stop=stop, warn=log, info=lambda _m: None).prepare(0, Path(bag))
    items = [(0, k) for k in range(cache.count)]
    top = np.asarray([f["teacher"] for f in cache.frames])
    truth = np.asarray([f["truth_label"] for f in cache.frames])
    stab = teacher_stability(teacher, [cache], items, top, seed=opts.seed, device=device)
    out: dict[str, Any] = {"teacher_stability": stability_summary(stab)}
    for name, path in {"original": original, **tuned}.items():
        m = teacher if name == "original" else load_model(path, device=device)
        counts = smoothed_counts(m, [cache], items, sigma=sigma, n=opts.eval_samples, seed=opts.seed, batch_size=opts.batch_size,
                                 device=device, num_classes=teacher.num_classes)
        out[name] = summarize(counts, top, truth, sigma=sigma, stable=stab["stable"])
    return out


def pick_evenly(items: list[Any], k: int) -> list[Any]:
    """``k`` items spread evenly over ``items`` (first and last included; all of them when k >= len)."""
    if k <= 0 or not items:
        return []
    if k >= len(items):
        return list(items)
    if k == 1:
        return [items[len(items) // 2]]
    return [items[round(i * (len(items) - 1) / (k - 1))] for i in range(k)]


def frames_bag(bag: Path, stamps: list[int], out: Path, tolerance_ns: int = 15_000_000) -> Path:
    """A copy of ``bag`` holding only the messages logged within ``tolerance_ns`` of one of ``stamps``
    (the frames to certify: ``pws replay`` then certifies exactly those)."""
    from ..bagio import BagWriter, prepare_output
    from ..bagio.reader import BagReader

    keep = sorted(int(s) for s in stamps)
    require(bool(keep), "no frame to certify")
    prepare_output(out, True)
    n = 0
    with BagReader(bag) as reader:
        writer = BagWriter(out, typestore=reader.typestore).open()
        try:
            for m in reader.messages():
                if min(abs(m.log_time_ns - s) for s in keep) <= tolerance_ns:
                    writer.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, reader.typestore_for(m.msgtype))
                    n += 1
        finally:
            writer.close()
    require(n > 0, f"{bag}: no message near the frames to certify")
    return out


def certify_recording(bag: Path, tuned: Path, cfg: Any, sigma: float, *, batch_size: int, device: str,
                      log: Callable[[str], None], max_frames: int | None = None) -> list[dict[str, Any]]:
    """Per frame of ``bag`` and axis of ``cfg``: the ceiling (a never-changing classifier) and the tuned
    model's certified radius, by :func:`pws_ros.replay.ceiling.ceiling` (the code of ``pws ceiling``)."""
    from ..core.model import load_model
    from ..replay import ReplayOptions
    from ..replay.ceiling import ceiling

    ccfg = replace(cfg, sigma=sigma, batch_size=batch_size, device=device, model_path=str(tuned))
    opts = ReplayOptions(bag=Path(bag), config=ccfg, write_output=False, max_frames=max_frames, quiet=True, progress=False,
                         log=lambda level, msg: log(f"[{level}] {msg}") if level in ("warn", "error") else None)
    t0 = time.perf_counter()
    rows, _top, _got = ceiling(opts, load_model(tuned, device=device))
    out = []
    for r in rows:
        d = r.to_dict()
        d["ratio"] = (r.model / r.ceiling) if r.ceiling > 0 and math.isfinite(r.model) else None
        out.append(d)
    log(f"certified {bag} at sigma {sigma:g}: {len(rows)} frame-axis rows in {time.perf_counter() - t0:.0f} s")
    return out


def certified_medians(entry: dict[str, Any]) -> dict[str, Any]:
    """Per axis, over every certified frame of a sigma: the median of radius / ceiling and the medians
    of both as a share of the requested radius."""
    rows = [r for rs in entry.get("certified", {}).values() for r in rs]
    out = {}
    for axis in dict.fromkeys(r["axis"] for r in rows):
        sel = [r for r in rows if r["axis"] == axis]
        ratios = [r["ratio"] for r in sel if r["ratio"] is not None]
        out[axis] = {"frames": len(sel), "ratio_median": float(np.median(ratios)) if ratios else None,
                     "ceiling_share_median": float(np.median([r["ceiling_share"] or 0.0 for r in sel])),
                     "model_share_median": float(np.median([r["model_share"] or 0.0 for r in sel]))}
    return out


SETTINGS = ("sigma", "epochs", "views_per_frame", "holdout", "stride", "seed", "render_factor")


def reusable(entry: dict[str, Any] | None, out: Path, want: dict[str, Any], eval_samples: int, original: Path, bag: Path) -> bool:
    """Whether a tuned model of an earlier run (``--resume``) was made with the settings ``want`` from
    ``original`` on ``bag``."""
    if not entry or not out.is_file() or "heldout" not in entry:
        return False
    import hashlib

    from ..core.model import load_model

    try:
        meta = load_model(out).meta.get("finetune") or {}
        rep = json.loads(out.with_name(out.stem + ".finetune.json").read_text())
        sha = hashlib.sha256(original.read_bytes()).hexdigest()
    except (PwsError, OSError, ValueError):
        return False
    recs = meta.get("recordings") or [{}]
    return (all(meta.get(k) == want[k] for k in want) and rep.get("eval_samples") == eval_samples
            and meta.get("from_sha256") == sha and [Path(str(r.get("bag"))).resolve() for r in recs] == [Path(bag).resolve()])


def run_bench(src: Path, work: Path, *, model: str = "lite0", sigmas: tuple[float, ...] = (0.25, 0.5), frames: int | None = 300,
              eval_bags: tuple[Path, ...] = (), epochs: int = 3, views: int = 2, stride: int = 1, holdout: float = 0.2,
              eval_samples: int = 1000, batch_size: int = 32, render_factor: int = 1, device: str = "cpu", seed: int = 0,
              config: Path | None = None, border: int | None = None, certify_heldout: int = 3, certify: bool = True,
              cert_params: dict[str, Any] | None = None, resume: bool = False,
              log: Callable[[str], None] = lambda m: print(m, file=sys.stderr)) -> dict[str, Any]:
    from ..finetune import FinetuneOptions, finetune
    from ..replay.options import load_replay_config, override_config

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    bag = sequence_bag(Path(src), work, frames)
    if model == "lite0":   # --resume keeps the exported file (a new export differs in its bytes, not in its weights)
        original = work / "lite0.pt"
        if not (resume and original.is_file()):
            export_lite0(original)
    else:
        original = Path(model)
    require(original.is_file(), f"model file not found: {original}")
    cfg = override_config(load_replay_config(config), {"render_factor": render_factor,
                                                      **({"border": border} if border is not None else {})})
    ccfg = override_config(cfg, dict(cert_params or {}))
    state = work / "bench.json"
    old: dict[str, Any] = {}
    if resume and state.is_file():
        old = json.loads(state.read_text())
        if old.get("sequence") != str(bag) or old.get("model") != str(original) or old.get("render_factor") != render_factor:
            old = {}
    rows: dict[str, Any] = {"sequence": str(bag), "model": str(original), "render_factor": render_factor, "sigmas": {},
                            "certification": {"n0": ccfg.n0, "n": ccfg.n, "num_anchors": ccfg.num_anchors, "alpha": ccfg.alpha,
                                              "axes": list(ccfg.axes), "radii": ccfg.radii, "batch_size": batch_size}}

    def save() -> None:
        rows["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        tmp = state.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(rows, indent=1) + "\n")
        tmp.replace(state)

    for sigma in sigmas:
        key = f"{sigma:g}"
        out = work / f"tuned_sigma{sigma:.2f}.pt"
        opts = FinetuneOptions(bags=[bag], model=original, out=out, config=cfg, sigma=sigma, epochs=epochs, views=views,
                               stride=stride, holdout=holdout, eval_samples=eval_samples, batch_size=batch_size, device=device,
                               seed=seed, overwrite=True, max_frames=frames, log=lambda level, msg: log(f"[{level}] {msg}"))
        want = {"sigma": float(sigma), "epochs": epochs, "views_per_frame": views, "holdout": holdout, "stride": stride,
                "seed": seed, "render_factor": render_factor}
        entry = old.get("sigmas", {}).get(key)
        if reusable(entry, out, want, eval_samples, original, bag):
            log(f"[info] sigma {key}: reusing {out} and its results (--resume)")
            entry = dict(entry)
        else:
            t0 = time.perf_counter()
            res = finetune(opts)
            require(res.exit_code == 0, res.message or f"finetune stopped ({res.exit_code})")
            rep = res.report
            entry = {"heldout": {"before": rep["before"], "after": rep["after"], "teacher_stability": rep.get("teacher_stability")},
                     "seconds": rep["seconds"], "memory": rep["memory"],
                     "frames": rep["recordings"], "wall_s": round(time.perf_counter() - t0, 1), "model": str(out)}
        entry["report"] = str(opts.report_path())
        recs = {k: v for k, v in entry.get("recordings", {}).items() if k in {str(eb) for eb in eval_bags}}
        entry["recordings"] = recs
        certified = {k: v for k, v in entry.get("certified", {}).items()} if certify else {}
        entry["certified"] = certified
        rows["sigmas"][key] = entry
        save()
        for eb in eval_bags:
            if str(eb) not in recs:
                recs[str(eb)] = evaluate_recording(Path(eb), original, {"tuned": out}, opts, work, sigma, log)
                save()
        if not certify:
            continue
        todo: list[tuple[str, Path | None]] = []
        chosen: list[int] = []
        if certify_heldout > 0:
            rep = json.loads(Path(entry["report"]).read_text())
            chosen = pick_evenly([int(f["stamp_ns"]) for f in rep["per_frame"]], certify_heldout)
            if sorted({r["stamp_ns"] for r in certified.get("held-out", [])}) != sorted(chosen):
                certified.pop("held-out", None)     # another --certify-heldout than the stored rows': certify again
            todo.append(("held-out", None))
        else:
            certified.pop("held-out", None)
        todo += [(str(eb), Path(eb)) for eb in eval_bags]
        for name, b in todo:
            if name in certified:
                continue
            if b is None:
                b = frames_bag(bag, chosen, work / f"heldout_sigma{sigma:.2f}")
            certified[name] = certify_recording(b, out, ccfg, sigma, batch_size=batch_size, device=device, log=log)
            entry["certified_medians"] = certified_medians(entry)
            save()
        if chosen:   # the original model's clean answer next to the certified class of each held-out frame
            teacher = {int(f["stamp_ns"]): f["teacher"] for f in rep["per_frame"]}
            for r in certified.get("held-out", []):
                r["teacher"] = teacher.get(int(r["stamp_ns"]))
        entry["certified_medians"] = certified_medians(entry)
        save()
    save()
    return rows


def table(rows: dict[str, Any]) -> str:
    """Side by side: per sigma and evaluation set, agreement and p_A median before -> after."""
    def f(v: Any) -> str:
        return "-" if v is None else f"{v:.3f}"

    lines = [f"{'sigma':>6s}  {'frames':42s} {'agree before':>12s} {'agree after':>12s} {'p_A med before':>14s} {'p_A med after':>14s}"
             f" {'teacher stable':>14s} {'agree on stable after':>21s}"]
    for s, e in rows["sigmas"].items():
        sets = [("held-out end of the sequence", e["heldout"]["before"], e["heldout"]["after"], e["heldout"].get("teacher_stability"))]
        for name, r in e.get("recordings", {}).items():
            sets.append((Path(name).name, r["original"], r["tuned"], r.get("teacher_stability")))
        for name, b, a, st in sets:
            stable = "-" if not st else f"{st['stable_frames']} of {st['frames']}" + ("" if st.get("frames_with_motion_views") else "*")
            lines.append(f"{s:>6s}  {name[:42]:42s} {f(b['agreement']):>12s} {f(a['agreement']):>12s} "
                         f"{f(b['p_a_quantiles'].get('q50')):>14s} {f(a['p_a_quantiles'].get('q50')):>14s}"
                         f" {stable:>14s} {f(a.get('agreement_on_stable')):>21s}")
        lines.append(f"{'':6s}  training {e['seconds']['training']:.0f} s, frames {e['seconds']['frames']:.0f} s, "
                     f"peak memory {e['memory']['peak_rss_mb']:.0f} MB")
        if any(st and not st.get("frames_with_motion_views") for *_, st in sets):
            lines.append(f"{'':6s}  * no motion views there: stable means under the noise alone")
    cert = [(s, e) for s, e in rows["sigmas"].items() if e.get("certified")]
    if cert:
        c = rows.get("certification", {})
        lines.append("")
        lines.append(f"certified radius of the tuned model vs the ceiling (a never-changing classifier), share of the requested "
                     f"radius; n0 {c.get('n0')}, n {c.get('n')}, {c.get('num_anchors')} anchors, alpha {c.get('alpha')}")
        lines.append(f"{'sigma':>6s}  {'frames':28s} {'stamp s':>10s} {'axis':>4s} {'requested':>10s} {'ceiling':>8s} {'tuned':>8s} "
                     f"{'ratio':>6s}  {'tuned class, p_A lower bound (clean: original)':44s} {'s':>5s}")
        for s, e in cert:
            for name, rs in e["certified"].items():
                for r in rs:
                    ratio = "-" if r.get("ratio") is None else f"{r['ratio']:.2f}"
                    cls = f"{r.get('model_class', '')}, {r['model_p_a']:.3f}" if r.get("model_p_a") is not None else "-"
                    if r.get("teacher"):
                        cls += f" (clean: {r['teacher']})"
                    secs = f"{(r.get('ceiling_s') or 0) + (r.get('model_s') or 0):.0f}"
                    lines.append(f"{s:>6s}  {Path(name).name[:28]:28s} {r['stamp_ns'] / 1e9:>10.3f} {r['axis']:>4s} "
                                 f"{r['requested']:>8.4g} {r['unit']:1s} {f(r.get('ceiling_share')):>8s} {f(r.get('model_share')):>8s} "
                                 f"{ratio:>6s}  {cls:44s} {secs:>5s}")
            for axis, m in e.get("certified_medians", {}).items():
                med = "-" if m["ratio_median"] is None else f"{m['ratio_median']:.2f}"
                lines.append(f"{'':6s}  {axis}: median radius / ceiling {med} over {m['frames']} frame(s); median share of the "
                             f"request: ceiling {m['ceiling_share_median']:.3f}, tuned {m['model_share_median']:.3f}")
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
    p.add_argument("--certify-heldout", type=int, default=3, metavar="K",
                   help="held-out frames of the sequence to certify (spread evenly; default 3, 0 = none)")
    p.add_argument("--no-certify", action="store_true", help="no certification (agreement and p_A only)")
    for name, kind, text in (("--n0", int, "selection samples"), ("--n", int, "estimation samples per anchor"),
                             ("--anchors", int, "most anchors per axis")):
        p.add_argument(name, type=kind, default=None, help=f"certification: {text} (default: config)")
    p.add_argument("--resume", action="store_true", help="keep the stages DIR/bench.json already holds (same settings)")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    try:
        sigmas = tuple(float(s) for s in a.sigmas.split(",") if s.strip())
        require(a.certify_heldout >= 0, f"--certify-heldout must be >= 0, got {a.certify_heldout}")
        cert = {k: v for k, v in (("n0", a.n0), ("n", a.n), ("num_anchors", a.anchors)) if v is not None}
        rows = run_bench(a.src, a.work, model=a.model, sigmas=sigmas, frames=a.frames, eval_bags=tuple(a.eval), epochs=a.epochs,
                         views=a.views, stride=a.stride, holdout=a.holdout, eval_samples=a.eval_samples, batch_size=a.batch_size,
                         render_factor=a.render_factor, device=a.device, seed=a.seed, config=a.config,
                         border=a.border, certify_heldout=a.certify_heldout, certify=not a.no_certify, cert_params=cert,
                         resume=a.resume)
    except (PwsError, ValueError) as exc:
        print(f"finetune_bench: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(rows, indent=1) if a.json else table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
