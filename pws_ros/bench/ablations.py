"""The ablations and scaling stages of ``pws bench`` (a mixin of :class:`.runner.Bench`)."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..core.certify import certify
from ..core.cloud import Cloud
from ..core.errors import PwsError
from ..core.model import LoadedModel
from ..core.motion import PAPER_RADIUS
from ..core.partition import plan_partitions
from ..core.render import Renderer
from ..core.smoothing import SmoothedClassifier
from .settings import scene_ids
from .grids import PLAN_CAP, grid_plan, timing_of
from .machine import PeakMemory


class Ablations:
    """σ, partitions, empirical robustness, denoiser and scaling stages (need the Bench's models, views, plans)."""

    @staticmethod
    def _record_all(records: list[dict], recs: list[dict], truth: int, **fields: Any) -> None:
        """Append certificate records to ``records`` with ``fields`` and ``correct`` (label == truth)."""
        for r in recs:
            r.update(fields)
            r["correct"] = bool(r.get("label") == truth)
            records.append(r)

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
                    self._record_all(records, recs, truth, **head)
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
                self._record_all(records, recs, truth, scene=scene, view=vi, axis=axis, radius_requested=b, method="pws_of",
                                 true_label=truth, grid=int(N))
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
                        self._record_all(records, recs, truth, scene=scene, view=vi, axis=axis, radius_requested=PAPER_RADIUS[axis],
                                         method="pws_of", true_label=truth, classifier=key, denoiser=use)
                        self.log(f"denoiser={use} classifier {key} scene {scene} {axis}: pairwise={recs[0]['status']}")
        return records

    # -- scaling -------------------------------------------------------------------------------
    def _scaled_cert(self, cloud, intr, model, axis, b, method, plan) -> dict[str, Any]:
        cfg = self.config(n0=self.s.scaling_n, n=self.s.scaling_n)
        with PeakMemory(self.device) as mem:
            cert = certify(cloud, intr, model, axis, b, method=method, config=cfg, plan=plan)
        return {"timings": timing_of(cert.timings), "classifier_calls": int(cert.classifier_calls), "num_partitions": int(cert.num_partitions),
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
