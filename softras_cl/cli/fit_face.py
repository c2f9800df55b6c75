"""`softras-cl fit-face PHOTO [--landmarks FILE] [--model FILE] --out DIR`, and many photos:
`softras-cl fit-face PHOTO|FOLDER|GLOB ... [--manifest CSV] --out DIR` (softras_cl.cli.batch)."""
from __future__ import annotations

import argparse

from softras_cl.cli.batch import BATCH_EPILOG, add_batch_options, is_batch, run_batch
from softras_cl.cli.runs import named_as_options, run_fit, run_state
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError

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
name with that suffix), else the landmark detector (the "landmarks" extra), largest face first.

""" + BATCH_EPILOG


def register(sub) -> None:
    """Add `fit-face` to the `softras-cl` subparsers `sub`."""
    from softras_cl.fitting.recipes.face import BUDGETS

    p = sub.add_parser("fit-face", help="fit a face model to a photo and its 68 landmarks",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("photos", nargs="*", metavar="PHOTO",
                   help="the photo (PNG/JPEG/...; sRGB, decoded to linear RGB for fitting); several "
                        "photos, folders or glob patterns fit each into its own folder under --out")
    p.add_argument("--landmarks", default=None,
                   help="68 landmarks of the photo in the iBUG 300-W order: .pts (iBUG, 1-based), "
                        ".txt (68 rows 'x y', 0-based pixel centres) or .npy (68, 2) (default: "
                        "PHOTO.pts/.txt/.npy beside the photo, else detected)")
    p.add_argument("--all-faces", action="store_true",
                   help="fit every face the detector finds, each into its own folder under --out "
                        "(NAME-face0 for the largest, NAME-face1, ...); without it, the largest")
    p.add_argument("--model", default=None,
                   help="face model file: the project's .npz, BFM 2009 .mat, BFM 2017 .h5 or FLAME "
                        ".pkl (default: the demo model shipped with softras-cl)")
    p.add_argument("--model-landmarks", default=None,
                   help="landmark mapping for a model without the 68 iBUG landmarks: vertex indices "
                        "or 'face b0 b1 b2' rows (.txt/.npy), or a FLAME landmark embedding")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--budget", choices=sorted(BUDGETS), default="default",
                   help="schedule: evaluations and sigma/gamma steps (default: default); "
                        "`softras-cl bench face` shows what each costs and gains")
    p.add_argument("--size", type=int, default=256,
                   help="longest side in pixels of the working image the fit runs at (default 256)")
    p.add_argument("--photo-weight", type=float, default=None,
                   help="weight of the photometric term (default 10, i.e. pixel noise ~0.3; higher "
                        "trusts the photo more: better on clean images, worse with hair, glasses "
                        "or expressions the model lacks; see `softras-cl bench face`)")
    p.add_argument("--focal", type=float, default=None,
                   help="focal length in pixels of the photo, if known (default: fitted)")
    p.add_argument("--n-id", type=int, default=None, help="identity components to use (default: all)")
    p.add_argument("--n-exp", type=int, default=None, help="expression components to use (default: all)")
    p.add_argument("--n-albedo", type=int, default=None, help="albedo components to use (default: all)")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted fit in --out from its checkpoint.npz (same photo, "
                        "landmarks, model and options, else refused); finished stages are skipped")
    add_batch_options(p, "face")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict:
    """The options of a fit (softras_cl.fitting.batch.FACE_OPTIONS) from the command line."""
    from softras_cl.fitting.batch import FACE_OPTIONS

    return {k: getattr(args, k) for k in FACE_OPTIONS}


def _load_inputs(args):
    """(photo (H, W, 3) linear RGB, landmarks (68, 2), model); ValueError/OSError on bad input."""
    from softras_cl.io.images import read_image
    from softras_cl.fitting.landmark_detect import resolve_landmarks
    from softras_cl.fitting.models.face_loaders import load_demo_face_model, load_face_model

    photo = read_image(args.photo)[..., :3]
    landmarks = resolve_landmarks(args.photo, args.landmarks)[0].points
    if args.model is None:
        if args.model_landmarks is not None:
            raise ValueError("--model-landmarks needs --model (the demo model has its landmarks)")
        model = load_demo_face_model()
    else:
        model = load_face_model(args.model, landmarks=args.model_landmarks)
    return photo, landmarks, model


def _run_record(args: argparse.Namespace) -> dict:
    """What makes a run of this command: the inputs' digests and the options that change the fit
    (the same record a batch item of this photo has)."""
    from softras_cl.fitting.batch import face_landmarks_source, face_record

    return face_record(args.photo, face_landmarks_source(args.photo, args.landmarks), _options(args))


def run(args: argparse.Namespace) -> int:
    """One photo into --out itself, or a batch (several photos, folders, globs, a manifest)."""
    if not args.photos and not args.manifest:
        raise InputError("give a photo (or several, folders, glob patterns, or --manifest CSV)")
    _config(args)                       # options checked before any photo is read
    if is_batch(args, args.photos):
        return run_batch(args, "face", args.photos, _options(args), args.landmarks)
    args.photo = args.photos[0]
    return run_one(args)


CONFIG_OPTIONS = {"size": "--size", "focal": "--focal", "photo_weight": "--photo-weight",
                  "n_id": "--n-id", "n_exp": "--n-exp", "n_albedo": "--n-albedo"}


def _config(args: argparse.Namespace):
    """The FaceFitConfig of the options; InputError naming the option that is out of range."""
    from softras_cl.fitting.recipes.face import FaceFitConfig

    with named_as_options(CONFIG_OPTIONS):
        return FaceFitConfig.from_budget(args.budget, photo_weight=args.photo_weight, size=args.size,
                                         focal=args.focal, n_id=args.n_id, n_exp=args.n_exp,
                                         n_albedo=args.n_albedo)


def run_one(args: argparse.Namespace) -> int:
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.fitting.reports.face import write_outputs

    photo, landmarks, model = _load_inputs(args)
    config = _config(args)
    def fit(folder):
        return fit_face(photo, landmarks, model, config, out_dir=folder, progress=not args.no_progress,
                        resume=args.resume)

    def write(fit, folder, metrics, seconds):
        return write_outputs(fit, photo, folder, metrics=metrics, run_config=dict(fit=config, options=args),
                             extra=dict(photo=str(args.photo), seconds=seconds, budget=args.budget))

    run = run_fit(args, "fit-face", _run_record(args), fit, ("landmark_error_px_full", "psnr_face_db"), write)
    metrics = run.metrics
    print(f"fit-face {run_state(run.interrupted)} in {run.seconds:.1f} s: landmark error "
          f"{metrics['landmark_error_px_full']:.2f} px, face-region PSNR {metrics['psnr_face_db']:.1f} dB "
          f"(model), {metrics['psnr_face_db_textured']:.1f} dB (with the detail texture; sRGB); "
          f"outputs in {run.folder}/")
    return EXIT_INTERRUPTED if run.interrupted else EXIT_OK
