"""Run records: what makes a fit (a SHA-256 of each input file and the options that change it),
the same for `softras-cl fit-face`/`fit-body` (run.json, complete.json, ``--resume``) and for a
batch item (its skip when finished). The options come from fitting.run_options."""
from __future__ import annotations

import json
from pathlib import Path

from softras_cl.errors import InputError
from softras_cl.fitting.run_options import BODY, FACE, FitOptions
from softras_cl.io.outputs import COMPLETE_RECORD, OUTPUTS, file_sha256, json_safe, missing_outputs

__all__ = ["face_landmarks_source", "refuse_face_choice", "face_record", "body_record", "completed"]


def _model_inputs(fit: FitOptions, values: dict) -> dict:
    """The record's digest of each model file option (None: not given)."""
    return {o.name: None if values[o.name] is None else file_sha256(values[o.name])
            for o in fit.options if o.file}


def face_landmarks_source(photo, landmarks=None, face: int | None = None, face_box=None) -> str:
    """What the run record says about a face's landmarks: the SHA-256 of the file (given, or
    beside the photo), else which detector and which face (``face``: the N-th, ``face_box``:
    (x, y, w, h) the face in that box; neither: the largest, face 0). InputError when a face is
    chosen but the landmarks come from a file (a file holds one face: nothing to choose)."""
    from softras_cl.fitting import detection as detect

    file = landmarks if landmarks is not None else detect.landmarks_beside(photo)
    if file is not None:
        refuse_face_choice(file, landmarks is None, face, face_box)
        return file_sha256(file)
    if face_box is not None:
        chosen = "the face in box " + ",".join(f"{v:g}" for v in face_box)
    else:
        chosen = f"face {face or 0}"
    return f"detected by {detect.default_backend() or 'no detector'}, {chosen}"


def refuse_face_choice(file, beside: bool, face: int | None, face_box) -> None:
    """InputError naming --face/--face-box when one is given for landmarks read from ``file``
    (``beside``: found beside the photo, else given as --landmarks)."""
    if face is None and face_box is None:
        return
    option = "--face" if face is not None else "--face-box"
    where = f"the file beside the photo, {file}" if beside else f"--landmarks {file}"
    raise InputError(f"{option} chooses among the faces the detector finds, but the landmarks come from "
                     f"{where} (one face, no detection): leave {option} out, or "
                     + ("move that file away" if beside else "leave --landmarks out") + " to detect")


def face_record(photo, landmarks: str | None, options: dict) -> dict:
    """The run record of a face fit: dict(command, inputs (SHA-256 per file), options).
    ``landmarks``: what face_landmarks_source returned; ``options``: fit-face's (FACE), the
    defaults for those missing or None."""
    values = FACE.values(options)
    inputs = dict(photo=file_sha256(photo), landmarks=landmarks, **_model_inputs(FACE, values))
    return dict(command=FACE.command, inputs=inputs, options=FACE.record_options(values))


def body_record(target, joints, options: dict) -> dict:
    """The run record of a body fit: dict(command, inputs (SHA-256 per file), options);
    ``options``: fit-body's (BODY), the defaults for those missing or None."""
    values = BODY.values(options)
    inputs = dict(target=file_sha256(target), **_model_inputs(BODY, values),
                  joints=None if joints is None else file_sha256(joints))
    return dict(command=BODY.command, inputs=inputs, options=BODY.record_options(values))


def completed(folder: Path, record: dict) -> dict | None:
    """folder/complete.json when it holds ``record`` and is a finished run whose outputs are all
    there (when it lists them, OUTPUTS: each file with its size), else None."""
    try:
        doc = json.loads((Path(folder) / COMPLETE_RECORD).read_text())
    except (OSError, ValueError):
        return None
    want = json.loads(json.dumps(json_safe(record), default=str))
    if not (isinstance(doc, dict) and doc.get("status") == "done" and all(doc.get(k) == v for k, v in want.items())):
        return None
    if OUTPUTS in doc and missing_outputs(folder, doc[OUTPUTS]):
        return None
    return doc
