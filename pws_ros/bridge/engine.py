"""``FrameCertifier``: the ROS-free per-frame pipeline (plan, render, certify every configured axis).

Used by the ``pipeline`` node (everything in memory), by the four nodes of the four-process mode
(each calls its own stage: :meth:`FrameCertifier.plan_bundle`, :meth:`FrameCertifier.render_axis`,
:meth:`FrameCertifier.certify_assembled`), by ``pws replay`` and by the benchmarks.

The cloud stays metric in the camera optical frame; frames are made by the imaging model of
:mod:`pws_ros.core.imaging` (``imaging``: ``surfel`` renders a centred crop of the camera at its native
resolution and block-averages it to the model's input size; ``paper`` rescales the camera to the
model's input size, or ``render_width x render_height``). One :class:`~pws_ros.core.imaging.Imaging`
per frame serves every axis (its masked border is computed from all the frame's radii; a time budget's
coarser level renders an axis at render factor 1, :mod:`pws_ros.bridge.sizing`).

Risk and noise: the frame's statement (every axis together) holds with probability at least
``1 - alpha``: each of the ``A`` axes spends ``alpha / A`` (Bonferroni), recorded in each certificate as
``alpha`` (per axis) and ``frame_alpha``; each axis draws its noise from its own seed derived from
(seed, stamp, axis) (:func:`~pws_ros.core.smoothing.derive_seed`). The model (and denoiser, and the dense cloud of method ``pws``) is
loaded once. A ``cuda:N`` device that is not available falls back to the CPU with a warning sent to
``log``. Any failure of one axis becomes an ERROR certificate for that axis (never an exception):
one bad axis or frame never stops a node. The axes of a frame run at the same time, each in a thread of its own,
where ``axis_threads`` and the cores allow (:mod:`.axis_threads`; one after another with a time
budget): each has its own renderer, plan and seed, so its certificate is the same either way.

The decisions on how much work a frame gets (the batch size of classifier calls, the time budget's
warm-ups, sizes and coarser geometry) are :mod:`pws_ros.bridge.sizing`'s (``FrameCertifier.budget``).
"""
from __future__ import annotations

import math
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.motion import UNITS
from ..core.result import Certificate, error_certificate
from ..core.volume import volume_text
from .config import PwsConfig, check_consistency, resolve_path
from .preview import render_previews
from .scheme import PlanBundle, rendered_plan_from_parts
from .selfaudit import audit_certificate
from .assembly import AssembledFrame
from .axis_threads import at_once, axis_imports, axis_workers
from .budget import Sizes
from .sizing import COARSE_FACTOR, FrameBudget, LogFn, size_advice


def _default_log(level: str, message: str) -> None:
    import sys

    print(f"[pws {level}] {message}", file=sys.stderr)


def resolve_device_with_fallback(device: str, log: LogFn | None = None) -> str:
    """``device`` if usable, else ``"cpu"`` with a warning (``cuda:N`` without CUDA or that GPU)."""
    import torch

    dev = (device or "cpu").strip()
    if dev.startswith("cuda"):
        why = ""
        if not torch.cuda.is_available():
            why = "CUDA is not available"
        else:
            try:
                index = torch.device(dev).index
            except (RuntimeError, TypeError):
                raise PwsError(f"invalid device {device!r}: expected cpu or cuda:N") from None
            if index is not None and index >= torch.cuda.device_count():
                why = f"only {torch.cuda.device_count()} CUDA device(s) exist"
        if why:
            (log or _default_log)("warn", f"device {dev} requested but {why}; falling back to cpu")
            return "cpu"
        return dev
    require(dev == "cpu", f"invalid device {device!r}: expected cpu or cuda:N")
    return dev


def filled_drawn(cloud: Cloud, imaging: Any) -> int:
    """How many of the points the imaging draws have a filled depth: ``cloud.filled``; none with a working
    volume, which draws measured points only (where the cloud says which points were filled)."""
    if getattr(imaging, "volume", None) is None or cloud.filled_mask is None:
        return int(cloud.filled)
    return 0


@dataclass
class FrameResult:
    """The outcome of one input frame: one certificate per configured axis (in config order)."""

    stamp_ns: int
    frame_id: str
    certificates: list[Certificate]
    plans: dict[str, Any] = field(default_factory=dict)        # axis -> core.partition.Plan (absent if planning failed)
    camera: CameraIntrinsics | None = None                     # the render camera
    timings: dict[str, float] = field(default_factory=dict)    # seconds: total, and "<axis>" per axis
    previews: list[tuple[str, int, np.ndarray]] = field(default_factory=list)  # (axis, index, uint8 RGB)
    imaging: Any = None                                        # the frame's core.imaging.Imaging (None: none was made)

    @property
    def compute_ms(self) -> dict[str, float]:
        return {a: 1000.0 * self.timings.get(a, float("nan")) for a in (c.axis for c in self.certificates)}


class FrameCertifier:
    """Certify frames against camera motion on every configured axis.

    ``model``, ``denoiser`` and ``dense_cloud`` may be given (tests, replay); otherwise they are
    loaded from ``config.model_path`` / ``denoiser_path`` / ``dense_cloud_path`` when first needed
    (``load=True`` loads them now, so a bad path fails at start-up with PwsError).
    """

    def __init__(self, config: PwsConfig, *, log: LogFn | None = None, model: Any = None, denoiser: Any = None,
                 dense_cloud: Cloud | None = None, load: bool = True):
        check_consistency(config)
        self.config = config
        self.log: LogFn = log or _default_log
        self.device = resolve_device_with_fallback(config.device, self.log)
        self.device_warning = "" if self.device == config.device else f"{config.device} unavailable, using cpu"
        self._model = model
        self._denoiser = denoiser
        self._dense = dense_cloud
        self._lock = threading.Lock()
        self._aspect_warned = False       # paper imaging: the aspect-ratio warning was given
        self._axes_warned: set[tuple[str, ...]] = set()   # four-process: planners' axes other than this node's, named once
        # surfel imaging: its description and memory estimate are logged at the first frame, and again when a
        # parameter change gives it another working volume, background or uncovered rule
        self._imaging_described: tuple | None = None
        self._sigma_checked: float | None = None
        self.batch_size = int(config.batch_size)   # images per classifier call: the configured, or a faster smaller one
        self._frames_seen = 0
        self.budget = FrameBudget(self)   # time_budget_s: the cost model and each axis' work (bridge.sizing)
        if load:
            self.model  # noqa: B018 - load now
            self.denoiser  # noqa: B018
            if config.method == "pws":
                self.dense_cloud  # noqa: B018
            if self.render_size is not None:
                self.check_batch_size(self.render_size)   # at start, not in the first frame's time
            if config.time_budget_s > 0 and getattr(self._model, "input_size", None) is not None:
                self.budget.warm_up_inference(tuple(self._model.input_size))

    # ---- lazily loaded resources ----
    @property
    def model(self) -> Any:
        with self._lock:
            if self._model is None:
                from ..core.model import load_model

                path = resolve_path(self.config.model_path, "model file")
                classes = str(resolve_path(self.config.classes_path, "class file")) if self.config.classes_path else None
                self._model = load_model(path, classes=classes, device=self.device)
                self.log("info", f"loaded model {path} ({len(self._model.class_names)} classes, input "
                                 f"{self._model.input_size or 'any size'}) on {self.device}")
            return self._model

    @property
    def denoiser(self) -> Any:
        with self._lock:
            if self._denoiser is None and self.config.denoiser_path:
                from ..core.model import load_denoiser

                self._denoiser = load_denoiser(resolve_path(self.config.denoiser_path, "denoiser file"), device=self.device)
            return self._denoiser

    @property
    def dense_cloud(self) -> Cloud | None:
        with self._lock:
            if self._dense is None and self.config.dense_cloud_path:
                self._dense = Cloud.load(resolve_path(self.config.dense_cloud_path, "dense cloud file"))
                self.log("info", f"loaded dense cloud {self.config.dense_cloud_path} ({len(self._dense)} points)")
            return self._dense

    @property
    def render_size(self) -> tuple[int, int] | None:
        """(H, W) of rendered frames: ``render_height x render_width`` if set, else the model's input size."""
        if self.config.render_width > 0 and self.config.render_height > 0:
            return (self.config.render_height, self.config.render_width)
        size = getattr(self.model, "input_size", None)
        return (int(size[0]), int(size[1])) if size is not None else None

    def imaging_for(self, intr: CameraIntrinsics, cloud: Cloud | None = None, render_factor: int | None = None) -> Any:
        """The :class:`~pws_ros.core.imaging.Imaging` of one frame (its border from all configured radii);
        ``render_factor`` (a time budget's coarser level) replaces the configured one."""
        from ..core.imaging import make_imaging

        c = self.config
        size = self.render_size
        if c.imaging == "paper" and size is not None and not self._aspect_warned:
            src, dst = intr.width / intr.height, size[1] / size[0]
            if abs(src - dst) > 0.01 * src:
                self._aspect_warned = True
                self.log("warn", f"camera {intr.width}x{intr.height} is rendered at {size[1]}x{size[0]}: the aspect ratio changes "
                                 f"(fx and fy are scaled differently; imaging: surfel crops instead)")
        im = make_imaging(c.imaging, intr, size, background=c.background_value, border=c.border, cloud=cloud, radii=c.radii,
                          render_factor=c.render_factor if render_factor is None else int(render_factor),
                          uncovered=c.uncovered, volume=c.working_volume)
        if render_factor is None and im.kind == "surfel" and self._imaging_described != (c.working_volume, im.background, im.uncovered):
            self._imaging_described = (c.working_volume, im.background, im.uncovered)   # a window's volume is per frame: once
            from ..core.certify import grid_cap, segment_bytes

            fit = grid_cap(im, self.certify_config())
            together = self.axis_workers(self.budget.on)
            self.log("info", f"{im.describe()}; memory per axis: frames and bounds of at most {fit} segments x "
                             f"{segment_bytes(im) / 2**20:.2f} MiB = {fit * segment_bytes(im) / 2**20:.0f} MiB "
                             f"(max_memory_mb {c.max_memory_mb:g}), the renderer streams in chunks"
                             + (f"; {together} axes at once (axis_threads)" if together > 1 else ""))
            for text in size_advice(im, self.batch_size):
                self.log("warn", text)
        return im

    def certify_config(self, axis: str | None = None, stamp_ns: int = 0, sizes: Sizes | None = None,
                       num_axes: int | None = None):
        """The core's CertifyConfig; for an axis of a frame: ``alpha / len(axes)`` (``num_axes``: the axes the
        frame's statement covers, where they are not the configured ones) and the derived seed; with ``sizes``
        (a time budget, :mod:`.budget`): their ``n0``, ``num_anchors``, ``n``, ``max_partitions`` and
        ``frontier_rounds``."""
        from dataclasses import replace

        from ..core.smoothing import derive_seed

        self._check_sigma()
        cfg = replace(self.config.certify_config(), device=self.device, batch_size=self.batch_size)
        if axis is not None:
            cfg = replace(cfg, alpha=self.config.alpha / max(1, len(self.config.axes) if num_axes is None else int(num_axes)),
                          seed=derive_seed(self.config.seed, int(stamp_ns), axis))
        if sizes is not None and sizes.reduced:
            # a budget that shrank the work: what it sized is spent (core.certify_common.CertifyConfig.spread_estimation)
            cfg = replace(cfg, spread_estimation=True, n0=int(sizes.n0), num_anchors=int(sizes.num_anchors), n=int(sizes.n),
                          max_partitions=int(sizes.max_partitions), min_partitions=min(int(cfg.min_partitions), int(sizes.max_partitions)))
        if sizes is not None:   # a coarser level (budget.Level): its frontier rounds and render factor
            cfg = replace(cfg, frontier_rounds=int(sizes.frontier_rounds),
                          render_factor=COARSE_FACTOR if sizes.coarse else cfg.render_factor)
        return cfg

    def axis_workers(self, budgeted: bool = False) -> int:
        """How many of a frame's axes :meth:`process` certifies at the same time (:func:`.axis_threads.axis_workers`)."""
        return axis_workers(len(self.config.axes), int(self.config.axis_threads), budgeted)

    def _stamp(self, cert: Certificate) -> Certificate:
        cert.frame_alpha = float(self.config.alpha)
        return cert

    def check_batch_size(self, shape: tuple[int, int]) -> float:
        """Once: the batch size of this engine's classifier calls (:meth:`.sizing.FrameBudget.check_batch_size`)."""
        return self.budget.check_batch_size(shape)

    def _check_sigma(self) -> None:
        """Warn (once per value) when the pixel noise sigma differs from the sigma the model's
        metadata says it was trained with: still sound, but p_A and the radii will likely suffer."""
        sigma = float(self.config.sigma)
        if self.config.method == "cms" or sigma == self._sigma_checked:
            return
        self._sigma_checked = sigma
        trained = (getattr(self.model, "meta", None) or {}).get("sigma")
        if isinstance(trained, (int, float)) and not math.isclose(float(trained), sigma, rel_tol=1e-6):
            self.log("warn", f"sigma {sigma:g} differs from the noise sigma {float(trained):g} the model was trained with "
                             f"({self.config.model_path}): certificates stay sound, but expect a smaller p_A and radius "
                             f"or abstentions")

    # ---- helpers ----
    def error_for(self, axis: str, reason: str, **kw: Any) -> Certificate:
        """An ERROR certificate for ``axis`` carrying this config's settings."""
        c = self.config
        return error_certificate(axis, UNITS[axis], c.method, c.coverage, c.radius_for(axis), reason,
                                 sigma=c.sigma, n0=c.n0, n=c.n, alpha=c.alpha / max(1, len(c.axes)), seed=c.seed,
                                 imaging=c.imaging, frame_alpha=c.alpha, working_volume=volume_text(c.working_volume), **kw)

    def _guard(self, axis: str, fn: Callable[[], Certificate]) -> Certificate:
        try:
            return fn()
        except PwsError as exc:
            return self.error_for(axis, str(exc))
        except Exception as exc:  # never let one axis kill the node
            self.log("error", f"axis {axis}: unexpected {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            return self.error_for(axis, f"internal error ({type(exc).__name__}): {' '.join(str(exc).split())[:200]}")

    def source_cloud(self, cloud: Cloud, dense_cloud: Cloud | None = None) -> Cloud:
        """The cloud planned and rendered from: the dense scene cloud for ``pws``, else the frame's."""
        if self.config.method == "pws":
            dense = dense_cloud if dense_cloud is not None else self.dense_cloud
            require(dense is not None, "method pws needs the entire scene cloud: set dense_cloud_path")
            return dense
        return cloud

    # ---- stage 1: plan ----
    def plan_axis(self, cloud: Cloud, imaging: Any, axis: str, max_partitions: int | None = None) -> Any:
        """The plan of one axis; ``max_partitions`` (a time budget's) replaces the configured cap."""
        from ..core.imaging import plan_for

        c = self.config
        require(c.method != "cms", "method cms has no partition plan")
        cap = int(c.max_partitions if max_partitions is None else max_partitions)
        return plan_for(cloud, imaging, axis, c.radius_for(axis), c.method, step_px=c.step_px,
                        delta=c.delta if c.delta > 0 else None, max_partitions=cap,
                        min_partitions=min(int(c.min_partitions), cap))

    def anchor_grid(self, cloud: Cloud, imaging: Any, plan: Any, stamp_ns: int = 0) -> Any:
        """The plan the four-process projector renders: with surfel imaging and ``coverage: anchors``
        refined for the certifier's adaptive anchors (:func:`~pws_ros.core.anchored.anchor_grid`, at the
        axis' own ``alpha``), else ``plan``."""
        from ..core.certify import anchor_grid

        return anchor_grid(cloud, imaging, plan, self.certify_config(plan.axis, stamp_ns))

    def plan_bundle(self, cloud: Cloud, intr: CameraIntrinsics, stamp_ns: int, frame_id: str = "",
                    dense_cloud: Cloud | None = None) -> PlanBundle:
        """Every axis' plan for one frame (errors per axis are recorded, not raised); the grids are those
        the projector renders (:meth:`anchor_grid`)."""
        try:
            imaging = self.imaging_for(intr, cloud)
        except PwsError as exc:
            bundle = PlanBundle(int(stamp_ns), frame_id or intr.frame_id, self.config.method, intr, list(self.config.axes))
            bundle.errors = {a: str(exc) for a in bundle.axes}
            return bundle
        bundle = PlanBundle(int(stamp_ns), frame_id or intr.frame_id, self.config.method, imaging.camera,
                            list(self.config.axes), imaging=imaging, filled_points=filled_drawn(cloud, imaging))
        if self.config.method == "cms":
            for a in bundle.axes:
                bundle.errors[a] = "method cms is only available in the pipeline node (it samples random poses inside the certifier)"
            return bundle
        try:
            src = self.source_cloud(cloud, dense_cloud)
        except PwsError as exc:
            bundle.errors = {a: str(exc) for a in bundle.axes}
            return bundle
        for a in bundle.axes:
            try:
                bundle.plans[a] = self.anchor_grid(src, imaging, self.plan_axis(src, imaging, a), stamp_ns)
            except PwsError as exc:
                bundle.errors[a] = str(exc)
            except Exception as exc:
                self.log("error", f"planning {a}: unexpected {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
                bundle.errors[a] = f"internal error ({type(exc).__name__}): {' '.join(str(exc).split())[:200]}"
        return bundle

    # ---- stage 2: render ----
    def render_axis(self, cloud: Cloud, imaging: Any, plan: Any, dense_cloud: Cloud | None = None) -> Any:
        """The :class:`~pws_ros.core.bounds.RenderedPlan` of one plan (frames + per-segment bounds).
        ``imaging``: the bundle's :class:`~pws_ros.core.imaging.Imaging` (a camera means paper imaging)."""
        from ..core.bounds import render_plan
        from ..core.imaging import Imaging, render_plan_surfel

        if isinstance(imaging, Imaging) and imaging.kind == "surfel":
            return render_plan_surfel(self.source_cloud(cloud, dense_cloud), imaging, plan, device=self.device)
        cam = imaging.camera if isinstance(imaging, Imaging) else imaging
        return render_plan(self.source_cloud(cloud, dense_cloud), cam, plan, background=self.config.background_value, device=self.device)

    # ---- stage 3: certify ----
    def certify_rendered(self, rendered: Any, stamp_ns: int = 0, imaging: Any = None, num_axes: int | None = None) -> Certificate:
        """Certify received frames and bounds; ``imaging`` (the bundle's) is recorded as the pipeline does;
        ``num_axes``: the axes of the frame's statement (:meth:`certify_config`)."""
        from ..core.certify import certify_rendered

        self.check_batch_size(tuple(rendered.frames.shape[1:3]))
        cert = certify_rendered(rendered, self.model, self.certify_config(rendered.plan.axis, stamp_ns, num_axes=num_axes),
                                denoiser=self.denoiser)
        cert.imaging = str(rendered.plan.details.get("imaging", self.config.imaging))
        if imaging is not None:
            cert.bounds["imaging"] = imaging.to_dict()
            cert.working_volume = volume_text(getattr(imaging, "volume", None))
        return self._stamp(cert)

    def certify_assembled(self, frame: AssembledFrame) -> FrameResult:
        """Certify what the four-process certifier assembled (``frame.info`` is the PlanBundle). The frame's
        statement covers the axes the planner sent, whatever this node's ``axes``: each gets ``alpha`` divided by
        their number (a planner configured with other axes is named in a warning, once per set of axes)."""
        t0 = time.perf_counter()
        bundle: PlanBundle | None = frame.info
        certs, timings, plans = [], {}, {}
        names = tuple(ax.axis for ax in frame.axes)
        if set(names) != set(self.config.axes) and names not in self._axes_warned:
            self._axes_warned.add(names)
            self.log("warn", f"the planner sent axes {', '.join(names)}, this certifier is configured for "
                             f"{', '.join(self.config.axes)}: the frame's alpha {self.config.alpha:g} is split over the "
                             f"{len(names)} axes certified (set the same axes on both nodes)")
        for ax in frame.axes:
            t1 = time.perf_counter()
            if not ax.ok:
                certs.append(self.error_for(ax.axis, ax.error))
            elif bundle is None or ax.axis not in bundle.plans:
                certs.append(self.error_for(ax.axis, "no plan for this axis"))
            else:
                plan = bundle.plans[ax.axis]
                plans[ax.axis] = plan
                certs.append(self._guard(ax.axis, lambda: self.certify_rendered(rendered_plan_from_parts(plan, ax.frames, ax.bounds),
                                                                                frame.stamp_ns, bundle.imaging, len(names))))
            if bundle is not None:
                certs[-1].filled_points = int(bundle.filled_points)   # as the pipeline: about the cloud with filled depth
            timings[ax.axis] = time.perf_counter() - t1
        timings["total"] = time.perf_counter() - t0
        return FrameResult(frame.stamp_ns, bundle.frame_id if bundle else "", certs, plans, bundle.camera if bundle else None, timings,
                           imaging=bundle.imaging if bundle else None)

    # ---- all stages in memory ----
    def certify_axis(self, cloud: Cloud, imaging: Any, axis: str, dense_cloud: Cloud | None = None,
                     preview_every: int = 0, previews: list | None = None, plans: dict | None = None,
                     stamp_ns: int = 0, sizes: Sizes | None = None) -> Certificate:
        """Plan, render and certify one axis with the core's ``certify`` (frames are never all kept in
        memory). ``imaging`` is the frame's :class:`~pws_ros.core.imaging.Imaging`; ``sizes`` (a time
        budget's, fixed before any sample is drawn) replace n0, num_anchors, n and max_partitions. Never
        raises: failures are ERROR certificates."""
        from ..core.certify import certify

        c = self.config
        intr = imaging.source or imaging.camera
        if c.method == "cms":
            return self._guard(axis, lambda: self._stamp(certify(cloud, intr, self.model, axis, c.radius_for(axis), method="cms",
                                                                 config=self.certify_config(axis, stamp_ns),
                                                                 denoiser=self.denoiser, imaging=imaging)))
        config = self.certify_config(axis, stamp_ns, sizes)

        def run() -> Certificate:
            t0 = time.perf_counter()
            src = self.source_cloud(cloud, dense_cloud)
            plan = (self.plan_axis(src, imaging, axis) if config.max_partitions == c.max_partitions
                    else self.plan_axis(src, imaging, axis, max_partitions=config.max_partitions))
            if plans is not None:
                plans[axis] = plan
            t_plan = time.perf_counter() - t0
            cert = certify(src, intr, self.model, axis, c.radius_for(axis), method=c.method,
                           config=config, denoiser=self.denoiser, plan=plan, imaging=imaging)
            if cert.plan is not None:  # the adaptive anchors may refine the plan: publish the poses it rests on
                plan = cert.plan
                if plans is not None:
                    plans[axis] = plan
            cert.timings["plan"] = t_plan
            cert.timings["total"] = time.perf_counter() - t0
            if previews is not None and preview_every > 0:
                previews.extend(render_previews(src, imaging, plan, preview_every, device=self.device))
            return self._stamp(cert)

        return self._guard(axis, run)

    def process(self, cloud: Cloud, intr: CameraIntrinsics, stamp_ns: int, dense_cloud: Cloud | None = None, *,
                frame_id: str = "", preview_every: int = 0,
                should_stop: Callable[[], bool] | None = None) -> FrameResult:
        """Plan, render and certify every configured axis of one frame (results in config order; the axes at the same
        time where :meth:`axis_workers` says so, else one after another).

        ``preview_every`` > 0 keeps every k-th rendered frame (and the alpha = 0 frame) as uint8 RGB
        in ``FrameResult.previews``. ``should_stop`` is polled as each axis begins (shutdown): the
        axes not begun become ERROR certificates.
        """
        t0 = time.perf_counter()
        certs: list[Certificate] = []
        timings: dict[str, float] = {}
        plans: dict[str, Any] = {}
        previews: list[tuple[str, int, np.ndarray]] = []
        imaging = None
        try:
            imaging = self.imaging_for(intr, cloud)
        except PwsError as exc:
            certs = [self.error_for(a, str(exc)) for a in self.config.axes]
        self._frames_seen += 1
        audit = self.config.audit_every > 0 and (self._frames_seen - 1) % self.config.audit_every == 0
        budgeted = imaging is not None and self.budget.on
        startup = self.check_batch_size(tuple(imaging.out_shape)) if imaging is not None else 0.0   # once; start-up work
        coarse: list[Any] = []   # the frame's imaging at the coarse level, made when first needed

        def coarse_imaging() -> Any:
            if not coarse:
                coarse.append(self.imaging_for(intr, cloud, render_factor=COARSE_FACTOR))
            return coarse[0]

        if budgeted:
            startup += self.budget.ready(cloud, imaging, dense_cloud, coarse_imaging)

        def one(k: int, axis: str) -> tuple[Certificate, list, float]:
            """The ``k``-th axis: its certificate (audited where due), its previews and its seconds."""
            t1 = time.perf_counter()
            share = 0.0
            if budgeted:   # of what is left of the frame's budget: an axis that took less leaves it to the next
                share = self.budget.share(t1 - t0 - startup, len(self.config.axes) - k)
            if should_stop is not None and should_stop():
                return self.error_for(axis, "shutting down"), [], time.perf_counter() - t1
            sizes = self.budget.size(share, imaging) if budgeted and self.budget.costs.ready else None
            used = imaging
            if sizes is not None and sizes.coarse:
                try:
                    used = coarse_imaging()
                except PwsError:   # cannot happen where the coarse level was measured; the configured imaging then
                    sizes = self.budget.size(share, imaging, coarse_ok=False)
            mine: list[tuple[str, int, np.ndarray]] = []
            cert = self.certify_axis(cloud, used, axis, dense_cloud, preview_every, mine, plans,
                                     stamp_ns=int(stamp_ns), sizes=sizes)
            cert.filled_points = filled_drawn(cloud, used)   # the statement is about the cloud with filled depth
            if sizes is not None:
                self.budget.record(cert, sizes, time.perf_counter() - t1, used)
            if audit and cert.status != "error" and axis in plans:
                audit_certificate(cert, self.source_cloud(cloud, dense_cloud), used, plans[axis], device=self.device,
                                  num_anchors=self.config.num_anchors, audit_poses=self.config.audit_poses, log=self.log)
            return cert, mine, time.perf_counter() - t1

        if imaging is not None:
            axes = list(self.config.axes)
            workers = self.axis_workers(budgeted)
            if workers > 1:   # the axes at the same time (axis_threads): each its own renderer, plan and noise seed
                axis_imports()
                done = at_once(lambda k: one(k, axes[k]), len(axes), workers)
            else:
                done = [one(k, axis) for k, axis in enumerate(axes)]
            for axis, (cert, mine, seconds) in zip(axes, done):   # in config order either way
                certs.append(cert)
                previews.extend(mine)
                timings[axis] = seconds
        if startup > 0:
            timings["startup"] = startup   # warm-ups and the batch size check: not the frame's work (nor in "total")
        timings["total"] = time.perf_counter() - t0 - startup
        return FrameResult(int(stamp_ns), frame_id or intr.frame_id, certs, plans,
                           imaging.camera if imaging is not None else None, timings, previews, imaging)


__all__ = ["FrameCertifier", "FrameResult", "LogFn", "resolve_device_with_fallback"]
