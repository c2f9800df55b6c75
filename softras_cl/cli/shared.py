"""What the commands share: their options, each declared once (a fit's own options come from
fitting.run_options; the output folder's, the face choice's, the cluster's are here), and the
closing summary line. Nothing here loads OpenCL: `--help` stays fast."""
from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError

if TYPE_CHECKING:
    from softras_cl.fitting.jobs.run import FitRun
    from softras_cl.fitting.run_options import FitOptions

# the help of --resume / --overwrite / --no-progress: command -> texts
RERUN_HELP = {
    "fit-face": ("continue the interrupted fit in --out from its checkpoint.npz (same photo, landmarks, model "
                 "and options, else refused); finished stages are skipped",
                 "replace a complete fit of another photo (other landmarks or model) that --out holds (else "
                 "refused; one of the same inputs is replaced, saying so if its options differ)",
                 "no progress bar"),
    "fit-body": ("continue the interrupted fit in --out from its checkpoint.npz (same target, model, joints "
                 "and options, else refused); finished stages are skipped",
                 "replace a complete fit of another target (other joints or model) that --out holds (else "
                 "refused; one of the same inputs is replaced, saying so if its options differ)",
                 "no progress bar"),
    "track-face": ("go on with the interrupted run in --out (same video, model and options, else refused) at "
                   "its first unfinished chunk",
                   "replace a complete run of another video that --out holds (else refused)",
                   "no progress line"),
}
CLUSTER_OPTIONS = ("workers", "threads_per_worker", "scheduler")


def add_fit_options(p: argparse.ArgumentParser, fit: FitOptions, files: bool) -> None:
    """Add the options of ``fit`` (fitting.run_options: FACE, BODY, TRACK) to a command's parser,
    each with its flag, type, default and help: its model files (``files``) or all the others."""
    for option in (o for o in fit.options if o.file == files):
        if option.switch:
            p.add_argument(option.flag, action="store_true", help=option.help)
        else:
            p.add_argument(option.flag, type=option.parse, default=option.default, choices=option.choices,
                           metavar=option.metavar, help=option.help)


def fit_values(args: argparse.Namespace, fit: FitOptions) -> dict:
    """The values of ``fit``'s options on the command line (option name -> value)."""
    return {name: getattr(args, name) for name in fit.names}


def add_out_option(p: argparse.ArgumentParser) -> None:
    """--out DIR, the output folder of a fit or a run."""
    p.add_argument("--out", required=True, help="output directory (created if missing)")


def add_rerun_options(p: argparse.ArgumentParser, command: str) -> None:
    """--resume and --overwrite of ``command`` (RERUN_HELP)."""
    resume, overwrite, _ = RERUN_HELP[command]
    p.add_argument("--resume", action="store_true", help=resume)
    p.add_argument("--overwrite", action="store_true", help=overwrite)


def add_progress_option(p: argparse.ArgumentParser, command: str) -> None:
    """--no-progress of ``command`` (RERUN_HELP)."""
    p.add_argument("--no-progress", action="store_true", help=RERUN_HELP[command][2])


def add_manifest_option(p: argparse.ArgumentParser, columns: str, examples: str | None = None) -> None:
    """--manifest CSV, whose ``columns`` (the input column and the optional ones) and option
    ``examples`` the help names."""
    examples = f" (e.g. {examples})" if examples else ""
    p.add_argument("--manifest", default=None, metavar="CSV",
                   help=f"CSV of {columns}, and any option of this command as a column{examples}; "
                        "empty cells take the command line's value; paths relative to the CSV's folder")


def add_face_choice(parser) -> argparse._MutuallyExclusiveGroup:
    """Add --face N and --face-box X,Y,W,H (dest face, face_box: an int and a string, None when
    not given; parse_face_box reads the string) to `parser` as a mutually exclusive group, and
    return the group (detect-landmarks and fit-face add --all-faces to it)."""
    from softras_cl.fitting.run_options import FACE_BOX_HELP, FACE_HELP

    which = parser.add_mutually_exclusive_group()
    which.add_argument("--face", type=int, default=None, metavar="N", help=FACE_HELP)
    which.add_argument("--face-box", default=None, metavar="X,Y,W,H", help=FACE_BOX_HELP)
    return which


def add_cluster_options(p: argparse.ArgumentParser, what: str) -> None:
    """--workers, --threads-per-worker, --scheduler: the Dask cluster that runs the items
    (``what``: "photos", "videos", for the help)."""
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of the local Dask cluster (default: cores / "
                        "--threads-per-worker, i.e. one per core)")
    p.add_argument("--threads-per-worker", type=int, default=None, metavar="T",
                   help="OpenCL (PoCL) threads of each worker (default: cores / --workers, so that "
                        "workers x threads fills the cores without oversubscribing them)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help=f"run the items on this running Dask scheduler's workers instead (they need "
                        f"softras-cl installed and must see the {what} and --out at the same paths)")


def cluster_asked(args: argparse.Namespace) -> bool:
    """Whether any of the cluster options (CLUSTER_OPTIONS) was given."""
    return any(getattr(args, k, None) is not None for k in CLUSTER_OPTIONS)


def cluster_values(args: argparse.Namespace) -> dict:
    """The cluster options as fitting.batch.client.fit_many takes them."""
    return {k: getattr(args, k) for k in CLUSTER_OPTIONS}


def check_cluster_args(args: argparse.Namespace) -> None:
    """InputError when --scheduler comes with the local cluster's options."""
    if args.scheduler is not None and (args.workers is not None or args.threads_per_worker is not None):
        raise InputError("--workers and --threads-per-worker start a local cluster; with --scheduler "
                         "the cluster's own workers run the items (start them with "
                         "POCL_MAX_PTHREAD_COUNT=T dask worker ... --nthreads 1)")


def say_summary(command: str, run: FitRun, details: str) -> None:
    """Print the run's summary line: "COMMAND done in S s: DETAILS; outputs in FOLDER/" on
    stdout, or, when the run was interrupted, that its outputs are from the best values so far,
    on stderr (with the other notices of the interrupt)."""
    state = ("interrupted; outputs are from the best values so far (--resume continues the fit)"
             if run.interrupted else "done")
    print(f"{command} {state} in {run.seconds:.1f} s: {details}; outputs in {run.folder}/",
          file=sys.stderr if run.interrupted else sys.stdout)


def run_job(args: argparse.Namespace, job, command: str) -> int:
    """Run a fit job whose inputs are read (fitting.jobs) into --out (--resume, --overwrite,
    --no-progress), print its summary line; the exit code."""
    from softras_cl.fitting.jobs.run import run_fit

    run = run_fit(job, args.out, resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress)
    say_summary(command, run, job.summary(run.metrics))
    return EXIT_INTERRUPTED if run.interrupted else EXIT_OK
