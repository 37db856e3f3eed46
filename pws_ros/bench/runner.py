"""The measurements of ``pws bench``: every figure is measured in this process, on the same scenes
and with the same classifier, and recorded with the settings that produced it.

Stages (each a list of plain records in ``results``):

* ``throughput``: pure classifier (and denoiser + classifier) images per second on noise batches;
* ``plans``: the Table 1 analogue, planning only (PwS on the entire dense cloud, PwS-L and PwS-OF on
  the one-frame cloud), with the dense cloud's consistent-run quantiles;
* ``certificates``: PwS / PwS-L / PwS-OF under the paper, pairwise and anchors coverage rules, and CMS,
  at the paper's radii; the paper rule is read from the pairwise run's own bounds (same counts);
* ``sigma``, ``partitions``, ``empirical``, ``denoiser``: the ablations;
* ``scaling``: time and peak memory against the number of partitions, the image size and the cloud size.
"""
from __future__ import annotations

import math
import os
import platform
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..core.certify import CertifyConfig, certify, certify_rendered
from ..core.coverage import PaperRule, cohen_radii
from ..core.bounds import render_plan
from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.model import LoadedModel, load_denoiser, load_model
from ..core.motion import PAPER_RADIUS, UNITS
from ..core.partition import DEFAULT_DELTA_PX, Plan, consistent_runs, make_grid, plan_partitions
from ..core.render import Renderer, resolve_device
from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED
from ..core.smoothing import SmoothedClassifier
from .settings import BenchSettings, scene_ids
from .shipped import stage_shipped

PLAN_CAP = 10_000_000          # larger plans are reported as "> PLAN_CAP" (the grid alone would not fit)
RUN_QUANTILES = (0.0, 1e-4, 1e-3, 1e-2, 0.5)
PLAN_METHODS = ("pws", "pws_l", "pws_of")
CERT_METHODS = ("pws", "pws_l", "pws_of")
COVERAGE_RULES = ("paper", "pairwise", "anchors")


# ------------------------------------------------------------------------------------------------
# small utilities
# ------------------------------------------------------------------------------------------------
def _rss_bytes() -> int | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


class PeakMemory:
    """Peak growth of this process's resident memory while the block runs (sampled every few ms
    from ``/proc/self/statm``), and of CUDA memory (``torch.cuda.max_memory_allocated``) on a GPU.
    ``peak_bytes`` is None where the platform does not expose the RSS."""

    def __init__(self, device: torch.device, interval: float = 0.004):
        self.device = device
        self.interval = interval
        self.peak_bytes: int | None = None
        self.cuda_peak_bytes: int | None = None
        self._stop = threading.Event()

    def _poll(self) -> None:
        while not self._stop.is_set():
            r = _rss_bytes()
            if r is not None and r > self._max:
                self._max = r
            self._stop.wait(self.interval)

    def __enter__(self) -> "PeakMemory":
        self._base = _rss_bytes()
        self._max = self._base or 0
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._cuda_base = torch.cuda.memory_allocated(self.device)
        self._thread = threading.Thread(target=self._poll, daemon=True) if self._base is not None else None
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            r = _rss_bytes()
            self.peak_bytes = max(self._max, r or 0) - self._base
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.cuda_peak_bytes = int(torch.cuda.max_memory_allocated(self.device) - self._cuda_base)


def machine_info(device: torch.device) -> dict[str, Any]:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    try:
        mem = int(Path("/proc/meminfo").read_text().split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        mem = None
    import scipy

    info = {
        "platform": platform.platform(), "python": sys.version.split()[0], "cpu": cpu, "cpu_count": os.cpu_count(),
        "usable_cpus": affinity, "memory_bytes": mem, "torch": torch.__version__, "numpy": np.__version__,
        "scipy": scipy.__version__, "torch_threads": torch.get_num_threads(), "device": str(device),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    try:
        import matplotlib

        info["matplotlib"] = matplotlib.__version__
    except ImportError:  # pragma: no cover
        info["matplotlib"] = None
    if device.type == "cuda":
        info["cuda_device"] = torch.cuda.get_device_name(device)
        info["cuda_version"] = torch.version.cuda
    try:
        from .. import __version__

        info["pws_ros"] = __version__
    except ImportError:  # pragma: no cover
        info["pws_ros"] = None
    return info


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def _display_path(p: Path) -> str:
    """``p`` relative to the working directory when it lies below it (keeps committed reports machine-neutral)."""
    try:
        return str(Path(p).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


def capped_plan(plan: Plan, cap: int, floor: int = 3) -> Plan:
    """The plan itself when it has between ``floor`` and ``cap`` partitions; else the uniform grid of
    ``cap`` (coarser: still sound, because certification rests on the rendered per-segment bounds, not
    on the plan) or ``floor`` partitions (finer: resolves the certified-radius curve)."""
    if floor <= plan.num_partitions <= cap:
        return plan
    target = cap if plan.num_partitions > cap else floor
    m = (target - 1) // 2
    alphas = make_grid(plan.radius, plan.radius / m, max_partitions=target)
    key = "capped_from" if plan.num_partitions > cap else "refined_from"
    details = {key: int(plan.num_partitions), "planned_delta_alpha": float(plan.delta_alpha),
               "lemma1_holds": None if key == "capped_from" else plan.details.get("lemma1_holds"),
               "plan_seconds": plan.details.get("plan_seconds", 0.0)}
    return Plan(plan.method, plan.axis, plan.radius, float(alphas[1] - alphas[0]), len(alphas), alphas, plan.unit, details)


def grid_plan(method: str, axis: str, radius: float, num_partitions: int) -> Plan:
    """An explicit uniform grid of ``num_partitions`` (odd) motions on ``[-radius, radius]``."""
    m = (int(num_partitions) - 1) // 2
    alphas = make_grid(radius, radius / m, max_partitions=int(num_partitions))
    return Plan(method, axis, radius, float(alphas[1] - alphas[0]), len(alphas), alphas, UNITS[axis], {"explicit_grid": True})


def paper_rule(p_a_lower, pair_bound_sq, alphas, sigma: float) -> tuple[str, bool, float]:
    """The paper's coverage rule (Theorem 1 with the sound per-segment bounds: ``max sqrt(B_i / 2) <
    min R_i`` over the symmetric sub-interval) read off a pairwise run: the same counts, the same
    Bonferroni level, so the same decision :func:`certify` would make with ``coverage='paper'``.
    Returns ``(status, certified, radius)``."""
    alphas = np.asarray(alphas, dtype=np.float64)
    p = np.asarray(p_a_lower, dtype=np.float64).reshape(-1)
    require(len(p) == len(alphas), "paper rule needs one p_A bound per partition")
    R = cohen_radii(p, sigma)
    centre = int(np.searchsorted(alphas, 0.0))
    j, _ = PaperRule().reach(R, centre, pair_bound_sq=pair_bound_sq)
    if not R[centre] > 0:
        return STATUS_ABSTAIN, False, 0.0
    certified = j == centre
    return (STATUS_CERTIFIED if certified else STATUS_NOT_CERTIFIED), certified, float(alphas[centre + j])


def _timing(t: dict[str, float]) -> dict[str, float]:
    return {k: float(t.get(k, 0.0)) for k in ("plan", "render", "inference", "statistics", "total")}


# ------------------------------------------------------------------------------------------------
# the bench
# ------------------------------------------------------------------------------------------------
class Bench:
    def __init__(self, settings: BenchSettings, models_dir: str | Path, device: str = "cpu",
                 log: Callable[[str], None] | None = None):
        self.s = settings.validate()
        self.device = resolve_device(device)
        self.models_dir = Path(models_dir)
        self._log = log
        self.t0 = time.perf_counter()
        self.results: dict[str, Any] = {}
        self._views: dict[tuple[int, int, int, int], Any] = {}
        self.plans: dict[tuple[int, str, str], Plan] = {}
        self.rendered: dict[tuple[int, str, str], Any] = {}
        self._models: dict[str, LoadedModel] = {}
        self.stage_seconds: dict[str, float] = {}

    # -- logging -------------------------------------------------------------------------------
    def log(self, msg: str) -> None:
        if self._log is not None:
            self._log(f"[bench {time.perf_counter() - self.t0:6.1f}s] {msg}")

    # -- inputs --------------------------------------------------------------------------------
    def model_files(self) -> dict[str, Path | None]:
        d = self.models_dir
        require(d.is_dir(), f"models folder not found: {d} (build it with `pws train all --out {d}`)")
        files: dict[str, Path | None] = {}
        for key in ("0.25", "0.50", "0.75"):
            p = d / f"classifier_sigma{key}.pt"
            files[key] = p if p.is_file() else None
        den = d / "denoiser_sigma0.50.pt"
        files["denoiser"] = den if den.is_file() else None
        require(files["0.50"] is not None, f"{d} lacks classifier_sigma0.50.pt (build it with `pws train all --out {d}`)")
        return files

    def model(self, key: str) -> LoadedModel:
        if key not in self._models:
            path = self.files[key]
            require(path is not None, f"{self.models_dir} lacks classifier_sigma{key}.pt")
            self._models[key] = load_model(path, device=self.device)
        return self._models[key]

    def classifier_for_sigma(self, sigma: float) -> tuple[str, str]:
        """(model key, note): the classifier trained at ``sigma``, else the sigma-0.5 one."""
        key = f"{sigma:.2f}"
        if self.files.get(key) is not None:
            return key, ""
        return "0.50", f"No classifier_sigma{key}.pt: the σ-0.5 classifier is smoothed with σ = {sigma:g}"

    def view(self, scene: int, view_index: int, dense: bool, width: int | None = None, height: int | None = None):
        """The bench view (cached); ``dense`` also builds the entire dense cloud."""
        from ..sim import render_view

        key = (scene, view_index, int(width or self.width), int(height or self.height))
        v = self._views.get(key)
        if v is None or (dense and v.dense is None):
            v = render_view(scene, view_index, key[2], key[3], dense=dense, samples_per_pixel=self.s.samples_per_pixel)
            self._views[key] = v
        return v

    def true_index(self, view, model: LoadedModel) -> int:
        names = list(model.class_names)
        return names.index(view.class_name) if view.class_name in names else int(view.label)

    def config(self, **kw) -> CertifyConfig:
        base = CertifyConfig(sigma=0.5, n0=self.s.n0, n=self.s.n, alpha=self.s.alpha, seed=self.s.seed, device=str(self.device),
                             batch_size=self.s.batch_size, coverage="pairwise", num_anchors=self.s.num_anchors,
                             background=self.s.background, delta=self.s.delta_px, imaging="paper",
                             max_partitions=20000)
        return replace(base, **kw)

    # -- run -----------------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        s = self.s
        self.files = self.model_files()
        base = self.model("0.50")
        require(base.input_size is not None, f"{base.path} declares no input size: the bench needs it to render views")
        self.height, self.width = (int(v) for v in base.input_size)
        self.results["settings"] = s.to_dict()
        self.results["machine"] = machine_info(self.device)
        self.results["models"] = {k: ({"file": _display_path(p), "sha256_16": _sha256(p)} if p is not None else None)
                                  for k, p in self.files.items()}
        self.results["image_size"] = [self.width, self.height]
        self.results["class_names"] = list(base.class_names)
        self.results["delta_px"] = DEFAULT_DELTA_PX if s.delta_px is None else s.delta_px
        self.results["scenes"] = [{"scene": a, "view": b} for a, b in scene_ids(s.plan_scenes)]
        for name, fn in (("throughput", self.stage_throughput), ("plans", self.stage_plans), ("certificates", self.stage_certificates),
                         ("shipped", lambda: stage_shipped(self)),
                         ("sigma", self.stage_sigma), ("partitions", self.stage_partitions), ("empirical", self.stage_empirical),
                         ("denoiser", self.stage_denoiser), ("scaling", self.stage_scaling)):
            t = time.perf_counter()
            self.log(f"stage {name} ...")
            self.results[name] = fn()
            self.stage_seconds[name] = time.perf_counter() - t
            self.log(f"stage {name} done in {self.stage_seconds[name]:.1f}s")
        self.results["stage_seconds"] = dict(self.stage_seconds)
        self.results["total_seconds"] = time.perf_counter() - self.t0
        self.results["machine"]["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
        return self.results

    # -- throughput ----------------------------------------------------------------------------
    def _throughput(self, fn, batch: int) -> dict[str, Any]:
        gen = torch.Generator(device=self.device).manual_seed(self.s.seed)
        x = torch.rand((batch, 3, self.height, self.width), generator=gen, device=self.device)
        fn(x)  # warm-up
        calls, t = 0, 0.0
        while calls < 3 * batch or t < 1.0:
            t1 = time.perf_counter()
            fn(x)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            t += time.perf_counter() - t1
            calls += batch
            if calls >= 20 * batch:
                break
        return {"calls": calls, "seconds": t, "calls_per_second": calls / t, "batch_size": batch}

    def stage_throughput(self) -> dict[str, Any]:
        model = self.model("0.50")
        out = {"classifier": self._throughput(lambda x: model(x).argmax(1), self.s.batch_size)}
        if self.files["denoiser"] is not None:
            self.denoiser = load_denoiser(self.files["denoiser"], device=self.device)
            den = self.denoiser
            out["denoiser+classifier"] = self._throughput(lambda x: model(den(x)).argmax(1), self.s.batch_size)
        else:
            self.denoiser = None
        self.pure_cps = out["classifier"]["calls_per_second"]
        self.log(f"classifier: {self.pure_cps:.0f} images/s at {self.width}x{self.height} (batch {self.s.batch_size})")
        return out

    # -- planning (Table 1) ----------------------------------------------------------------------
    def stage_plans(self) -> dict[str, Any]:
        s = self.s
        records, runs = [], []
        scenes = scene_ids(s.plan_scenes)
        for i, (scene, vi) in enumerate(scenes):
            need_dense = i < s.pws_plan_scenes or i < s.cert_scenes
            v = self.view(scene, vi, dense=need_dense)
            for axis in s.plan_axes:
                b = PAPER_RADIUS[axis]
                for method in PLAN_METHODS:
                    if method == "pws":
                        if not (i < s.pws_plan_scenes or (axis in s.cert_axes and i < s.cert_scenes)):
                            continue
                        cloud, cname = v.dense, "dense"
                    else:
                        cloud, cname = v.one_frame, "one_frame"
                    rec: dict[str, Any] = {"scene": scene, "view": vi, "class_name": v.class_name, "axis": axis, "radius": b,
                                           "method": method, "cloud": cname, "cloud_points": int(len(cloud))}
                    t = time.perf_counter()
                    try:
                        with PeakMemory(self.device) as mem:
                            plan = plan_partitions(cloud, v.intrinsics, axis, b, method, delta=s.delta_px, max_partitions=PLAN_CAP)
                        rec.update(num_partitions=int(plan.num_partitions), delta_alpha=float(plan.delta_alpha),
                                   lemma1_holds=plan.details.get("lemma1_holds"), min_run=plan.details.get("min_run"),
                                   seconds=time.perf_counter() - t, peak_bytes=mem.peak_bytes, window=plan.details.get("window"))
                        if i < s.cert_scenes and axis in s.cert_axes:
                            self.plans[(i, axis, method)] = plan
                    except PwsError as exc:
                        rec.update(num_partitions=None, error=str(exc), seconds=time.perf_counter() - t)
                    records.append(rec)
                    self.log(f"plan scene {scene} {axis} {method:6s} ({cname}, {len(cloud)} pts): "
                             f"N={rec.get('num_partitions')} in {rec['seconds']:.1f}s")
                if i < min(s.run_length_scenes, s.cert_scenes) and axis in s.run_length_axes and (i, axis, "pws") in self.plans:
                    plan = self.plans[(i, axis, "pws")]
                    t = time.perf_counter()
                    pts = v.dense.points[v.dense.points[:, 2] > 0]
                    r = consistent_runs(pts, v.intrinsics, axis, b, plan.details.get("window", 4.0))
                    lengths = np.sort(r.end - r.start)
                    q = {str(qq): float(np.quantile(lengths, qq)) for qq in RUN_QUANTILES} if len(lengths) else {}
                    runs.append({"scene": scene, "view": vi, "axis": axis, "radius": b, "num_runs": int(len(lengths)), "quantiles": q,
                                 "partitions_at_quantile": {k: int(2 * math.ceil(b / max(val, 1e-300)) + 1) if val > 0 else None
                                                            for k, val in q.items()},
                                 "seconds": time.perf_counter() - t})
        return {"records": records, "run_lengths": runs}

    # -- certification (Tables 2-3) ------------------------------------------------------------------
    def _certify_plan(self, cloud: Cloud, intr, plan: Plan, model: LoadedModel, cfg: CertifyConfig, denoiser=None,
                      rendered=None, plan_seconds: float = 0.0, with_anchors: bool = True) -> tuple[list[dict], Any]:
        """Pairwise certificate, paper rule from the same counts, and (optionally) anchors certificate."""
        if rendered is None:
            rendered = render_plan(cloud, intr, plan, background=cfg.background, device=str(self.device))
            render_s = rendered.seconds
        else:
            render_s = rendered.seconds
        out = []
        cert = certify_rendered(rendered, model, replace(cfg, coverage="pairwise"), denoiser=denoiser)
        for coverage in ("pairwise", "paper") + (("anchors",) if with_anchors else ()):
            if coverage == "anchors":
                cert = certify_rendered(rendered, model, replace(cfg, coverage="anchors", n=self.s.anchor_n), denoiser=denoiser)
            t = _timing(cert.timings)
            t["plan"] = plan_seconds
            t["render"] += render_s
            t["total"] += plan_seconds + render_s
            rec = {"coverage": coverage, "status": cert.status, "certified": bool(cert.certified), "radius": float(cert.radius),
                   "label": int(cert.label), "num_partitions": int(plan.num_partitions), "num_bounds": int(cert.num_bounds),
                   "classifier_calls": int(cert.classifier_calls), "frames_rendered": int(cert.frames_rendered),
                   "min_p_a_lower": float(cert.min_p_a_lower), "M": cert.bounds.get("M"), "R_min": cert.bounds.get("R_min"),
                   "segments_covered": cert.bounds.get("segments_covered"), "n": int(cert.n), "n0": int(cert.n0),
                   "sigma": float(cert.sigma), "timings": t, "capped_from": plan.details.get("capped_from"),
                   "refined_from": plan.details.get("refined_from"),
                   "lemma1_holds": plan.details.get("lemma1_holds")}
            if coverage == "paper":
                status, certified, radius = paper_rule(cert.p_a_lower, rendered.pair_bound_sq, plan.alphas, cfg.sigma)
                rec.update(status=status, certified=certified, radius=radius, shares_counts_with="pairwise")
                rec["segments_covered"] = None
            rec["overhead_ratio"] = t["total"] / (rec["classifier_calls"] / self.pure_cps) if rec["classifier_calls"] else None
            out.append(rec)
        return out, rendered

    def stage_certificates(self) -> list[dict]:
        s = self.s
        model = self.model("0.50")
        records = []
        for i, (scene, vi) in enumerate(scene_ids(s.cert_scenes)):
            v = self.view(scene, vi, dense=True)
            truth = self.true_index(v, model)
            for axis in s.cert_axes:
                b = PAPER_RADIUS[axis]
                head = {"scene": scene, "view": vi, "class_name": v.class_name, "true_label": truth, "axis": axis, "radius_requested": b}
                for method in CERT_METHODS:
                    plan = self.plans.get((i, axis, method))
                    cloud = v.dense if method == "pws" else v.one_frame
                    if plan is None:
                        for cov in COVERAGE_RULES:
                            records.append({**head, "method": method, "coverage": cov, "status": "error", "certified": False,
                                            "correct": False, "radius": 0.0, "error": "no plan (planning failed)"})
                        continue
                    cplan = capped_plan(plan, s.cert_max_partitions, s.cert_min_partitions)
                    try:
                        recs, rendered = self._certify_plan(cloud, v.intrinsics, cplan, model, self.config(),
                                                            plan_seconds=float(plan.details.get("plan_seconds", 0.0)))
                    except PwsError as exc:
                        recs, rendered = [{"coverage": c, "status": "error", "certified": False, "radius": 0.0, "label": -1,
                                           "error": str(exc)} for c in COVERAGE_RULES], None
                    if method == "pws_of" and rendered is not None:
                        self.rendered[(i, axis, method)] = rendered
                    for r in recs:
                        r.update(head, method=method, planned_partitions=int(plan.num_partitions))
                        r["correct"] = bool(r.get("label") == truth)
                        records.append(r)
                    pw = recs[0]
                    self.log(f"certify scene {scene} {axis} {method:6s}: N={pw.get('num_partitions')} "
                             f"(planned {plan.num_partitions}) pairwise={pw['status']} paper={recs[1]['status']} "
                             f"anchors={recs[-1]['status']} label={pw.get('label')}/{truth}")
                cfg = self.config(n0=s.cms_n0, n=s.cms_n)
                try:
                    cert = certify(v.dense, v.intrinsics, model, axis, b, method="cms", config=cfg)
                    t = _timing(cert.timings)
                    rec = {**head, "method": "cms", "coverage": "cms", "status": cert.status, "certified": bool(cert.certified),
                           "radius": float(cert.radius), "label": int(cert.label), "correct": bool(cert.label == truth),
                           "classifier_calls": int(cert.classifier_calls), "frames_rendered": int(cert.frames_rendered),
                           "min_p_a_lower": float(cert.min_p_a_lower), "n": int(cert.n), "n0": int(cert.n0), "sigma": float(cert.sigma),
                           "num_partitions": 0, "timings": t,
                           "overhead_ratio": t["total"] / (cert.classifier_calls / self.pure_cps) if cert.classifier_calls else None}
                except PwsError as exc:
                    rec = {**head, "method": "cms", "coverage": "cms", "status": "error", "certified": False, "radius": 0.0,
                           "correct": False, "error": str(exc)}
                records.append(rec)
                self.log(f"certify scene {scene} {axis} cms   : {rec['status']} R={rec['radius']:.4g} label={rec.get('label')}/{truth}")
        return records

    # -- ablations -----------------------------------------------------------------------------
    def stage_sigma(self) -> list[dict]:
        s = self.s
        records = []
        main = self.results["certificates"]
        for sigma in s.sigmas:
            key, note = self.classifier_for_sigma(sigma)
            if sigma == 0.5:
                for r in main:
                    if r["method"] == "pws_of" and r["coverage"] in ("pairwise", "paper"):
                        records.append({**r, "sigma": 0.5, "classifier": key, "note": note})
                continue
            model = self.model(key)
            for i, (scene, vi) in enumerate(scene_ids(s.cert_scenes)):
                v = self.view(scene, vi, dense=True)
                truth = self.true_index(v, model)
                for axis in s.cert_axes:
                    rendered = self.rendered.get((i, axis, "pws_of"))
                    head = {"scene": scene, "view": vi, "axis": axis, "radius_requested": PAPER_RADIUS[axis], "method": "pws_of",
                            "true_label": truth, "classifier": key, "note": note}
                    if rendered is None:
                        records.append({**head, "coverage": "pairwise", "sigma": sigma, "status": "error", "certified": False,
                                        "correct": False, "radius": 0.0, "error": "no rendered plan"})
                        continue
                    recs, _ = self._certify_plan(v.one_frame, v.intrinsics, rendered.plan, model, self.config(sigma=sigma),
                                                 rendered=rendered, with_anchors=False)
                    for r in recs:
                        r.update(head)
                        r["correct"] = bool(r["label"] == truth)
                        records.append(r)
                    self.log(f"sigma {sigma:g} scene {scene} {axis}: pairwise={recs[0]['status']} paper={recs[1]['status']}")
        return records

    def stage_partitions(self) -> list[dict]:
        s = self.s
        model = self.model("0.50")
        axis = s.partition_axis
        b = PAPER_RADIUS[axis]
        records = []
        for i, (scene, vi) in enumerate(scene_ids(s.cert_scenes)):
            v = self.view(scene, vi, dense=True)
            truth = self.true_index(v, model)
            for N in s.partition_counts:
                plan = grid_plan("pws_of", axis, b, N)
                recs, _ = self._certify_plan(v.one_frame, v.intrinsics, plan, model, self.config(), with_anchors=False)
                for r in recs:
                    r.update(scene=scene, view=vi, axis=axis, radius_requested=b, method="pws_of", true_label=truth, grid=int(N))
                    r["correct"] = bool(r["label"] == truth)
                    records.append(r)
                self.log(f"partitions N={N} scene {scene} {axis}: pairwise={recs[0]['status']} min p_A={recs[0]['min_p_a_lower']:.3f}")
        return records

    def stage_empirical(self) -> list[dict]:
        s = self.s
        model = self.model("0.50")
        records = []
        main = {(r["scene"], r["axis"]): r for r in self.results["certificates"] if r["method"] == "pws_of" and r["coverage"] == "pairwise"}
        for i, (scene, vi) in enumerate(scene_ids(s.cert_scenes)):
            v = self.view(scene, vi, dense=True)
            truth = self.true_index(v, model)
            for k, axis in enumerate(s.cert_axes):
                b = PAPER_RADIUS[axis]
                rng = np.random.default_rng([s.seed, scene, k, 7])
                alphas = rng.uniform(-b, b, size=s.empirical_perturbations)
                t = time.perf_counter()
                r = Renderer(v.one_frame, v.intrinsics, axis, background=s.background, device=self.device)
                frames = r.render_batch(np.concatenate([[0.0], alphas]))
                sc = SmoothedClassifier(model, 0.5, batch_size=s.batch_size, seed=s.seed + 1 + i)
                counts = sc.sample_counts(frames, s.empirical_n)
                preds = counts.argmax(dim=1).numpy()
                clean = int(sc.predict(frames[:1])[0])
                cert = main.get((scene, axis), {})
                rec = {"scene": scene, "view": vi, "axis": axis, "radius_requested": b, "true_label": truth,
                       "benign_correct": bool(preds[0] == truth), "clean_correct": bool(clean == truth),
                       "robust_correct": bool(np.all(preds == truth)), "perturbed_correct_fraction": float(np.mean(preds[1:] == truth)),
                       "certified_correct": bool(cert.get("certified") and cert.get("correct")),
                       "classifier_calls": int(sc.calls), "seconds": time.perf_counter() - t, "num_perturbations": len(alphas)}
                records.append(rec)
                self.log(f"empirical scene {scene} {axis}: benign={rec['benign_correct']} robust={rec['robust_correct']} "
                         f"certified={rec['certified_correct']}")
        return records

    def stage_denoiser(self) -> list[dict]:
        s = self.s
        records = []
        if self.denoiser is None:
            return [{"error": f"{self.models_dir} has no denoiser_sigma0.50.pt"}]
        for key in s.denoiser_classifiers:
            if self.files.get(key) is None:
                records.append({"classifier": key, "error": f"no classifier_sigma{key}.pt"})
                continue
            model = self.model(key)
            for use in (False, True):
                for i, (scene, vi) in enumerate(scene_ids(s.cert_scenes)):
                    v = self.view(scene, vi, dense=True)
                    truth = self.true_index(v, model)
                    for axis in s.denoiser_axes:
                        rendered = self.rendered.get((i, axis, "pws_of"))
                        if rendered is None:
                            continue
                        recs, _ = self._certify_plan(v.one_frame, v.intrinsics, rendered.plan, model, self.config(n=s.denoiser_n),
                                                     denoiser=self.denoiser if use else None, rendered=rendered, with_anchors=False)
                        for r in recs:
                            r.update(scene=scene, view=vi, axis=axis, radius_requested=PAPER_RADIUS[axis], method="pws_of",
                                     true_label=truth, classifier=key, denoiser=use)
                            r["correct"] = bool(r["label"] == truth)
                            records.append(r)
                        self.log(f"denoiser={use} classifier {key} scene {scene} {axis}: pairwise={recs[0]['status']}")
        return records

    # -- scaling -------------------------------------------------------------------------------
    def _scaled_cert(self, cloud, intr, model, axis, b, method, plan) -> dict[str, Any]:
        cfg = self.config(n0=self.s.scaling_n, n=self.s.scaling_n)
        with PeakMemory(self.device) as mem:
            cert = certify(cloud, intr, model, axis, b, method=method, config=cfg, plan=plan)
        return {"timings": _timing(cert.timings), "classifier_calls": int(cert.classifier_calls), "num_partitions": int(cert.num_partitions),
                "frames_rendered": int(cert.frames_rendered), "peak_bytes": mem.peak_bytes, "cuda_peak_bytes": mem.cuda_peak_bytes,
                "status": cert.status}

    def stage_scaling(self) -> dict[str, Any]:
        s = self.s
        model = self.model("0.50")
        axis = s.scaling_axis
        b = PAPER_RADIUS[axis]
        scene, vi = scene_ids(1)[0]
        v = self.view(scene, vi, dense=True)
        out: dict[str, Any] = {"scene": scene, "view": vi, "axis": axis, "radius": b, "n": s.scaling_n, "n0": s.scaling_n}
        rows = []
        for N in s.scaling_partitions:
            rec = self._scaled_cert(v.one_frame, v.intrinsics, model, axis, b, "pws_of", grid_plan("pws_of", axis, b, N))
            rec.update(num_partitions=int(N), cloud_points=int(len(v.one_frame)))
            rows.append(rec)
            self.log(f"scaling N={N}: {rec['timings']['total']:.2f}s peak {self._mb(rec['peak_bytes'])}")
        out["vs_partitions"] = rows
        rows = []
        any_model = LoadedModel(module=model.module, class_names=list(model.class_names), input_size=None, path=model.path,
                                meta=dict(model.meta), device=model.device)
        sizes = list(s.scaling_sizes) or [(self.width, self.height)]
        n_fixed = s.scaling_partitions[min(1, len(s.scaling_partitions) - 1)]
        for (w, h) in sizes:
            rec: dict[str, Any] = {"width": int(w), "height": int(h), "num_partitions": int(n_fixed)}
            try:
                vv = self.view(scene, vi, dense=False, width=w, height=h) if (w, h) != (self.width, self.height) else v
                t = time.perf_counter()
                with PeakMemory(self.device) as mem:
                    plan = plan_partitions(vv.one_frame, vv.intrinsics, axis, b, "pws_of", delta=s.delta_px, max_partitions=PLAN_CAP)
                rec.update(plan_seconds=time.perf_counter() - t, plan_peak_bytes=mem.peak_bytes, planned_partitions=int(plan.num_partitions),
                           cloud_points=int(len(vv.one_frame)))
                rec.update(self._scaled_cert(vv.one_frame, vv.intrinsics, any_model, axis, b, "pws_of", grid_plan("pws_of", axis, b, n_fixed)))
            except PwsError as exc:
                rec["error"] = str(exc)
            rows.append(rec)
            self.log(f"scaling size {w}x{h}: {rec.get('timings', {}).get('total', float('nan')):.2f}s {rec.get('error', '')}")
        out["vs_image_size"] = rows
        rows = []
        dense = v.dense
        full_plan = next((r for r in self.results["plans"]["records"] if r["scene"] == scene and r["axis"] == axis and r["method"] == "pws"), None)
        for f in s.scaling_cloud_fractions:
            rng = np.random.default_rng([s.seed, 99, int(f * 1e6)])
            k = max(1, int(round(f * len(dense))))
            idx = np.sort(rng.choice(len(dense), size=k, replace=False)) if k < len(dense) else np.arange(len(dense))
            sub = Cloud(dense.points[idx], dense.colors[idx])
            rec = {"fraction": float(f), "cloud_points": int(k), "num_partitions": int(n_fixed)}
            if f == 1.0 and full_plan is not None and full_plan.get("num_partitions") is not None:
                rec.update(plan_seconds=full_plan["seconds"], plan_peak_bytes=full_plan.get("peak_bytes"),
                           planned_partitions=full_plan["num_partitions"], plan_reused=True)
            else:
                t = time.perf_counter()
                try:
                    with PeakMemory(self.device) as mem:
                        plan = plan_partitions(sub, v.intrinsics, axis, b, "pws", max_partitions=PLAN_CAP)
                    rec.update(plan_seconds=time.perf_counter() - t, plan_peak_bytes=mem.peak_bytes, planned_partitions=int(plan.num_partitions))
                except PwsError as exc:
                    rec.update(plan_seconds=time.perf_counter() - t, plan_error=str(exc))
            rec.update(self._scaled_cert(sub, v.intrinsics, model, axis, b, "pws", grid_plan("pws", axis, b, n_fixed)))
            rows.append(rec)
            self.log(f"scaling cloud {k} pts: plan {rec.get('plan_seconds', float('nan')):.1f}s, certify {rec['timings']['total']:.2f}s")
        out["vs_cloud_size"] = rows
        return out

    @staticmethod
    def _mb(b) -> str:
        return "?" if b is None else f"{b / 2**20:.1f} MiB"
