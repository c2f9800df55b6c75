"""`softras-cl fit-face PHOTO [--landmarks FILE] [--model FILE] --out DIR`, many photos:
`softras-cl fit-face PHOTO|FOLDER|GLOB ... [--manifest CSV] --out DIR` (softras_cl.cli.batch), and
several photos of one person: `softras-cl fit-face A B C --same-person [--landmarks A.pts B.pts C.pts]
--out DIR`. The work is fitting.jobs.face_photo's; this module reads the command line and prints."""
from __future__ import annotations

import argparse

from softras_cl.cli.batch import BATCH_EPILOG, add_batch_options, is_batch, run_batch
from softras_cl.cli.shared import (add_face_choice, add_fit_options, add_out_option, add_progress_option,
                                   add_rerun_options, fit_values, run_job)
from softras_cl.errors import InputError

DESCRIPTION = """\
Fit a morphable face model to a photo and its 68 iBUG landmarks: shape (identity and
expression), skin albedo, spherical-harmonic light and head pose (paper sec. 5.3, figure 14).
Stage 1 fits pose, focal length, identity and expression to the landmarks; the photometric
stages then fit everything to the photo in linear RGB over the rendered face region, with a
sigma/gamma schedule; then a detail texture is read off the photo (un-lit by the fitted light,
the unseen side filled by symmetry or the model albedo). Writes into --out: face.ply (fitted
mesh with the model's albedo colours), face_textured.obj/.mtl/.png (the same mesh with the
detail texture), overlay.png (textured fit over the photo; overlay_model.png: the model alone),
figure.png (photo / fit / albedo / shading / error), params.json and params.npz (fitted blocks,
camera K, R, t for the photo, metrics: PSNR of the model and of the textured fit),
loss_curve.png, history.json and checkpoint.npz (best values so far, written as the fit goes),
run.json (inputs and options) and, last, complete.json. Every file is replaced atomically and --out is locked while the fit runs.
Ctrl-C or SIGTERM stops the fit and still writes every output from the best values found so
far (exit 130; --resume continues it).

Landmarks: --landmarks FILE, else a file beside the photo (PHOTO.pts/.txt/.npy, i.e. the photo's
name with that suffix), else the face detector (MediaPipe, the "detect" extra): the largest face,
or --face N (faces numbered largest first), or --face-box X,Y,W,H; the faces found, the one
fitted and why are printed and written to detection.json; in a batch (below) --face N fits face N
of each photo. A detected face whose landmarks do not form a face stops the run (exit 1) before
fitting. Every fit also writes landmarks_detected.pts (the 68 points it was given) and
landmarks_fitted.pts (the fitted model's, projected into the photo; both iBUG .pts, 1-based).

""" + BATCH_EPILOG + """

One person in several photos: --same-person fits one identity (shape) and one albedo to all the
photos given (files, folders or glob patterns, at least two; the largest face of each when
detected), each photo with its own pose,
focal length, expression and light: `fit-face A.jpg B.jpg C.jpg --same-person --landmarks A.pts
B.pts C.pts --out DIR` (one landmark file per photo in the same order, or none: each photo's file
beside it, else the detector). Writes into --out: face.ply (the shared identity, neutral
expression), photos/NAME/ (per photo, what a single-photo fit writes), figure.png (every photo
with its fit), params.json/.npz (all blocks, each photo's inputs with their SHA-256, cameras and
metrics), the solver's files, run.json and, last, complete.json; --resume continues it.
--same-camera (photos of one size, one camera and zoom) fits one focal length for all of them.
Without --same-person several photos are independent fits (above)."""


def register(sub) -> None:
    """Add `fit-face` to the `softras-cl` subparsers `sub`."""
    from softras_cl.fitting.run_options import FACE

    p = sub.add_parser("fit-face", help="fit a face model to a photo and its 68 landmarks",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("photos", nargs="*", metavar="PHOTO",
                   help="the photo (PNG/JPEG/...; sRGB, decoded to linear RGB for fitting); several "
                        "photos, folders or glob patterns fit each into its own folder under --out")
    p.add_argument("--landmarks", default=None, nargs="+", metavar="FILE",
                   help="68 landmarks of the photo in the iBUG 300-W order: .pts (iBUG, 1-based), "
                        ".txt (68 rows 'x y', 0-based pixel centres) or .npy (68, 2) (default: "
                        "PHOTO.pts/.txt/.npy beside the photo, else detected); with --same-person "
                        "one file per photo, in the photos' order")
    p.add_argument("--same-person", action="store_true",
                   help="the photos show one person: fit one identity and albedo to all of them "
                        "(each with its own pose, focal length, expression and light) into --out")
    p.add_argument("--same-camera", action="store_true",
                   help="with --same-person: the photos (all of one size) were taken with one camera "
                        "and zoom, so they share one fitted focal length (default: one per photo)")
    which = add_face_choice(p)
    which.add_argument("--all-faces", action="store_true",
                       help="fit every face the detector finds whose landmarks form a face, each into its "
                            "own folder under --out, NAME-faceN for face N (0: the largest); without it, "
                            "the largest (or --face / --face-box)")
    add_fit_options(p, FACE, files=True)
    add_out_option(p)
    add_fit_options(p, FACE, files=False)
    add_rerun_options(p, "fit-face")
    add_batch_options(p, "face")
    add_progress_option(p, "fit-face")
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict:
    """The options of a fit (softras_cl.fitting.run_options.FACE) from the command line."""
    from softras_cl.fitting.run_options import FACE

    return fit_values(args, FACE)


def say_detection(found, name: str | None = None) -> None:
    """Print where the landmarks (fitting.detection.PhotoLandmarks) came from when fit-face
    found them itself: the file beside the photo (one line), or every face detected, the one
    fitted ("*") and why; nothing for a --landmarks file. ``name``: the photo's, before the
    lines (several photos)."""
    if found.source == "beside":
        lines = [f"landmarks: {found.path} (the file beside the photo; --landmarks FILE gives another)"]
    else:
        lines = [] if found.detection is None else found.detection.describe()
    for line in lines:
        print(line if name is None else f"{name}: {line}")


def _face_box(args: argparse.Namespace):
    """--face-box as a (4,) float64 box (x, y, w, h), or None."""
    from softras_cl.fitting.detection import parse_face_box

    return None if args.face_box is None else parse_face_box(args.face_box)


def run(args: argparse.Namespace) -> int:
    """One photo into --out itself, or a batch (several photos, folders, globs, a manifest)."""
    from softras_cl.fitting.jobs.face_photo import check_fov
    from softras_cl.fitting.run_options import FACE

    if not args.photos and not args.manifest:
        raise InputError("give a photo (or several, folders, glob patterns, or --manifest CSV)"
                         + (" before --landmarks, which takes the files after it" if args.landmarks else ""))
    FACE.config(_options(args))         # options checked before any photo is read
    check_fov(_options(args))
    _face_box(args)                     # --face-box's X,Y,W,H too
    if args.same_person:
        return run_same_person(args)
    if args.same_camera:
        raise InputError("--same-camera goes with --same-person (one person's photos fitted together)")
    args.landmarks = _single_landmarks(args.landmarks)
    if args.landmarks is not None:
        from softras_cl.fitting.run_records import refuse_face_choice
        refuse_face_choice(args.landmarks, False, args.face, args.face_box)
    if is_batch(args, args.photos):
        return run_batch(args, "face", args.photos, _options(args), args.landmarks)
    return run_one(args, args.photos[0])


def _single_landmarks(files: list[str] | None) -> str | None:
    """The one --landmarks file of a fit that is not --same-person (None: none given)."""
    if files is not None and len(files) > 1:
        raise InputError(f"--landmarks takes one file, got {len(files)}: several landmark files, one per "
                         "photo, go with --same-person (several photos of one person)")
    return None if files is None else files[0]


def run_one(args: argparse.Namespace, photo) -> int:
    """Fit one photo into --out (fitting.jobs.face_photo.FacePhotoJob)."""
    from softras_cl.fitting.jobs.face_photo import FacePhotoJob
    from softras_cl.io.outputs import check_output_folder

    check_output_folder(args.out)                 # before the photo is read and searched
    job = FacePhotoJob(photo, args.landmarks, _options(args), face=args.face, face_box=_face_box(args),
                       recorded=args)
    job.read()
    say_detection(job.landmarks)
    job.record()          # refuses a --face/--face-box that a landmark file beside the photo makes moot
    return run_job(args, job, "fit-face")


def _check_same_person(args: argparse.Namespace) -> list:
    """The photos of a --same-person run (files, folders, globs expanded, in order); InputError
    naming the options that do not go with it, before any photo is read."""
    from softras_cl.fitting.batch.items import expand_paths

    if args.same_camera and args.focal is not None:
        raise InputError("--same-camera fits one focal length for all the photos; --focal gives it already: "
                         "use one or the other")
    clashes = [option for option, given in (
        ("--all-faces", args.all_faces), ("--face", args.face is not None),
        ("--face-box", args.face_box is not None), ("--manifest", args.manifest is not None),
        ("--workers", args.workers is not None), ("--threads-per-worker", args.threads_per_worker is not None),
        ("--scheduler", args.scheduler is not None), ("--dense-landmarks", bool(args.dense_landmarks)))
        if given]
    if clashes:
        raise InputError(f"--same-person fits the photos together in this process, as one person with "
                         f"one face each (the largest when detected); it does not go with {', '.join(clashes)}")
    photos = expand_paths(args.photos, "face")
    if len(photos) < 2:
        raise InputError(f"--same-person needs at least two photos of the person, got {len(photos)} "
                         f"({', '.join(map(str, photos))}); for one photo leave --same-person out")
    if args.landmarks is not None and len(args.landmarks) != len(photos):
        raise InputError(f"--landmarks gives {len(args.landmarks)} files for {len(photos)} photos: with "
                         "--same-person give one per photo, in the photos' order (or none: each photo's "
                         "file beside it, else the detector)")
    return photos


def run_same_person(args: argparse.Namespace) -> int:
    """Several photos of one person into --out (fitting.jobs.face_photo.FaceViewsJob)."""
    from softras_cl.fitting.jobs.face_photo import FaceViewsJob

    from softras_cl.io.outputs import check_output_folder

    paths = _check_same_person(args)
    check_output_folder(args.out)
    job = FaceViewsJob(paths, args.landmarks, _options(args), same_camera=args.same_camera, recorded=args)
    job.read()
    for photo, landmarks in zip(paths, job.landmarks):
        say_detection(landmarks, str(photo))
    return run_job(args, job, "fit-face --same-person")
