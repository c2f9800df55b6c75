"""One fit into one output folder, as every data path's job runs it.

A job (fitting.jobs.face_photo, body_photo, body_target) knows its inputs and how to fit and
write them; :func:`run_fit` runs it into a locked output folder (run.json from the job's record,
``resume`` continues the fit there, a complete fit of other inputs is refused unless
``overwrite``); :func:`fit_and_write` is the part a batch task shares with it: the fit, its
required metrics checked finite, the outputs written under a late interrupt, complete.json.
"""
from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator, Protocol

from softras_cl.fitting.metrics import finite_metrics
from softras_cl.interrupts import Caught, first_interrupt_calls
from softras_cl.io.outputs import INPUT_FILES, OutputFolder

__all__ = ["FitJob", "FitRun", "run_fit", "fit_and_write", "finishing_outputs"]


class FitJob(Protocol):
    """What a data path's job offers the runners.

    command: the command named in run records and locks ("fit-face", "fit-body").
    required: the metrics that must be finite for the fit to count (else ResultError).
    started: (optional) time.perf_counter() when read() began, for run_fit's seconds.
    """
    command: str
    required: tuple[str, ...]

    def record(self) -> dict:
        """The run record: command, the inputs' digests, the options (fitting.run_records)."""

    def files(self) -> list[str]:
        """The input files as given, for complete.json."""

    def fit(self, folder: Path, progress: bool, resume: bool):
        """Run the recipe, its solver files in ``folder``; the recipe's fit (FaceFit,
        FaceViewsFit, BodyFit, BodyPhotoFit)."""

    def write(self, fit, folder: Path, metrics: dict, seconds: float) -> dict:
        """Every output through fitting.reports; the metrics written."""

    def summary(self, metrics: dict) -> str:
        """The details of the command's closing line."""


@dataclass
class FitRun:
    """What a run reports: the metrics written, its seconds, whether it was stopped early
    (Ctrl-C/SIGTERM during the fit or while writing), and the output folder. seconds: the fit's
    alone from fit_and_write (what complete.json and params.json record); from run_fit, the
    whole run's, from the job's ``started`` (set when it began reading its inputs: decoding the
    photo, detection) to the last file written, when the job has one."""
    metrics: dict
    seconds: float
    interrupted: bool
    folder: Path


def _say_finishing(signum: int) -> None:
    print("softras-cl: interrupted; writing the outputs first (interrupt again to stop at once: "
          "every file already written stays complete)", file=sys.stderr)


@contextlib.contextmanager
def finishing_outputs() -> Iterator[Caught]:
    """A first Ctrl-C/SIGTERM while the outputs are written is noted (``caught.signum``) and the
    writing goes on; a second one stops at once."""
    with first_interrupt_calls(_say_finishing) as caught:
        yield caught


def fit_and_write(job: FitJob, out: OutputFolder, progress: bool, resume: bool) -> FitRun:
    """Fit ``job`` into the held folder ``out`` (its run.json already begun), check its required
    metrics, write its outputs and, unless interrupted, complete.json."""
    start = time.perf_counter()
    result = job.fit(out.path, progress, resume)
    seconds = time.perf_counter() - start
    metrics = finite_metrics(result, out.path, job.required)
    with finishing_outputs() as late:
        metrics = job.write(result, out.path, metrics, seconds)
        interrupted = result.result.interrupted or late.signum is not None
        if not interrupted:
            out.finish({"status": "done", INPUT_FILES: job.files(), "metrics": metrics, "seconds": seconds})
    return FitRun(metrics, seconds, interrupted, out.path)


def run_fit(job: FitJob, out, *, resume: bool = False, overwrite: bool = False, progress: bool = True) -> FitRun:
    """Run ``job`` into the output folder ``out`` (locked; named --out in messages): run.json
    from its record, the fit (``resume``: continued from the folder's checkpoint), its outputs and
    complete.json. Prints the line saying what a replaced complete run held, if any."""
    with OutputFolder(out, job.command, "--out") as folder:
        replacing = folder.begin(job.record(), resume=resume, overwrite=overwrite)
        if replacing:
            print(replacing)
        run = fit_and_write(job, folder, progress, resume)
    started = getattr(job, "started", None)
    return run if started is None else replace(run, seconds=time.perf_counter() - started)
