"""`softras-cl fit-body TARGET [--model FILE] --out DIR [--joints FILE]`: the work is
fitting.jobs.body's (a photo of a person, or a renderer-made target); this module reads the
command line and prints."""
from __future__ import annotations

import argparse

from softras_cl.cli.batch import BATCH_EPILOG, add_batch_options, is_batch, run_batch
from softras_cl.cli.shared import (add_fit_options, add_out_option, add_progress_option, add_rerun_options,
                                   fit_values, run_job)
from softras_cl.errors import InputError

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
    add_out_option(p)
    p.add_argument("--joints", default=None,
                   help="2D joints of the target, one row per model joint in the model's order: "
                        ".txt rows 'x y' or 'x y weight' (0-based pixels; weight 0 = unseen) or .npy")
    add_fit_options(p, BODY, files=False)
    add_rerun_options(p, "fit-body")
    add_batch_options(p, "body")
    add_progress_option(p, "fit-body")
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict:
    """The options of a fit (softras_cl.fitting.run_options.BODY) from the command line."""
    from softras_cl.fitting.run_options import BODY

    return fit_values(args, BODY)


def run(args: argparse.Namespace) -> int:
    """One target into --out itself, or a batch (several targets, folders, globs, a manifest)."""
    from softras_cl.fitting.run_options import BODY

    if not args.targets and not args.manifest:
        raise InputError("give a target image (or several, folders, glob patterns, or --manifest CSV)")
    BODY.config(_options(args))         # options checked before any target is read
    if is_batch(args, args.targets):
        return run_batch(args, "body", args.targets, _options(args), args.joints)
    return run_one(args, args.targets[0])


def run_one(args: argparse.Namespace, target) -> int:
    """Fit one target into --out (fitting.jobs.body: the photo of a person's detection, or the
    target's and joints' checks, before --out is touched)."""
    from softras_cl.fitting.jobs.body import body_job
    from softras_cl.fitting.jobs.body_photo import BodyPhotoJob
    from softras_cl.io.outputs import check_output_folder

    check_output_folder(args.out)                 # before the target is read (a photo: and searched)
    job = body_job(target, args.joints, _options(args), recorded=args)
    job.read()
    if isinstance(job, BodyPhotoJob):
        print(job.describe())
    return run_job(args, job, "fit-body")
