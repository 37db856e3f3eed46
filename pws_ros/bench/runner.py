"""The measurements of ``pws bench``: every figure is measured in this process, on the same scenes
and with the same classifier, and recorded with the settings that produced it.

Stages (each a list of plain records in ``results``):

* ``throughput``: pure classifier (and denoiser + classifier) images per second on noise batches;
* ``plans``: the Table 1 analogue, planning only (PwS on the entire dense cloud, PwS-L and PwS-OF on
  the one-frame cloud), with the dense cloud's consistent-run quantiles;
* ``certificates``: PwS / PwS-L / PwS-OF under the paper, pairwise and anchors coverage rules, and CMS,
  at the paper's radii; the paper rule is read from the pairwise run's own bounds (same counts);
* ``sigma``, ``partitions``, ``empirical``, ``denoiser``: the ablations;
* ``shipped``: PwS-OF with the shipped defaults on a 640x480 camera, beside CMS (:mod:`.shipped`);
* ``scaling``: time and peak memory against the number of partitions, the image size and the cloud size.

The ablation and scaling stages live in :mod:`.ablations`, the grids in :mod:`.grids`, the machine
record and peak memory in :mod:`.machine`.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..core.certify import CertifyConfig, certify, certify_rendered
from ..core.coverage import COVERAGES
from ..core.bounds import render_plan
from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.model import LoadedModel, load_denoiser, load_model
from ..core.motion import PAPER_RADIUS
from ..core.partition import DEFAULT_DELTA_PX, Plan, consistent_runs, plan_partitions
from ..core.render import resolve_device
from .settings import BenchSettings, scene_ids
from .ablations import Ablations
from .grids import PLAN_CAP, capped_plan, paper_rule, timing_of
from .machine import PeakMemory, display_path, machine_info, sha256_16
from .shipped import stage_shipped

RUN_QUANTILES = (0.0, 1e-4, 1e-3, 1e-2, 0.5)
PLAN_METHODS = ("pws", "pws_l", "pws_of")
CERT_METHODS = ("pws", "pws_l", "pws_of")


# ------------------------------------------------------------------------------------------------
class Bench(Ablations):
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
        self.results["models"] = {k: ({"file": display_path(p), "sha256_16": sha256_16(p)} if p is not None else None)
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
            t = timing_of(cert.timings)
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
                        for cov in COVERAGES:
                            records.append({**head, "method": method, "coverage": cov, "status": "error", "certified": False,
                                            "correct": False, "radius": 0.0, "error": "no plan (planning failed)"})
                        continue
                    cplan = capped_plan(plan, s.cert_max_partitions, s.cert_min_partitions)
                    try:
                        recs, rendered = self._certify_plan(cloud, v.intrinsics, cplan, model, self.config(),
                                                            plan_seconds=float(plan.details.get("plan_seconds", 0.0)))
                    except PwsError as exc:
                        recs, rendered = [{"coverage": c, "status": "error", "certified": False, "radius": 0.0, "label": -1,
                                           "error": str(exc)} for c in COVERAGES], None
                    if method == "pws_of" and rendered is not None:
                        self.rendered[(i, axis, method)] = rendered
                    self._record_all(records, recs, truth, **head, method=method, planned_partitions=int(plan.num_partitions))
                    pw = recs[0]
                    self.log(f"certify scene {scene} {axis} {method:6s}: N={pw.get('num_partitions')} "
                             f"(planned {plan.num_partitions}) pairwise={pw['status']} paper={recs[1]['status']} "
                             f"anchors={recs[-1]['status']} label={pw.get('label')}/{truth}")
                cfg = self.config(n0=s.cms_n0, n=s.cms_n)
                try:
                    cert = certify(v.dense, v.intrinsics, model, axis, b, method="cms", config=cfg)
                    t = timing_of(cert.timings)
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

