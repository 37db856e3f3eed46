"""The overlay picture of one certified frame (ROS-free, OpenCV): what the classifier saw at the recorded
pose with the verdict drawn under it. Published by the nodes on ``certification/overlay``
(``publish_overlay``) and written by ``pws replay --video`` for every frame; one function draws it,
:func:`draw_overlay`.

Layout (fixed, so that a viewer, or a test, can read the bars from the pixels; docs/ros2.md):

* the **view**: the α = 0 frame the classifier got (uint8 RGB, e.g. 160x90 for the demo model), scaled up
  with nearest-neighbour by the integer factor ``ceil(MIN_WIDTH / width)`` (1 for a view at least
  ``MIN_WIDTH`` wide); a frame without a view (an input that could not be converted) gets a blank
  ``BLANK_SIZE`` view;
* under it a **panel** of the view's width on ``PANEL_BG``: a header row of ``HEADER_H`` px (the label, its
  class name, the least p_A lower bound over the axes, the verdict: *certified* when every axis is, and the
  stamp), then one row of ``ROW_H`` px per axis, in the message's axis order: the axis name, a **bar** and
  the certified share in words;
* each bar spans ``x in [BAR_X0, width - BAR_RIGHT)`` and ``BAR_H`` rows centred in its row; its track is
  ``TRACK`` and its first ``round(length * min(1, radius / requested_radius))`` pixels are coloured by the
  axis' level: ``LEVEL_RGB['OK']`` green (certified), ``['WARN']`` orange (not certified, abstained),
  ``['ERROR']`` red (could not certify; its radius is 0, so only the words show it). Text is white or of
  its level's colour, anti-aliased on the neutral ``PANEL_BG``, so no text pixel has the bluish ``TRACK``.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_ERROR, Certificate
from .diagnostics import LEVEL_FOR_STATUS, certified_label

MIN_WIDTH = 640                  # the view is scaled up (nearest, integer factor) to at least this width
BLANK_SIZE = (360, 640)          # (H, W) of the view of a frame that has none
HEADER_H = 34                    # px: the header row of the panel
ROW_H = 28                       # px: one row per axis
BAR_X0 = 64                      # px: where every bar starts
BAR_RIGHT = 150                  # px: room right of the bar for the share in words
BAR_H = 14                       # px: the bar's height, centred in its row
PANEL_BG = (24, 24, 24)
TRACK = (60, 60, 110)            # the bar's empty part (bluish: no anti-aliased text on PANEL_BG has it)
LEVEL_RGB = {"OK": (40, 200, 40), "WARN": (255, 150, 0), "ERROR": (220, 30, 30)}
WHITE = (235, 235, 235)
_LEVEL_ORDER = ("OK", "WARN", "ERROR")


def certified_share(cert: Certificate) -> float:
    """The bar's filled share: ``radius / requested_radius`` in [0, 1] (0 for an ERROR)."""
    if cert.status == STATUS_ERROR or not cert.requested_radius > 0 or not math.isfinite(cert.radius):
        return 0.0
    return float(min(1.0, max(0.0, cert.radius / cert.requested_radius)))


def bar_length(width: int) -> int:
    """Pixels of a full bar in an overlay ``width`` px wide."""
    return max(1, int(width) - BAR_RIGHT - BAR_X0)


def upscale(view: np.ndarray) -> np.ndarray:
    """The view as uint8 RGB, scaled up (nearest) by ``ceil(MIN_WIDTH / width)``."""
    v = np.asarray(view)
    if v.ndim == 2:
        v = np.repeat(v[:, :, None], 3, axis=2)
    if v.dtype != np.uint8:   # a float frame in [0, 1]
        v = np.clip(np.rint(v.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    v = v[:, :, :3]
    k = max(1, math.ceil(MIN_WIDTH / max(1, v.shape[1])))
    return np.ascontiguousarray(v.repeat(k, axis=0).repeat(k, axis=1) if k > 1 else v)


def _text(img: np.ndarray, text: str, x: int, y: int, color: tuple[int, int, int], scale: float = 0.5) -> None:
    import cv2

    cv2.putText(img, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def frame_level(certs: Sequence[Certificate]) -> str:
    """The worst level of a frame's axes (OK, WARN or ERROR; ERROR for no axis)."""
    levels = [LEVEL_FOR_STATUS.get(c.status, "ERROR") for c in certs]
    return max(levels, key=_LEVEL_ORDER.index) if levels else "ERROR"


def _header(certs: Sequence[Certificate], stamp_ns: int | None) -> tuple[str, str, str]:
    """(left text, verdict, the verdict's level) of the header row."""
    level = frame_level(certs)
    ran = [c for c in certs if c.status != STATUS_ERROR]
    labels = {(int(c.label), c.class_name) for c in ran if c.status != STATUS_ABSTAIN}
    if len(labels) == 1:
        label, name = next(iter(labels))
        left = f"{name or label} (label {label})"
    elif len(labels) > 1:
        left = "axes disagree: " + ", ".join(f"{n or l}" for l, n in sorted(labels))
    else:
        left = "abstained" if ran else "no label"
    p_a = [c.min_p_a_lower for c in ran if c.p_a_lower]
    if p_a:
        left += f"   p_A >= {min(p_a):.3f}"
    if certified_label(certs) is not None:
        verdict, level = "CERTIFIED", "OK"
    else:   # not every axis certified, or axes that certified different labels
        verdict, level = ("ERROR", "ERROR") if level == "ERROR" else ("NOT CERTIFIED", "WARN")
    if stamp_ns is not None:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        verdict += f"  t={sec}.{nsec // 1_000_000:03d}"
    return left, verdict, level


def _row_text(cert: Certificate) -> str:
    if cert.status == STATUS_ERROR:
        return "ERROR"
    if cert.status == STATUS_ABSTAIN:
        return "abstain"
    return f"{100.0 * certified_share(cert):3.0f}% {'OK' if cert.status == STATUS_CERTIFIED else 'WARN'}"


def draw_overlay(view: np.ndarray | None, certs: Sequence[Certificate], stamp_ns: int | None = None) -> np.ndarray:
    """The overlay (uint8 RGB, (H, W, 3)) of one frame: ``view`` (the α = 0 frame, uint8 RGB or float in
    [0, 1]; None: a blank one) scaled up, and under it the panel with the verdict and one bar per
    certificate (module docstring)."""
    top = upscale(view) if view is not None else np.zeros((*BLANK_SIZE, 3), np.uint8)
    H, W = top.shape[:2]
    panel = np.empty((HEADER_H + ROW_H * len(certs), W, 3), np.uint8)
    panel[:] = PANEL_BG
    left, verdict, level = _header(certs, stamp_ns)
    _text(panel, left, 8, 23, WHITE, 0.6)
    import cv2

    (tw, _th), _ = cv2.getTextSize(verdict, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 1)
    _text(panel, verdict, max(8, W - 8 - tw), 23, LEVEL_RGB[level], 0.55)
    length = bar_length(W)
    for i, cert in enumerate(certs):
        y0 = HEADER_H + i * ROW_H
        lv = LEVEL_FOR_STATUS.get(cert.status, "ERROR")
        _text(panel, cert.axis, 8, y0 + 19, WHITE)
        b0 = y0 + (ROW_H - BAR_H) // 2
        panel[b0:b0 + BAR_H, BAR_X0:BAR_X0 + length] = TRACK
        fill = int(round(length * certified_share(cert)))
        if fill > 0:
            panel[b0:b0 + BAR_H, BAR_X0:BAR_X0 + fill] = LEVEL_RGB[lv]
        _text(panel, _row_text(cert), BAR_X0 + length + 10, y0 + 19, LEVEL_RGB[lv])
    return np.ascontiguousarray(np.concatenate([top, panel], axis=0))


__all__ = ["BAR_H", "BAR_RIGHT", "BAR_X0", "BLANK_SIZE", "HEADER_H", "LEVEL_RGB", "MIN_WIDTH", "PANEL_BG", "ROW_H", "TRACK",
           "bar_length", "certified_share", "draw_overlay", "frame_level", "upscale"]
