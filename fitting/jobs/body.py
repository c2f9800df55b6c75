"""Which body job a target takes: :func:`input_kind` tells a photo of a person from a
renderer-made target (part colours, RGBA, a mask), :func:`body_job` makes the job
(fitting.jobs.body_photo or body_target)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.jobs.body_photo import BodyPhotoJob
from softras_cl.fitting.jobs.body_target import BodyTargetJob
from softras_cl.fitting.run_options import BODY

__all__ = ["INPUTS", "input_kind", "body_job"]

INPUTS = ("auto", "photo", "parts", "mask")
AUTO_BACKGROUND_SHARE = 0.2     # "auto": an RGB image with at least this share of background pixels is parts


def input_kind(path, given: str = "auto", silhouette: bool = False, background=(0.0, 0.0, 0.0),
               joints: bool = False) -> str:
    """"photo", "parts" or "mask": what fit-body fits to the target file ``path``.

    ``given`` (--input) other than "auto" decides; --silhouette means "mask". "auto": a target
    given with 2D joints (``joints``: --joints, only for renderer-made targets) is "parts"; an .npy or
    an RGBA image is what a renderer makes ("parts": fitting.recipes.body reads a mask from an
    (H, W) one); an RGB image is "parts" when at least AUTO_BACKGROUND_SHARE of its pixels are the
    background colour to 8 bits, a grey one when that share is black (a mask), else a "photo": a
    part-coloured target or a mask is drawn on one flat colour, and photos practically never hold
    a fifth of their pixels at one exact colour."""
    if given not in INPUTS:
        raise InputError(f"--input must be one of {', '.join(INPUTS)}, got {given!r}")
    if silhouette:
        if given == "photo":
            raise InputError("--silhouette says the target is a mask; it cannot go with --input photo")
        return "mask"
    if given != "auto":
        return given
    from softras_cl.io.images import read_image
    from softras_cl.srgb import to_srgb

    if joints or Path(path).suffix.lower() == ".npy":
        return "parts"
    image = read_image(path)
    if image.ndim == 3 and image.shape[2] == 4:
        return "parts"
    # a grey image: a mask (on 0) or a grey photo; an RGB one: part colours (on --background) or a photo
    flat = np.zeros(1) if image.ndim == 2 else np.asarray(background, np.float64)
    on_background = np.abs(to_srgb(image) - to_srgb(flat)) < 0.5 / 255
    share = (on_background if image.ndim == 2 else on_background.all(-1)).mean()
    return "parts" if share >= AUTO_BACKGROUND_SHARE else "photo"


def body_job(target, joints=None, options: dict | None = None, recorded=None):
    """The job of fitting ``target`` (a path) with its 2D ``joints`` file (or None) and fit-body's
    ``options``: a BodyPhotoJob for a photo of a person, else a BodyTargetJob (read as a mask
    when --silhouette or --input mask says so). Options are checked before the target is read."""
    values = BODY.values(options or {})
    background = BODY.config(values).background
    kind = input_kind(target, values["input"], values["silhouette"], background, joints is not None)
    if kind == "photo":
        return BodyPhotoJob(target, joints, values, recorded=recorded)
    return BodyTargetJob(target, joints, values, silhouette=kind == "mask", recorded=recorded)
