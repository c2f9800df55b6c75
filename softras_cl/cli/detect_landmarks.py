"""`softras-cl detect-landmarks PHOTO --out FILE.pts`: find the faces of a photo, choose one and
say why, and write its 68 iBUG points (MediaPipe by default, dlib opt-in; docs/landmarks.md)."""
from __future__ import annotations

import argparse
from pathlib import Path

from softras_cl.cli.shared import add_face_choice
from softras_cl.fitting.detection import BACKENDS, ORDER
from softras_cl.fitting.detection.dlib_backend import DEFAULTS as DLIB_OPTIONS     # argparse dest -> default


MAX_OVERLAY_SCALE = 4.0     # --overlay-scale's largest value: a 4000x3000 photo's overlay is 16000x12000


def overlay_scale(text: str) -> float:
    """--overlay-scale's value: a number in (0, MAX_OVERLAY_SCALE], else argparse's error (exit 2,
    naming the option) before anything is read or written (50 drew a 222 MB PNG in 171 s)."""
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value <= MAX_OVERLAY_SCALE:        # NaN fails too
        raise argparse.ArgumentTypeError(f"must be a number in (0, {MAX_OVERLAY_SCALE:g}], got {text!r}")
    return value


def face_out_path(out, index: int) -> Path:
    """Where --all-faces writes face `index` (its number): FILE.pts -> FILE_0.pts, FILE_1.pts..."""
    out = Path(out)
    return out.with_name(f"{out.stem}_{index}{out.suffix}")


def json_out_path(args: argparse.Namespace) -> Path:
    """--json, else --out with the suffix .json (FILE.pts -> FILE.json)."""
    return Path(args.json) if args.json else Path(args.out).with_suffix(".json")


def _run_detect(args: argparse.Namespace) -> int:
    from softras_cl.fitting.detection import parse_face_box, resolve_landmarks
    from softras_cl.io.images import read_rgb8
    from softras_cl.io.landmarks import write_pts

    image = read_rgb8(args.photo)
    _check_output_files(args)
    face_box = None if args.face_box is None else parse_face_box(args.face_box)
    found = resolve_landmarks(args.photo, None, beside=False, image=image, backend=args.backend,
                              all_faces=args.all_faces, face=args.face, face_box=face_box,
                              **_backend_options(args))
    detection = found[0].detection
    for line in detection.describe(written=[face.index for face in found] if args.all_faces else None):
        print(line)
    written = {}
    for face in found:
        out = face_out_path(args.out, face.index) if args.all_faces else Path(args.out)
        write_pts(out, face.points)
        written[face.index] = str(out)
        print(f"wrote {out} (68 iBUG points of face {face.index}, 1-based .pts pixel coordinates)")
    _write_json(args, detection, written)
    if args.overlay:
        _write_overlay(args, image, detection)
    return 0


def _backend_options(args: argparse.Namespace) -> dict:
    """The dlib options given (None: not given) for --backend dlib; InputError naming one given
    with another backend."""
    from softras_cl.errors import InputError

    given = {k: getattr(args, k) for k in DLIB_OPTIONS if getattr(args, k) is not None}
    if args.backend == "dlib":
        return {k: given.get(k, default) for k, default in DLIB_OPTIONS.items()}
    if given:
        option = "--" + next(iter(given)).replace("_", "-")
        raise InputError(f"{option} is an option of the dlib backend: add --backend dlib, or leave it out")
    return {}


def _write_json(args: argparse.Namespace, detection, written: dict) -> None:
    """Every face found (boxes, scores, 68 and 478 points), which was chosen and why, and which
    .pts file holds which face."""
    from softras_cl.io.outputs import write_json

    doc = dict(photo=str(args.photo), **detection.to_json())
    if args.all_faces:
        doc.update(chosen=sorted(written), reason="--all-faces: every face whose landmarks form a face")
    doc["written"] = {str(k): v for k, v in written.items()}
    path = json_out_path(args)
    write_json(path, doc)
    print(f"wrote {path} (every face found: boxes, scores, landmarks, which was chosen and why)")


def _write_overlay(args: argparse.Namespace, image, detection) -> None:
    from softras_cl.fitting.detection import draw_detection
    from softras_cl.io.images import image_format
    from softras_cl.io.outputs import atomic_path

    overlay = draw_detection(image, detection, scale=args.overlay_scale, all_landmarks=args.all_faces)
    with atomic_path(args.overlay) as tmp:
        overlay.save(tmp, format=image_format(args.overlay))
    print(f"wrote {args.overlay} (every face's box and number; the chosen one green, with its points)")


def _check_output_files(args: argparse.Namespace) -> None:
    """--out, the JSON (and --overlay) can be written, checked before detecting: OutputError
    (exit 3) naming the option, InputError for an --overlay that is no image file or a JSON
    path that is --out itself."""
    from softras_cl.errors import InputError
    from softras_cl.io.images import image_format
    from softras_cl.io.outputs import check_output_file

    check_output_file(face_out_path(args.out, 0) if args.all_faces else args.out, "--out")
    if json_out_path(args) == Path(args.out):
        raise InputError(f"--out {args.out}: the JSON of the faces would overwrite it; give --out a "
                         ".pts name or --json another file")
    check_output_file(json_out_path(args), "--json" if args.json else "--out (its .json)")
    if args.overlay:
        image_format(args.overlay, what="--overlay")
        check_output_file(args.overlay, "--overlay")


def register(sub) -> None:
    p = sub.add_parser(
        "detect-landmarks", help="find the faces of a photo and write one's 68 iBUG landmarks (.pts)",
        description="Find the faces of a photo, choose one (the largest, --face N or --face-box) and say "
                    "which and why, and write its 68 iBUG 300-W landmarks as an iBUG .pts file (1-based "
                    "pixel coordinates), the input of `softras-cl fit-face --landmarks`, plus a JSON of "
                    f"every face found. Faces are numbered {ORDER}. Backends: mediapipe (the default: "
                    "MediaPipe's face detectors on the whole image and on tiles for small faces, then "
                    "Face Mesh on each face's crop turned upright, 478 points, 68 of them standing for the iBUG "
                    'points; Apache-2.0; pip install "softras-cl[detect]") and dlib (opt-in: HOG '
                    "detector + the iBUG-trained 68-point predictor; its 68-point model is for "
                    'non-commercial use only; pip install "softras-cl[landmarks]").')
    p.add_argument("photo", metavar="PHOTO", help="image file (PNG, JPEG, ...)")
    p.add_argument("--out", required=True, metavar="FILE.pts",
                   help="where to write the chosen face's 68 landmarks (.pts); with --all-faces, "
                        "FILE_N.pts for face N")
    p.add_argument("--json", metavar="FILE.json", default=None,
                   help="where to write every face found (boxes, scores, 68 and 478 points, the choice "
                        "and why) (default: --out with the suffix .json)")
    p.add_argument("--overlay", metavar="FILE.png", default=None,
                   help="also write the photo with every face's box and number drawn, and the chosen "
                        "face's 68 points (every face's with --all-faces), to check them or choose a face")
    p.add_argument("--overlay-scale", type=overlay_scale, default=1.0, metavar="S",
                   help=f"scale of the overlay image relative to the photo, in (0, {MAX_OVERLAY_SCALE:g}] "
                        "(default 1)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="face detector: mediapipe (the default) or dlib (non-commercial 68-point model)")
    which = add_face_choice(p)
    which.add_argument("--all-faces", action="store_true",
                       help="write every face whose landmarks form a face, FILE_N.pts for face N")
    p.add_argument("--upsample", type=int, default=None, metavar="N",
                   help=f"dlib: double the image N times before detecting (default {DLIB_OPTIONS['upsample']}: "
                        "faces down to about 40 px; 0: about 80 px, 3x faster)")
    p.add_argument("--min-score", type=float, default=None, metavar="S",
                   help=f"dlib: drop detections scoring below S (default {DLIB_OPTIONS['min_score']}; dlib's own "
                        "threshold is 0)")
    p.set_defaults(func=_run_detect)
