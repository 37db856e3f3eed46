"""One tuning run (:func:`finetune`): check, cache the frames, evaluate the teacher, train with
checkpoints, save the model file, evaluate it, write the report."""
from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..core.errors import PwsError, require, require_creatable
from ..core.jsonable import jsonable
from ..core.model import load_model, save_model, sidecar_path
from ..core.render import resolve_device
from ..replay.interrupt import Interrupted, StopSignals
from ..replay.progress_log import Progress
from .cache import FramePreparer, atomic_write_text, split_by_clip
from .evaluate import clean_predictions, heldout_items, per_frame, smoothed_counts, stability_summary, summarize, teacher_stability
from .options import FinetuneOptions, FinetuneResult
from .train import Student, Trainer, TrainSet, atomic_save, load_checkpoint, quiet_jit

REPORT_FORMAT = "pws_ros-finetune-report-1"
MANIFEST = "manifest.json"
CHECKPOINT = "checkpoint.pt"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _bag_stamp(path: Path) -> list:
    """Size and modification time of a recording's files (a changed recording is a new cache)."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return [[p.name, p.stat().st_size, int(p.stat().st_mtime)] for p in files]


def _key(d: dict) -> str:
    return hashlib.sha256(json.dumps(jsonable(d), sort_keys=True).encode()).hexdigest()[:32]


def _peak_memory() -> dict[str, float]:
    out = {"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


class FinetuneRun:
    def __init__(self, opts: FinetuneOptions):
        self.opts = opts
        self.warnings: list[str] = []
        self.bar: Progress | None = None

    # ---- logging ----
    def log(self, level: str, message: str) -> None:
        if level == "warn":
            self.warnings.append(message)
        if self.opts.log is not None:
            self.opts.log(level, message)
            return
        if level == "info" and self.opts.quiet:
            return
        if self.bar is not None:
            self.bar.clear()
        prefix = "pws finetune: " + ("warning: " if level == "warn" else "")
        print(prefix + message, file=sys.stderr, flush=True)

    def progress(self, total: int | None, label: str, unit: str) -> Progress:
        o = self.opts
        mode = None if o.progress is None else ("bar" if o.progress else "off")
        if o.quiet:
            mode = "off"
        elif o.log is not None and mode is None:
            mode = "log"
        self.bar = Progress(total, label=f"pws finetune: {label}", unit=unit, mode=mode, interval_s=o.progress_interval_s,
                            emit=lambda line: self.log("info", f"{label}: {line}"))
        return self.bar

    def close_bar(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    # ---- set-up ----
    def _check_paths(self) -> None:
        o = self.opts
        for bag in o.bags:
            require(Path(bag).exists(), f"recording not found: {bag}")
        out = Path(o.out)
        require(out.suffix != "", f"--out {out}: give a model file name such as tuned.pt")
        require(not out.exists() or out.is_file(), f"--out {out} is a folder, not a model file")
        require(o.model is None or out.resolve() != Path(o.model).resolve(), f"--out {out} is the input model itself")
        require(o.overwrite or o.resume or not out.exists(), f"output {out} already exists: choose another --out or pass --overwrite")
        require_creatable(out, "--out")
        work = o.resolved_work_dir()
        self._made_work = not work.exists()
        if work.exists():
            require(work.is_dir(), f"work folder {work} is a file")
            ours = (work / MANIFEST).exists() or not any(work.iterdir())
            if not o.resume:
                require(o.overwrite, f"work folder {work} exists (an earlier run): pass --resume to continue it, or --overwrite to "
                                     "start over")
                require(ours, f"work folder {work} is not a pws finetune work folder: choose another --work-dir")
                shutil.rmtree(work)
        require_creatable(work, "work folder")
        try:
            work.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PwsError(f"cannot make the work folder {work}: {exc}") from None

    def _manifest(self, teacher: Any, sigma: float) -> tuple[dict, str, str]:
        o, c = self.opts, self.opts.config
        cache = {"bags": [[str(Path(b).resolve()), _bag_stamp(Path(b))] for b in o.bags], "model_sha256": self.model_sha,
                 "classes": list(teacher.class_names), "imaging": c.imaging, "render_factor": c.render_factor, "border": c.border,
                 "background": c.background_value,
                 "working_volume": None if c.working_volume is None else c.working_volume.to_dict(), "render_size": [c.render_height, c.render_width], "axes": list(c.axes),
                 "radii": c.radii, "views": o.views, "seed": o.seed, "stride": o.stride, "max_frames": o.max_frames,
                 "topics": dict(sorted(o.topics.items())), "sync": [c.sync_tolerance_s, c.sync_max_skew_s],
                 "input_mode": c.input_mode, "source": self.source, "use_truth": o.use_truth, "fresh_head": o.fresh_head}
        train = {"cache": _key(cache), "sigma": sigma, "mode": o.mode, "targets": o.targets, "use_truth": o.use_truth,
                 "holdout": o.holdout, "holdout_clips": o.holdout_clips, "consistency": o.consistency, "noise_warmup": o.noise_warmup, "clean_share": o.clean_share, "augment": o.augment, "epochs": o.epochs, "batch_size": o.batch_size, "lr": o.learning_rate,
                 "weight_decay": o.weight_decay, "mse_weight": o.mse_weight if o.mode == "denoiser" else None,
                 "denoiser": [o.denoiser_channels, o.denoiser_depth, str(o.init_denoiser or "")] if o.mode == "denoiser" else None}
        return {"cache": cache, "train": train}, _key(cache), _key(train)

    def _check_manifest(self, work: Path, manifest: dict) -> None:
        path = work / MANIFEST
        if path.exists():
            old = json.loads(path.read_text(encoding="utf-8"))
            if old.get("cache") != jsonable(manifest["cache"]):
                diff = sorted(k for k in manifest["cache"] if jsonable(manifest["cache"][k]) != old.get("cache", {}).get(k))
                raise PwsError(f"--resume: the work folder {work} was made with other recordings, model or frame settings "
                               f"({', '.join(diff) or 'format'} differ): run without --resume (with --overwrite) to start over")
        atomic_write_text(path, json.dumps(jsonable(manifest), indent=1) + "\n")

    # ---- the run ----
    def run(self) -> FinetuneResult:
        """The whole run; where it refuses its input before any frame is kept, a work folder it made goes too."""
        self._made_work = False
        try:
            return self._run_all()
        except PwsError:
            work = self.opts.resolved_work_dir()
            # (a frame cached is kept: --resume continues from it)
            if self._made_work and work.is_dir() and not any(f.is_file() and f.name not in (MANIFEST, "new_head.pt")
                                                             for f in work.rglob("*")):
                shutil.rmtree(work, ignore_errors=True)
            raise

    def _run_all(self) -> FinetuneResult:
        o = self.opts
        o.check()
        sigma = o.noise_sigma()
        t_start = time.perf_counter()
        device = resolve_device(o.device)
        require(o.model is None or Path(o.model).is_file(), f"model file not found: {o.model}")
        self.source = str(o.backbone) if o.backbone else str(Path(o.model).resolve())
        self._check_paths()
        work = o.resolved_work_dir()
        if o.fresh_head:
            o = self.opts = replace(o, model=self._new_head(work), classes=None)
        teacher = load_model(o.model, classes=o.classes, device=device)
        require(teacher.num_classes >= 2, f"model {o.model} has {teacher.num_classes} output(s): a classifier needs at least 2 classes")
        self.model_sha = _sha256(Path(o.model))
        manifest, cache_key, train_key = self._manifest(teacher, sigma)
        self._check_manifest(work, manifest)

        from ..bridge.engine import FrameCertifier

        # the engine only makes the imaging; its sigma is the teacher's own (no "sigma differs" warning here) and its
        # batch size this command's (no advice about a config batch size the command does not use)
        trained = teacher.meta.get("sigma")
        ecfg = replace(o.config, sigma=float(trained) if isinstance(trained, (int, float)) and trained > 0 else sigma,
                       device=str(device), batch_size=int(o.batch_size))
        engine = FrameCertifier(ecfg, model=teacher, load=False,
                                log=lambda level, msg: self.log("warn" if level in ("warn", "error") else "info", msg))
        result = FinetuneResult(None, None, {})
        with StopSignals() as stop:
            try:
                return self._run(teacher, engine, device, sigma, work, train_key, stop, t_start)
            except KeyboardInterrupt as exc:
                signame = exc.signame if isinstance(exc, Interrupted) else "SIGINT"
                self.close_bar()
                result.interrupted = signame
                result.exit_code = Interrupted(signame).exit_code
                result.message = (f"stopped by {signame}: {self.stopped_at}; the work folder {work} keeps what is done: "
                                  "rerun the same command with --resume to continue")
                result.report = {"interrupted": signame, "work_dir": str(work)}
                return result

    stopped_at = "while caching the frames"

    def _new_head(self, work: Path) -> Path:
        """The starting model of a new head (:mod:`.heads`), made once in the work folder (kept for --resume)."""
        from .heads import build_new_head, class_list

        o = self.opts
        path = work / "new_head.pt"
        if o.resume and path.is_file():
            return path
        classes = class_list(o.classes, o.bags, o.config, o.topics, lambda m: self.log("warn", m))
        size = o.input_size
        if size is None:
            size = (load_model(o.model).input_size if o.model is not None else None) or (120, 160)
        build_new_head(path, classes=classes, input_size=tuple(size), seed=o.seed, backbone=o.backbone, model=o.model)
        self.log("info", f"a new head for {len(classes)} classes ({', '.join(classes)}) on "
                         f"{o.backbone or o.model}, input {size[1]}x{size[0]}")
        return path

    def _run(self, teacher: Any, engine: Any, device: torch.device, sigma: float, work: Path, train_key: str, stop: Any,
             t_start: float) -> FinetuneResult:
        o = self.opts
        # 1. the frames
        t0 = time.perf_counter()
        bar = self.progress(None, "caching frames", "frames")
        prep = FramePreparer(o, teacher, engine, work, device=device, stop=stop, warn=lambda m: self.log("warn", m),
                             info=lambda m: self.log("info", m), progress=bar)
        caches = [prep.prepare(i, Path(b)) for i, b in enumerate(o.bags)]
        self.close_bar()
        prep_s = time.perf_counter() - t0
        splits = split_by_clip(caches, list(o.holdout_clips)) if o.holdout_clips else [c.split(o.holdout) for c in caches]
        train_split = [s for s, _ in splits]
        held_split = [h for _, h in splits]
        held = heldout_items(caches, held_split)
        n_train = sum(len(s) for s in train_split)
        self.log("info", f"{sum(c.count for c in caches)} frames cached in {prep_s:.0f} s: {n_train} to train on "
                         f"({n_train * (1 + o.views)} images with the motion views), {len(held)} held out ("
                         + (f"clips {', '.join(o.holdout_clips)}" if o.holdout_clips else f"the last {o.holdout:.0%} of each recording")
                         + ")")
        teacher_top = np.asarray([caches[ci].frames[k]["teacher"] for ci, k in held], dtype=np.int64)
        truth = np.asarray([caches[ci].frames[k]["truth_label"] for ci, k in held], dtype=np.int64)

        # 2. the teacher under noise (the "before"), kept in the work folder for a resumed run; a new head has no
        # teacher: its measure is the label (truth) and there is no "before"
        if o.fresh_head:
            teacher_top = truth
            before = stab = None
        else:
            before_path = work / f"before_{train_key}.npy"
            if before_path.exists():
                before = np.load(before_path)
            else:
                self.stopped_at = "while evaluating the original model"
                before = self._evaluate(teacher, caches, held, sigma, device, teacher.num_classes, "evaluating the original model")
                with stop.section():
                    np.save(before_path.with_name(before_path.name + ".tmp.npy"), before)
                    os.replace(before_path.with_name(before_path.name + ".tmp.npy"), before_path)

            # the ceiling of the agreement: on which held-out frames the teacher's own answer is stable
            stab = teacher_stability(teacher, caches, held, teacher_top, seed=o.seed, device=device)
            self.log("info", f"the teacher keeps its clean answer (>= 90% of copies with noise sigma 0.01 and every motion "
                             f"view) on {int(stab['stable'].sum())} of {len(held)} held-out frames: the agreement any smoothed "
                             "classifier can be expected to reach there")

        # 3. training
        student = Student(o.mode, Path(o.model), device, channels=o.denoiser_channels, depth=o.denoiser_depth,
                          init_denoiser=o.init_denoiser)
        data = TrainSet(caches, train_split, o.use_truth)
        trainer = Trainer(student, data, sigma=sigma, epochs=o.epochs, batch_size=o.batch_size, lr=o.learning_rate,
                          weight_decay=o.weight_decay, targets=o.targets, mse_weight=o.mse_weight, seed=o.seed, device=device,
                          consistency=o.consistency, noise_warmup=o.noise_warmup, clean_share=o.clean_share,
                          augment=o.augment, background=o.config.background_value)
        ckpt_path = work / CHECKPOINT
        elapsed_before = 0.0
        if o.resume:
            state = load_checkpoint(ckpt_path, train_key, device)
            if state is not None:
                trainer.load(state)
                elapsed_before = float(state.get("elapsed_s", 0.0))
                self.log("info", f"resuming from the checkpoint at step {trainer.step}/{trainer.total}")
        elif ckpt_path.exists():
            ckpt_path.unlink()
        truth_frames = sum(1 for c, s in zip(caches, train_split) for k in s if c.frames[k]["truth_label"] >= 0) if o.use_truth else 0
        self.log("info", f"training the {o.mode} ({student.num_params()} parameters) on {device}: {trainer.total} steps "
                         f"({o.epochs} epochs x {trainer.steps_per_epoch}) of {o.batch_size} noisy images at sigma {sigma:g}, "
                         f"targets: " + ", ".join(([f"ground truth on {truth_frames} frame(s)"] if truth_frames else [])
                                                  + ([] if o.fresh_head else
                                                     [f"the teacher's {'probabilities' if o.targets == 'soft' else 'top class'}"]))
                         + (f", consistency weight {o.consistency:g}" if o.consistency > 0 else "")
                         + (f", {o.clean_share:.0%} of each batch clean" if o.clean_share > 0 else "")
                         + (", augmented (colour gains, shifts, scales)" if o.augment else ""))
        t_train = time.perf_counter()
        bar = self.progress(trainer.total, "training", "steps")
        bar.update(trainer.step)

        def checkpoint() -> None:
            with stop.section():
                atomic_save(trainer.state(train_key, elapsed_before + time.perf_counter() - t_train), ckpt_path)

        last_ckpt = time.monotonic()
        cudnn = (torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark)
        # CUDA: deterministic cuDNN algorithms, so that a resumed run repeats the uninterrupted one bit for bit
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
        try:
            while trainer.step < trainer.total:
                with stop.section():
                    loss = trainer.one_step()
                bar.update(1, note=f"loss {loss:.3f}")
                if trainer.epoch_end or (o.checkpoint_every_s > 0 and time.monotonic() - last_ckpt >= o.checkpoint_every_s):
                    checkpoint()
                    last_ckpt = time.monotonic()
                if o.on_step is not None:
                    o.on_step(trainer.step)
        except KeyboardInterrupt:
            self.stopped_at = f"training at step {trainer.step}/{trainer.total} (checkpoint saved)"
            self.close_bar()
            with stop.section():
                atomic_save(trainer.state(train_key, elapsed_before + time.perf_counter() - t_train), ckpt_path)
            raise
        finally:
            torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = cudnn
        self.close_bar()
        train_s = elapsed_before + time.perf_counter() - t_train
        self.log("info", f"trained in {train_s:.0f} s" + (f" ({train_s / 60:.1f} min)" if train_s > 90 else ""))

        # 4. the model file (and the denoiser alone), written atomically
        self.stopped_at = "while writing the model file"
        with stop.section():
            paths = self._save(student, teacher, caches, splits, sigma, trainer, work)
        model_path = paths[0]

        # 5. the tuned model under noise, loaded back from its file (the contract checked)
        self.stopped_at = "while evaluating the tuned model (the model file is written)"
        tuned = load_model(model_path, device=device)
        after = self._evaluate(tuned, caches, held, sigma, device, teacher.num_classes, "evaluating the tuned model")
        self.clean = {"after": clean_predictions(tuned, caches, held, device),
                      "before": None if o.fresh_head else clean_predictions(teacher, caches, held, device)}

        report = self._report(teacher, caches, splits, held, before, after, teacher_top, truth, stab, sigma, trainer, student,
                              device, prep_s, train_s, time.perf_counter() - t_start, model_path, paths[1:])
        report_path = self.opts.report_path()
        with stop.section():
            atomic_write_text(report_path, json.dumps(jsonable(report), indent=1) + "\n")
        if not o.keep_work:
            shutil.rmtree(work, ignore_errors=True)
        return FinetuneResult(model_path, report_path, report, 0, "", "", list(paths[1:]))

    def _evaluate(self, model: Any, caches, held, sigma, device, classes, label) -> np.ndarray:
        bar = self.progress(len(held), label, "frames")
        counts = smoothed_counts(model, caches, held, sigma=sigma, n=self.opts.eval_samples, seed=self.opts.seed,
                                 batch_size=max(1, self.opts.batch_size), device=device, num_classes=classes,
                                 progress=bar.update)
        self.close_bar()
        return counts

    def _save(self, student: Student, teacher: Any, caches, splits, sigma: float, trainer: Trainer, work: Path) -> list[Path]:
        o = self.opts
        out = Path(o.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        info = {k: v for k, v in teacher.meta.items() if k not in ("format", "class_names", "input_height", "input_width", "sigma")}
        info["sigma"] = float(sigma)
        tuned = {"tool": "pws finetune", "mode": o.mode, "from_model": self.source, "new_head": o.fresh_head, "from_sha256": self.model_sha,
                 "from_sigma": teacher.meta.get("sigma"), "sigma": float(sigma),
                 "recordings": [{"bag": c.bag, "frames": c.count, "trained_on": len(s), "held_out": len(h),
                                 "first_held_out_stamp_ns": c.frames[h[0]]["stamp_ns"] if len(h) else None}
                                for c, (s, h) in zip(caches, splits)],
                 "views_per_frame": o.views, "axes": list(o.config.axes), "radii": o.config.radii, "imaging": o.config.imaging,
                 "render_factor": o.config.render_factor, "holdout": o.holdout, "holdout_clips": o.holdout_clips,
                 "working_volume": None if o.config.working_volume is None else o.config.working_volume.to_dict(),
                 "consistency": o.consistency, "clean_share": o.clean_share, "augment": o.augment, "stride": o.stride, "targets": o.targets,
                 "ground_truth_used": o.use_truth, "epochs": o.epochs, "steps": trainer.total, "batch_size": o.batch_size,
                 "lr": o.learning_rate, "seed": o.seed, "report": o.report_path().name}
        info["finetune"] = tuned
        tmp = work / "model_out.pt"
        module = student.export_module().cpu()   # a model file holds CPU tensors (the loaders map them to their device)
        with quiet_jit():
            if o.mode == "denoiser":
                module = torch.jit.script(module)
            save_model(module, tmp, teacher.class_names, input_size=teacher.input_size, meta=jsonable(info))
        _move(tmp, out)
        _move(sidecar_path(tmp), sidecar_path(out))
        paths = [out]
        if o.mode == "denoiser":
            from ..sim.train import save_denoiser

            dtmp = work / "denoiser_out.pt"
            save_denoiser(student.trainable.eval().cpu(), dtmp, sigma, teacher.input_size, meta=jsonable({"finetune": tuned}))
            _move(dtmp, o.denoiser_path())
            paths.append(o.denoiser_path())
        return paths

    def _report(self, teacher, caches, splits, held, before, after, teacher_top, truth, stab, sigma, trainer, student, device,
                prep_s, train_s, total_s, model_path, extra) -> dict:
        o = self.opts
        stable = None if stab is None else stab["stable"]
        clean = self.clean
        b = None if before is None else summarize(before, teacher_top, truth, sigma=sigma, stable=stable, clean=clean["before"])
        a = summarize(after, teacher_top, truth, sigma=sigma, stable=stable, clean=clean["after"])
        pbs = [None] * len(held) if before is None else per_frame(before, teacher_top)
        rows = []
        for i, ((ci, k), pb, pa) in enumerate(zip(held, pbs, per_frame(after, teacher_top))):
            f = caches[ci].frames[k]
            row = {"recording": caches[ci].bag, "index": f["index"], "stamp_ns": f["stamp_ns"], "clip": f.get("clip", ""),
                   "truth": (teacher.class_name(f["truth_label"]) if f["truth_label"] >= 0 else None),
                   "clean_after": teacher.class_name(int(clean["after"][i])),
                   "after": {**pa, "top": teacher.class_name(pa["top"])}}
            if pb is not None:
                row.update({"teacher": teacher.class_name(f["teacher"]), "teacher_stable": bool(stable[i]),
                            "teacher_noise_keep": float(stab["noise"][i]), "teacher_motion_keep": float(stab["motion"][i]),
                            "before": {**pb, "top": teacher.class_name(pb["top"])}})
            rows.append(row)
        held_by = f"the clips {', '.join(o.holdout_clips)}" if o.holdout_clips else "the last part of each recording by time"
        against = "the frame's label" if o.fresh_head else "the original model's clean prediction"
        return {
            "format": REPORT_FORMAT,
            "model": str(model_path), "extra_files": [str(p) for p in extra], "teacher_model": self.source,
            "new_head": o.fresh_head, "classes": list(teacher.class_names),
            "mode": o.mode, "sigma": sigma, "eval_samples": o.eval_samples,
            "measure": (f"held-out alpha = 0 frames ({held_by}, never trained on): the smoothed "
                        f"prediction (majority of eval_samples noisy copies at sigma) against {against} (agreement); "
                        "clean_accuracy_vs_truth = the base classifier on the clean frame against the label; "
                        "p_a = the top class's share of the copies, p_teacher = the target's share; "
                        "l2_radius_median = median over frames of sigma * Phi^-1(p_a lower bound, alpha 0.001) where the "
                        "smoothed prediction agrees (0 elsewhere); the same noise draws before and after"),
            "before": b, "after": a, "teacher_stability": None if stab is None else stability_summary(stab),
            "recordings": [{"bag": c.bag, "frames": c.count, "trained_on": len(s), "held_out": len(h),
                            "held_out_clips": sorted({c.frames[k].get("clip", "") for k in h} - {""}),
                            "input_frames_seen": c.info.get("input_frames_seen"),
                            "input_frames_skipped": c.info.get("input_frames_skipped")} for c, (s, h) in zip(caches, splits)],
            "frames": {"views_per_frame": o.views, "axes": list(o.config.axes), "radii": o.config.radii,
                       "imaging": o.config.imaging, "render_factor": o.config.render_factor, "shape": list(caches[0].views.shape[1:]),
                       "working_volume": None if o.config.working_volume is None else o.config.working_volume.to_dict()},
            "training": {"steps": trainer.total, "epochs": o.epochs, "batch_size": o.batch_size, "lr": o.learning_rate,
                         "targets": "labels" if o.fresh_head else o.targets, "ground_truth_used": o.use_truth,
                         "consistency": o.consistency, "noise_warmup_epochs": o.noise_warmup, "clean_share": o.clean_share,
                         "augment": o.augment, "trainable_parameters": student.num_params(),
                         "history": trainer.history, "seed": o.seed, "device": str(device)},
            "seconds": {"frames": round(prep_s, 1), "training": round(train_s, 1), "total": round(total_s, 1)},
            "memory": _peak_memory(),
            "per_frame": rows,
            "warnings": self.warnings,
        }


def _move(src: Path, dst: Path) -> None:
    try:
        os.replace(src, dst)
    except OSError:  # another file system (--work-dir elsewhere): copy beside, then rename
        tmp = dst.with_name(dst.name + ".tmp")
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
        src.unlink(missing_ok=True)


def finetune(options: FinetuneOptions) -> FinetuneResult:
    """Run ``pws finetune`` (see :mod:`pws_ros.finetune`). PwsError for bad input (one line)."""
    return FinetuneRun(options).run()


from .summary import summary_lines  # noqa: E402  (re-exported: pws_ros.finetune.run.summary_lines)


__all__ = ["FinetuneRun", "finetune", "summary_lines"]
