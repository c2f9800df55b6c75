"""`softras-cl fit-body TARGET [--model FILE] --out DIR [--joints FILE]`."""
from __future__ import annotations

import argparse

from softras_cl.cli.batch import BATCH_EPILOG, add_batch_options, is_batch, run_batch
from softras_cl.cli.runs import add_fit_options, fit_values, run_fit, say_summary
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError

PHOTO_REQUIRED = ("silhouette_iou", "keypoint_error_px_full")    # finite, or the fit of a photo failed

DESCRIPTION = """\
Fit an SMPL-like body model (shape betas, joint rotations, global rotation, translation) to one
image seen by one frontal camera (paper sec. 5.3, figure 13). The target is a part-coloured
image (the model's part colours as fitting.body.part_colours draws them, the right hand red, on
--background), the same with an alpha channel, or with --silhouette a mask of the body; 2D
joints (--joints) add a reprojection term and a first joints-only stage. The image stages
follow a sigma/gamma schedule (--budget). Writes into --out: body.ply (fitted posed mesh with
part colours), overlay.png (fit blended over the target, joints drawn), params.json and
params.npz (fitted blocks, 3D joints and their pixels, camera K, R, t, metrics),
loss_curve.png, history.json, checkpoint.npz (best values so far, written as the fit goes),
run.json (inputs and options) and, last, complete.json. Every file is replaced atomically and
--out is locked while the fit runs. Ctrl-C or SIGTERM stops the fit and still writes every
output from the best values found so far (exit 130; --resume continues it).

A photo of a person (--input photo, or told apart from a part-coloured target by --input auto)
goes through a person detector (MediaPipe pose: 33 keypoints with their visibility, and its
person mask; extra "detect"), and the fit follows the keypoints (mapped onto the model's joints)
and the mask's outline through the soft silhouette (docs/body_photos.md). Its camera: --fov, or
the photo's EXIF focal length, at the distance where the model's torso is as long as the
detected one. It also writes keypoints.png (detected and fitted keypoints), mask.png (the
detector's mask) and figure.png; params.json holds the detection. A photo with no person exits 1.

Camera of a rendered target: at (0, --height, --distance) looking at (0, --height, 0) (the model's y up, the body
facing +z and standing near the origin), --fov degrees across the shorter image side.

""" + BATCH_EPILOG


def register(sub) -> None:
    """Add `fit-body` to the `softras-cl` subparsers `sub`."""
    from softras_cl.fitting.run_options import BODY

    p = sub.add_parser("fit-body", help="fit a body model to a photo of a person, a part-coloured image or a mask",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("targets", nargs="*", metavar="TARGET",
                   help="target image (PNG/JPEG/..., or .npy of linear values): a photo of a person, part "
                        "colours on --background, RGBA, or a mask (--input); several targets, folders or "
                        "glob patterns fit each into its own folder under --out")
    add_fit_options(p, BODY, files=True)
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--joints", default=None,
                   help="2D joints of the target, one row per model joint in the model's order: "
                        ".txt rows 'x y' or 'x y weight' (0-based pixels; weight 0 = unseen) or .npy")
    add_fit_options(p, BODY, files=False)
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted fit in --out from its checkpoint.npz (same target, "
                        "model, joints and options, else refused); finished stages are skipped")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a complete fit of another target (other joints or model) that --out "
                        "holds (else refused; one of the same inputs is replaced, saying so if its "
                        "options differ)")
    add_batch_options(p, "body")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _load_inputs(args, silhouette: bool):
    """(target, joints (J, 2) or None, joint weights or None, model, config); ValueError/OSError
    on bad input."""
    from softras_cl.fitting.body_files import read_joints, read_target
    from softras_cl.fitting.model_cache import load_model

    model = load_model("body", args.model)
    target = read_target(args.target, silhouette)
    joints, weights = (None, None) if args.joints is None else read_joints(args.joints, model.n_joints)
    return target, joints, weights, model, _config(args)


def _config(args: argparse.Namespace):
    """The BodyFitConfig of the options; InputError naming the option that is out of range."""
    from softras_cl.fitting.run_options import BODY

    return BODY.config(_options(args))


def _run_record(args: argparse.Namespace) -> dict:
    """What makes a run of this command: the inputs' digests and the options that change the fit."""
    from softras_cl.fitting.run_records import body_record

    return body_record(args.target, args.joints, _options(args))


def _options(args: argparse.Namespace) -> dict:
    """The options of a fit (softras_cl.fitting.run_options.BODY) from the command line."""
    from softras_cl.fitting.run_options import BODY

    return fit_values(args, BODY)


def run(args: argparse.Namespace) -> int:
    """One target into --out itself, or a batch (several targets, folders, globs, a manifest)."""
    if not args.targets and not args.manifest:
        raise InputError("give a target image (or several, folders, glob patterns, or --manifest CSV)")
    _config(args)                       # options checked before any target is read
    if is_batch(args, args.targets):
        return run_batch(args, "body", args.targets, _options(args), args.joints)
    args.target = args.targets[0]
    return run_one(args)


def run_one(args: argparse.Namespace) -> int:
    from softras_cl.fitting.recipes.body import fit_body, prepare_target
    from softras_cl.fitting.recipes.body_photo import input_kind
    from softras_cl.fitting.reports.body import write_outputs

    kind = input_kind(args.target, args.input, args.silhouette, _config(args).background, args.joints is not None)
    if kind == "photo":
        return run_photo(args)
    target, joints, weights, model, config = _load_inputs(args, kind == "mask")
    prepare_target(target, config.size, config.background, joints, weights, model.n_joints)
    def fit(folder):
        return fit_body(target, model, config, joints, weights, out_dir=folder,
                        progress=not args.no_progress, resume=args.resume)

    def write(fit, folder, metrics, seconds):
        return write_outputs(fit, target, folder, metrics=metrics, run_config=dict(fit=config, options=args),
                             extra=dict(target=str(args.target), seconds=seconds, budget=args.budget))

    required = ("silhouette_iou",) + (("joint_error_px_full",) if joints is not None else ())
    run = run_fit(args, "fit-body", _run_record(args), fit, required, write, [args.target])
    metrics = run.metrics
    joints_msg = (f", joint error {metrics['joint_error_px_full']:.1f} px" if "joint_error_px_full" in metrics
                  else "")
    say_summary("fit-body", run, f"silhouette IoU {metrics['silhouette_iou']:.3f}{joints_msg}")
    return EXIT_INTERRUPTED if run.interrupted else EXIT_OK


def run_photo(args: argparse.Namespace) -> int:
    """One photo of a person into --out: detection (before --out is touched), fit, outputs."""
    import numpy as np

    from softras_cl.fitting.model_cache import load_model
    from softras_cl.fitting.recipes.body_photo import fit_body_photo, read_person
    from softras_cl.fitting.reports.body import write_photo_outputs

    if args.joints is not None:
        raise InputError("--joints is for part-coloured targets and masks: a photo's keypoints are detected "
                         "(--input parts if the target is one)")
    model, config = load_model("body", args.model), _config(args)
    photo, detection, fov = read_person(args.target)
    print(f"person in {args.target}: box {np.round(detection.box).astype(int).tolist()}, torso visibility "
          f"{detection.score:.2f}; {detection.note}")

    def fit(folder):
        return fit_body_photo(photo.shape[:2], detection, model, config, args.budget, fov, out_dir=folder,
                              progress=not args.no_progress, resume=args.resume)

    def write(fit, folder, metrics, seconds):
        return write_photo_outputs(fit, photo, folder, metrics=metrics, run_config=dict(fit=config, options=args),
                                   extra=dict(target=str(args.target), input="photo", seconds=seconds,
                                              budget=args.budget))

    run = run_fit(args, "fit-body", _run_record(args), fit, PHOTO_REQUIRED, write, [args.target])
    m = run.metrics
    say_summary("fit-body", run, f"silhouette IoU {m['silhouette_iou']:.3f} against the person mask, keypoint "
                                 f"error {m['keypoint_error_px_full']:.1f} px over {m['keypoints_used']} keypoints")
    return EXIT_INTERRUPTED if run.interrupted else EXIT_OK
