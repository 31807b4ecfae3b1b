"""Helpers of the real-graph tests (no fixtures): spinning an executor until a condition holds, and domain ids
that Fast DDS accepts."""

from __future__ import annotations

import itertools
import os
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


def domain_ids(first: int, last: int):
    """Endless domain ids of one test file, cycling through first..last (inclusive) from an offset set by this
    process id (parallel test runs rarely meet). Fast DDS ends the process (status 1, no traceback) for an id over
    232, whose ports do not exist, so every file keeps to a block within 0..232."""
    if not 0 <= first <= last <= 232:
        raise ValueError(f"domain ids must lie within 0..232, got {first}..{last}")
    span, start = last - first + 1, os.getpid()
    return (first + (start + i) % span for i in itertools.count())
