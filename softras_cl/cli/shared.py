"""What the fitting commands share around a fit: their options' arguments (from
fitting.run_options), late interrupts, the summary line."""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

from softras_cl.fitting.metrics import finite_metrics
from softras_cl.io.outputs import INPUT_FILES, OutputFolder
from softras_cl.interrupts import Caught, first_interrupt_calls

if TYPE_CHECKING:
    from softras_cl.fitting.run_options import FitOptions


def add_fit_options(p: argparse.ArgumentParser, fit: FitOptions, files: bool) -> None:
    """Add the options of ``fit`` (fitting.run_options: FACE, BODY) to a command's parser, each
    with its flag, type, default and help: its model files (``files``) or all the others."""
    for option in (o for o in fit.options if o.file == files):
        if option.switch:
            p.add_argument(option.flag, action="store_true", help=option.help)
        else:
            p.add_argument(option.flag, type=option.parse, default=option.default, choices=option.choices,
                           metavar=option.metavar, help=option.help)


def fit_values(args: argparse.Namespace, fit: FitOptions) -> dict:
    """The values of ``fit``'s options on the command line (option name -> value)."""
    return {name: getattr(args, name) for name in fit.names}


def _say_finishing(signum: int) -> None:
    print("softras-cl: interrupted; writing the outputs first (interrupt again to stop at once: "
          "every file already written stays complete)", file=sys.stderr)


@contextlib.contextmanager
def finishing_outputs() -> Iterator[Caught]:
    """A first Ctrl-C/SIGTERM while the outputs are written is noted (``caught.signum``) and the
    writing goes on; a second one stops at once."""
    with first_interrupt_calls(_say_finishing) as caught:
        yield caught


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


def say_summary(command: str, run: FitRun, details: str) -> None:
    """Print the run's summary line: "COMMAND done in S s: DETAILS; outputs in FOLDER/" on
    stdout, or, when the run was interrupted, that its outputs are from the best values so far,
    on stderr (with the other notices of the interrupt)."""
    state = ("interrupted; outputs are from the best values so far (--resume continues the fit)"
             if run.interrupted else "done")
    print(f"{command} {state} in {run.seconds:.1f} s: {details}; outputs in {run.folder}/",
          file=sys.stderr if run.interrupted else sys.stdout)
