"""Time that jumps back (``ros2 bag play --loop``, a restarted driver, a reset simulation clock).

Every stamp-ordered piece of the bridge (:class:`~pws_ros.bridge.sync.StampMatcher`,
:class:`~pws_ros.bridge.assembly.PartitionAssembler`) treats a stamp more than
``jump_back_tolerance_ns`` (default :data:`JUMP_BACK_TOLERANCE_NS`, 1 s) older than its newest
match/frame as a new timeline, as tf2 does: it counts the jump in ``time_jumps``, reports it once
through ``on_time_jump(text)`` (the nodes log it as WARN) and resets, so the new pass is matched and
certified instead of being dropped as "late" forever. What was buffered from before the jump is
dropped and counted (the assembler releases its incomplete sets as failed), so every input frame is
still either answered or counted. :class:`~pws_ros.bridge.sync.LatestSlot` keeps no stamps and needs
no reset.
"""
from __future__ import annotations

from typing import Callable

from ..core.errors import require

JUMP_BACK_TOLERANCE_NS = 1_000_000_000
"""A stamp older than the newest match/frame by more than this (1 s) starts a new timeline."""


class Timeline:
    """What a stamp-ordered buffer keeps about time jumping back: ``jump_back_tolerance_ns``,
    ``on_time_jump`` (settable after construction) and the count ``time_jumps``."""

    def _init_timeline(self, jump_back_tolerance_ns: int, on_time_jump: Callable[[str], None] | None) -> None:
        require(int(jump_back_tolerance_ns) >= 0, f"jump-back tolerance must be >= 0, got {jump_back_tolerance_ns} ns")
        self.jump_back_tolerance_ns = int(jump_back_tolerance_ns)
        self.on_time_jump = on_time_jump
        self.time_jumps = 0

    def _jumped_back(self, newest_ns: int | None, stamp_ns: int, what: str, reset: Callable[[int], None],
                     repeat: bool = False) -> bool:
        """When ``stamp_ns`` is older than ``newest_ns`` by more than the tolerance, or ``repeat`` (the caller
        saw this stamp come again: a loop shorter than the tolerance): ``reset(back_ns)``, count the jump
        and report it once (the text names ``what``); True then, else False."""
        if newest_ns is None or (stamp_ns >= newest_ns - self.jump_back_tolerance_ns and not repeat):
            return False
        back_ns = newest_ns - stamp_ns
        reset(back_ns)
        self.time_jumps += 1
        if self.on_time_jump is not None:
            self.on_time_jump(f"{what}: time jumped back by {back_ns / 1e9:.3f} s (to stamp {stamp_ns}; a looped bag, a "
                              f"restarted driver or a reset clock): starting over, what was buffered before the jump is dropped")
        return True


__all__ = ["JUMP_BACK_TOLERANCE_NS", "Timeline"]
