"""What the fitting commands share around a fit: option names in errors, late interrupts, the summary."""
from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from softras_cl.errors import InputError
from softras_cl.fitting.metrics import finite_metrics
from softras_cl.io.outputs import INPUT_FILES, OutputFolder
from softras_cl.interrupts import Caught, first_interrupt_calls


@contextlib.contextmanager
def named_as_options(options: dict[str, str]) -> Iterator[None]:
    """Reword a configuration's InputError ("fov_deg must be ...") with the command's option for
    that field ("--fov must be ..."); ``options`` maps field names to option names."""
    try:
        yield
    except InputError as e:
        field, _, rest = str(e).partition(" ")
        if field not in options:
            raise
        raise InputError(f"{options[field]} {rest}") from None


def _say_finishing(signum: int) -> None:
    print("softras-cl: interrupted; writing the outputs first (interrupt again to stop at once: "
          "every file already written stays complete)", file=sys.stderr)


@contextlib.contextmanager
def finishing_outputs() -> Iterator[Caught]:
    """A first Ctrl-C/SIGTERM while the outputs are written is noted (``caught.signum``) and the
    writing goes on; a second one stops at once."""
    with first_interrupt_calls(_say_finishing) as caught:
        yield caught


def run_state(interrupted: bool) -> str:
    """How the summary line describes the run."""
    if interrupted:
        return "interrupted; outputs are from the best values so far (--resume continues the fit)"
    return "done"


@dataclass
class FitRun:
    """What `run_fit` reports: the metrics written, the fit's seconds, whether it was stopped
    early (Ctrl-C/SIGTERM during the fit or while writing), and the output folder."""
    metrics: dict
    seconds: float
    interrupted: bool
    folder: Path


def run_fit(args, command: str, record: dict, fit: Callable, required: tuple[str, ...],
            write: Callable, files: list) -> FitRun:
    """One fit into the locked folder ``args.out``: run.json from ``record`` (``args.resume``
    continues the fit there; a complete fit of other inputs there is refused unless
    ``args.overwrite``), ``fit(folder) -> FaceFit | BodyFit``, its ``required`` metrics
    checked finite, ``write(fit, folder, metrics, seconds) -> metrics`` under finishing_outputs,
    and complete.json (naming the input ``files``, as given) unless the run was interrupted."""
    with OutputFolder(args.out, command, "--out") as out:
        replacing = out.begin(record, resume=args.resume, overwrite=args.overwrite)
        if replacing:
            print(replacing)
        start = time.perf_counter()
        result = fit(out.path)
        seconds = time.perf_counter() - start
        metrics = finite_metrics(result, out.path, required)
        with finishing_outputs() as late:
            metrics = write(result, out.path, metrics, seconds)
            interrupted = result.result.interrupted or late.signum is not None
            if not interrupted:
                out.finish({"status": "done", INPUT_FILES: [str(f) for f in files], "metrics": metrics,
                            "seconds": seconds})
    return FitRun(metrics, seconds, interrupted, out.path)
