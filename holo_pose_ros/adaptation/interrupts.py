"""A Ctrl-C that cannot be lost: Python raises KeyboardInterrupt wherever the main thread happens to be, and when
that is a finalizer (a GL object's or a tensor's __del__ run by the garbage collector) the exception is printed as
'Exception ignored' and the run goes on. The latch remembers the signal so that a loop stops at its next step."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager


@contextmanager
def sigint_latch() -> Iterator[Callable[[], None]]:
    """Within the block SIGINT still raises KeyboardInterrupt at once (the previous handler runs), and is also
    latched: the yielded check() raises KeyboardInterrupt from then on, so a swallowed one is raised again by the
    next check. Off the main thread (where signals cannot be handled) check() does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    latched = threading.Event()
    previous = signal.getsignal(signal.SIGINT)

    def handler(signum, frame):
        latched.set()
        if callable(previous):
            previous(signum, frame)
        else:
            raise KeyboardInterrupt

    def check() -> None:
        if latched.is_set():
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, handler)
    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)
