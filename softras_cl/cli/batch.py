"""What `fit-face` and `fit-body` share for many photos: the options, when a run is a batch, and
the batch run itself (softras_cl.fitting.batch.client.fit_many)."""
from __future__ import annotations

import argparse
import glob
from pathlib import Path

from softras_cl.cli.shared import (add_cluster_options, add_manifest_option, check_cluster_args, cluster_asked,
                                   cluster_values)
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError, ResultError

BATCH_EPILOG = """\
Many photos: give several photos, folders (their image files, not subfolders; X_landmarks.png
drawings beside a photo X are left out) or quoted glob patterns, and/or --manifest CSV. Each
item is fitted into its own folder under --out, named after the photo's file name (a hash of
the path is appended when two share a name; --all-faces appends -faceN, N the face's number,
largest first); --out also gets results.csv, results.jsonl and summary.png. Items run on a
Dask cluster: a LocalCluster of --workers processes on this machine by default, or --scheduler.
Running the same command again skips every item whose folder holds a complete.json with the
same inputs and options, and redoes the others. Exit code 0 when every item succeeded, 1 when
some failed (results.csv says which and why), 130 on Ctrl-C (finished items and the table are
kept)."""


def add_batch_options(p: argparse.ArgumentParser, kind: str) -> None:
    """--manifest, --workers, --threads-per-worker, --scheduler on a fit-face/fit-body parser."""
    side = "landmarks" if kind == "face" else "joints"
    add_manifest_option(p, f"items: a 'photo' column, optional '{side}' and 'name' columns", "size, budget")
    add_cluster_options(p, "photos")


def is_batch(args: argparse.Namespace, inputs: list[str]) -> bool:
    """Several inputs, a folder, a glob pattern, a manifest, --all-faces or a cluster option make
    a batch; one photo file alone is the single-photo run (outputs in --out itself)."""
    if len(inputs) != 1 or args.manifest or getattr(args, "all_faces", False):
        return True
    if cluster_asked(args):
        return True
    return Path(inputs[0]).is_dir() or (not Path(inputs[0]).exists() and glob.has_magic(inputs[0]))


def check_batch_args(args: argparse.Namespace) -> None:
    """InputError for options that do not apply to a batch."""
    if getattr(args, "face_box", None) is not None:
        raise InputError("--face-box names a box in one photo: give a single photo (without --manifest, "
                         "--all-faces or cluster options), or --face N to fit face N of each photo")
    if args.resume:
        raise InputError("--resume continues the fit of one photo; run the batch again instead: it "
                         "skips the finished items and redoes the others")
    check_cluster_args(args)


def check_faces_found(items) -> None:
    """--all-faces on one photo whose landmarks are detected: NoFaceError (exit 2, as without
    --all-faces) when the detector finds no face in it, before the batch starts (it used to
    become a failed item, exit 1). Several photos: each one's own row says so."""
    from softras_cl.fitting.detection import landmarks_beside, resolve_landmarks

    if len(items) == 1 and items[0].kind == "face" and items[0].landmarks is None \
            and landmarks_beside(items[0].photo) is None:
        resolve_landmarks(items[0].photo, None, all_faces=True)


def say_interrupted(kind: str, result) -> None:
    """One line on stderr after Ctrl-C: how many items finished, that they are kept, where the
    table is, and how to go on (a batch printed nothing there)."""
    import sys

    finished = {status: n for status, n in result.counts.items() if status != "cancelled"}
    details = ", ".join(f"{n} {status}" for status, n in finished.items()) or "none"
    print(f"softras-cl fit-{kind}: interrupted: {sum(finished.values())} of {len(result.rows)} items finished "
          f"({details}), kept and listed in {result.out}/results.csv; run the same command again to fit "
          "the others", file=sys.stderr)


def run_batch(args: argparse.Namespace, kind: str, inputs: list[str], options: dict,
              side_file: str | None) -> int:
    """Fit every item (softras_cl.fitting.batch), print one summary line; the exit code."""
    from softras_cl.fitting.batch.client import fit_many
    from softras_cl.fitting.batch.items import collect_items
    from softras_cl.fitting.model_cache import load_model

    check_batch_args(args)
    items = collect_items(inputs, kind, options, manifest=args.manifest, landmarks=side_file,
                          face=getattr(args, "face", None))
    load_model(kind, options.get("model"), options.get("model_landmarks"))   # a bad model: exit 2 now
    if getattr(args, "all_faces", False):
        check_faces_found(items)
    result = fit_many(items, args.out, kind, **cluster_values(args), all_faces=getattr(args, "all_faces", False),
                      progress=not args.no_progress)
    counts = ", ".join(f"{n} {s}" for s, n in result.counts.items())
    print(f"fit-{kind}: {len(result.rows)} items: {counts}; results in {result.out}/results.csv")
    if result.interrupted:
        say_interrupted(kind, result)
        return EXIT_INTERRUPTED
    if result.failed:
        first = result.failed[0]
        raise ResultError(f"{len(result.failed)} of {len(result.rows)} items failed (first: "
                          f"{first['name']}: {first['error']}); {result.out}/results.csv says which")
    return EXIT_OK
