"""A real Ctrl-C for tests of long-running commands."""
from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path


def _interrupt_when_exists(path: Path, stop: threading.Event) -> None:
    while not stop.is_set():
        if path.exists():
            stop.wait(0.5)
            os.kill(os.getpid(), signal.SIGINT)
            return
        stop.wait(0.05)


@contextlib.contextmanager
def sigint_once_written(path: Path):
    """Send this process a SIGINT half a second after ``path`` appears (e.g. the solver's first
    checkpoint, so the fit is surely running) while the block runs."""
    stop = threading.Event()
    watcher = threading.Thread(target=_interrupt_when_exists, args=(Path(path), stop))
    watcher.start()
    try:
        yield
    finally:
        stop.set()
        watcher.join()
