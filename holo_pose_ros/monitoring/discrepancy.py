"""One joint's watch: a window of its latest discrepancies (estimate - reported; radians, metres for prismatic
joints) and an alarm level debounced over `persistence` consecutive frames, so that one bad frame raises nothing
and one good frame clears nothing.

Levels (the values of diagnostic_msgs/DiagnosticStatus): a frame is OK when |d| <= warn, WARN when
warn < |d| <= error, ERROR when |d| > error. The joint's level rises to L once its last `persistence` frames are
all at L or above, and falls to L once they are all at L or below (the level those frames agree on): a fault that
holds for `persistence` frames is raised, and cleared only after `persistence` frames without it. Frames whose
discrepancy is NaN (a joint missing or not finite on either side) are skipped: they neither raise nor clear."""

from __future__ import annotations

import math
from collections import deque

import numpy as np

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


def frame_level(d: float, warn: float, error: float) -> int:
    """The level of one frame's discrepancy `d` (finite) for thresholds warn <= error."""
    magnitude = abs(d)
    return ERROR if magnitude > error else WARN if magnitude > warn else OK


class JointWatch:
    """Window and debounced level of one joint; see the module docstring."""

    def __init__(self, name: str, warn: float, error: float, window: int = 30, persistence: int = 3):
        if not (warn > 0 and error >= warn):
            raise ValueError(f"{name}: thresholds need 0 < warn <= error, got warn {warn}, error {error}")
        if window < 1 or persistence < 1:
            raise ValueError(f"{name}: window and persistence must be >= 1")
        self.name, self.warn, self.error, self.persistence = name, float(warn), float(error), int(persistence)
        self._window: deque[float] = deque(maxlen=int(window))
        self._recent: deque[int] = deque(maxlen=self.persistence)
        self.level = OK
        self.last = math.nan  # the latest finite discrepancy
        self.samples = 0  # finite discrepancies since start
        self.skipped = 0  # NaN discrepancies since start

    def add(self, d: float) -> int:
        """Take one frame's discrepancy; returns the joint's level after it."""
        if not math.isfinite(d):
            self.skipped += 1
            return self.level
        self.samples += 1
        self.last = float(d)
        self._window.append(self.last)
        self._recent.append(frame_level(self.last, self.warn, self.error))
        if len(self._recent) == self.persistence:
            low, high = min(self._recent), max(self._recent)
            if low > self.level:
                self.level = low
            elif high < self.level:
                self.level = high
        return self.level

    def reset(self) -> None:
        """Forget the frames (the streams went stale): level OK, empty window; the counters stay."""
        self._window.clear()
        self._recent.clear()
        self.level, self.last = OK, math.nan

    @property
    def mean_abs(self) -> float:
        """Mean |discrepancy| over the window (NaN when empty)."""
        return float(np.mean(np.abs(self._window))) if self._window else math.nan

    @property
    def max_abs(self) -> float:
        return float(np.max(np.abs(self._window))) if self._window else math.nan

    @property
    def window_size(self) -> int:
        return len(self._window)
