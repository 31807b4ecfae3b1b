"""Helpers of the real-graph tests (no fixtures): spinning an executor until a condition holds."""

from __future__ import annotations

import time


def spin_until(executor, predicate, timeout: float = 20.0, action=None, period: float = 0.1) -> bool:
    """Spin `executor` until `predicate()` holds or `timeout` s pass, calling `action()` every `period` s."""
    deadline, next_action = time.monotonic() + timeout, 0.0
    while time.monotonic() < deadline:
        if predicate():
            return True
        if action is not None and time.monotonic() >= next_action:
            action()
            next_action = time.monotonic() + period
        executor.spin_once(timeout_sec=0.02)
    return predicate()
