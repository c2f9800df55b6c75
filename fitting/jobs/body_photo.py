"""A body from a photo of a person: `softras-cl fit-body` (--input photo, or a photo told apart
by --input auto) and a batch's body items run :class:`BodyPhotoJob`. It reads the photo once,
finds the person (fitting.detection.detect_person: 33 keypoints with their visibility and a
person mask), takes the camera's field of view from --fov or the photo's EXIF 35 mm equivalent
focal length (:func:`photo_fov`), fits the body with fitting.recipes.body_photo and writes
through fitting.reports.body."""
from __future__ import annotations

import math
import time
from pathlib import Path

from softras_cl.errors import InputError
from softras_cl.fitting.detection import detect_person
from softras_cl.fitting.jobs.run import FitJob
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.run_options import BODY
from softras_cl.fitting.run_records import body_record
from softras_cl.io.images import read_photo

__all__ = ["BodyPhotoJob", "photo_fov"]

FILM_DIAGONAL_MM = 43.27        # of the 36 x 24 mm frame of "35 mm equivalent" focal lengths
EXIF_IFD, FOCAL_35MM = 0x8769, 41989


def photo_fov(path, image_size) -> float | None:
    """Field of view (degrees) across the shorter side of an (H, W) photo from its EXIF 35 mm
    equivalent focal length (by the frame diagonal), or None when the file has none."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            focal = img.getexif().get_ifd(EXIF_IFD).get(FOCAL_35MM)
    except (OSError, ValueError, AttributeError):
        return None
    if not focal:
        return None
    h, w = image_size
    half_diagonal = math.atan(FILM_DIAGONAL_MM / 2 / float(focal))
    return math.degrees(2 * math.atan(math.tan(half_diagonal) * min(h, w) / math.hypot(h, w)))


class BodyPhotoJob(FitJob):
    """A body fit of one photo of a person. ``options``: fit-body's (fitting.run_options.BODY;
    missing: the defaults), checked here; ``joints`` must be None (a photo's keypoints are
    detected); ``recorded``: what params.json's provenance names as the run's options (default
    ``options``). :meth:`read` reads the photo and finds the person."""
    command = BODY.command
    required = ("silhouette_iou", "keypoint_error_px_full")

    def __init__(self, photo, joints=None, options: dict | None = None, *, recorded=None):
        if joints is not None:
            raise InputError("--joints is for part-coloured targets and masks: a photo's keypoints are "
                             "detected (--input parts if the target is one)")
        self.path = photo
        self.options = BODY.values(options or {})
        self.config = BODY.config(self.options)
        self.recorded = self.options if recorded is None else recorded
        self.photo = self.detection = self.fov = self.model = self.parts = None

    def read(self) -> None:
        """Read the photo, find the person (NoPersonError naming the photo when none), say which
        body parts are in view (InputError when too little is: check_enough_in_view), read the
        field of view from its EXIF, load the model; ResultError, before anything is written,
        when the camera would stand inside the body (fitting.recipes.body_photo.check_in_view:
        a --fov near 180 degrees)."""
        from softras_cl.fitting.recipes.body_photo import (check_enough_in_view, check_in_view, parts_in_view,
                                                           photo_setup)

        self.started = time.perf_counter()
        self.model = load_model("body", self.options["model"])
        self.photo = read_photo(self.path)
        self.detection = detect_person(self.photo.rgb8, str(self.path))
        self.parts = parts_in_view(self.detection.keypoints, self.detection.visibility, self.photo.rgb8.shape[:2])
        check_enough_in_view(self.parts, str(self.path))
        self.fov = photo_fov(self.path, self.photo.rgb8.shape[:2])
        check_in_view(photo_setup(self.photo.rgb8.shape[:2], self.detection, self.model, self.config, self.fov),
                      self.model)

    def describe(self) -> str:
        """Two lines: the person found (and, of several, which and why), and the body parts in
        view (fitting.recipes.body_photo.in_view_line)."""
        from softras_cl.fitting.recipes.body_photo import in_view_line

        box = [int(round(v)) for v in self.detection.box]
        return (f"person in {self.path}: box {box}, torso visibility {self.detection.score:.2f}; "
                f"{self.detection.note}\n{in_view_line(self.parts)}")

    def record(self) -> dict:
        return body_record(self.path, None, self.options)

    def files(self) -> list[str]:
        return [str(self.path)]

    def fit(self, folder: Path, progress: bool, resume: bool):
        from softras_cl.fitting.recipes.body_photo import fit_body_photo

        if self.photo is None:
            self.read()
        return fit_body_photo(self.photo.rgb8.shape[:2], self.detection, self.model, self.config,
                              self.options["budget"], self.fov, out_dir=folder, progress=progress, resume=resume)

    def write(self, fit, folder: Path, metrics: dict, seconds: float) -> dict:
        from softras_cl.fitting.reports.body import write_photo_outputs

        return write_photo_outputs(fit, self.photo.linear, folder, metrics=metrics,
                                   run_config=dict(fit=self.config, options=self.recorded),
                                   extra=dict(target=str(self.path), input="photo", seconds=seconds,
                                              budget=self.options["budget"]))

    def summary(self, metrics: dict) -> str:
        return (f"silhouette IoU {metrics['silhouette_iou']:.3f} against the person mask, keypoint error "
                f"{metrics['keypoint_error_px_full']:.1f} px over {metrics['keypoints_used']} keypoints")
