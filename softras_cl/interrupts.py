"""Ctrl-C (and SIGTERM) as a request to finish cleanly, then as an order to stop.

``with first_interrupt_calls(callback) as caught:`` - while the block runs, the first SIGINT (or
SIGTERM, when its handler is Python's default_int_handler, as the command line sets it) calls
``callback(signum)`` instead of raising KeyboardInterrupt, and records it in ``caught.signum``;
the handlers then revert to raising, so a second signal interrupts at once. Outside the main
thread, or when the program installed handlers of its own, nothing is changed.

The solver uses it to stop nlopt between evaluations and keep the best values; the command line
uses it to finish writing the outputs after a late Ctrl-C.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from dataclasses import dataclass
from typing import Callable, Iterator

__all__ = ["Caught", "first_interrupt_calls"]

STOP_SIGNALS = tuple(s for s in (signal.SIGINT, getattr(signal, "SIGTERM", None)) if s is not None)


@dataclass
class Caught:
    """The signal number of the first interrupt caught in the block, or None."""
    signum: int | None = None


@contextlib.contextmanager
def first_interrupt_calls(callback: Callable[[int], None]) -> Iterator[Caught]:
    caught = Caught()
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    taken = [s for s in STOP_SIGNALS if signal.getsignal(s) is signal.default_int_handler]

    def handler(signum, frame):
        for s in taken:                       # a second signal raises KeyboardInterrupt at once
            signal.signal(s, signal.default_int_handler)
        caught.signum = signum
        callback(signum)

    previous = {s: signal.signal(s, handler) for s in taken}
    try:
        yield caught
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
