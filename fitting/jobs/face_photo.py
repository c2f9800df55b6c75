"""A face from photos: `softras-cl fit-face` and a batch's face items run these jobs.

:class:`FacePhotoJob`, one photo: it reads the photo once (softras_cl.io.images.read_photo: the
detector's 8-bit copy and the fit's linear one from one decode), takes its 68 landmarks from a
file, a file beside the photo or the detector (fitting.detection.resolve_landmarks: the largest
face, face N, the face in a box, or face N of --all-faces), fits them with
fitting.recipes.face.fit_face and writes through fitting.reports.face.
:class:`FaceViewsJob`, several photos of one person (--same-person): the same for each photo,
one joint fit (fitting.recipes.face_views), written by fitting.reports.face_views.

The focal length, first to last (:func:`with_focal_prior`): --focal fixes it; --fov (degrees across
the shorter side, as fit-body's) sets where the fit starts it and centres its prior; else a
photo's EXIF 35 mm equivalent focal length, when it has one, does (:func:`exif_focal`); else a 30
degree field of view across the longer side (FaceFitConfig.fov_deg) does. The fit still moves
it unless --focal gives it.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.detection import resolve_landmarks
from softras_cl.fitting.detection.files import check_beside
from softras_cl.fitting.jobs.run import FitJob
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.recipes.face_settings import joint_config
from softras_cl.fitting.run_options import FACE
from softras_cl.fitting.run_records import face_landmarks_source, face_record
from softras_cl.io.images import read_photo
from softras_cl.io.outputs import stable_names

__all__ = ["FacePhotoJob", "FaceViewsJob", "face_model", "face_landmarks", "check_uncut", "exif_focal",
           "longer_side_fov", "with_focal_prior", "check_fov"]

REQUIRED = ("landmark_error_px_full", "psnr_face_db")     # finite, or the fit failed


def longer_side_fov(fov_short: float, image_size) -> tuple[float, float]:
    """(focal length in pixels, field of view in degrees across the longer side) of an (H, W)
    photo whose field of view across the shorter side is ``fov_short`` degrees."""
    focal = 0.5 * min(image_size) / math.tan(math.radians(fov_short) / 2.0)
    return focal, math.degrees(2.0 * math.atan(0.5 * max(image_size) / focal))


def exif_focal(path, image_size) -> tuple[float, float] | None:
    """(focal length in pixels of an (H, W) photo, its field of view in degrees across the longer
    side) from the photo's EXIF 35 mm equivalent focal length (by the frame diagonal, as
    fitting.jobs.body_photo.photo_fov reads it), or None when the file has none."""
    from softras_cl.fitting.jobs.body_photo import photo_fov

    fov_short = photo_fov(path, image_size)
    return None if fov_short is None else longer_side_fov(fov_short, image_size)


def check_fov(options: dict) -> None:
    """InputError, before anything is read, for a --fov that is no field of view (finite, in
    (0, 180) degrees)."""
    fov = options.get("fov")
    if fov is not None and not (math.isfinite(fov) and 0.0 < fov < 180.0):
        raise InputError(f"--fov must be a field of view in degrees, above 0 and below 180, got {fov!r}")


def with_focal_prior(config, fov: float | None, path, image_size):
    """(config, where its focal length comes from: "--focal", "--fov", "exif" or "prior") for an
    (H, W) photo. ``config`` (FaceFitConfig) as given when it fixes the focal length (--focal
    wins: the user knows it, e.g. a calibrated camera); else with fov_deg from ``fov`` (--fov,
    degrees across the shorter side): the user's word beats the file's, which a crop or an
    editor's resize carries over from the whole frame; else from the EXIF (:func:`exif_focal`): a
    camera's own record beats the typical 30 degrees; else as given ("prior"). fov_deg sets the
    fit's initial focal length and the centre of its prior; the fit still moves it."""
    if config.focal is not None:
        return config, "--focal"
    if fov is not None:
        return dataclasses.replace(config, fov_deg=longer_side_fov(fov, image_size)[1]), "--fov"
    found = exif_focal(path, image_size)
    if found is None:
        return config, "prior"
    return dataclasses.replace(config, fov_deg=found[1]), "exif"


def face_model(options: dict):
    """The face model of the options ``model`` (and ``model_landmarks``; the demo model when
    None); InputError when it lacks what ``landmark_map`` asks for."""
    from softras_cl.fitting.recipes.face import check_landmark_map

    values = FACE.values(options)
    if values["model"] is None and values["model_landmarks"] is not None:
        raise ValueError("--model-landmarks needs --model (the demo model has its landmarks)")
    model = load_model("face", values["model"], values["model_landmarks"])
    with FACE.named_as_options():
        check_landmark_map(values["landmark_map"], model)
    return model


def face_landmarks(photo, landmarks=None, face: int | None = None, face_box=None, all_faces: bool = False):
    """The landmarks of one face of a photo (fitting.detection.PhotoLandmarks): a file (given, or
    beside the photo), else the detected face ``face`` (None: the largest) or the one in
    ``face_box``; with ``all_faces``, face number ``face`` among those whose landmarks form a
    face. ``photo``: a softras_cl.io.images.Photo (decoded once)."""
    if not all_faces:
        found = resolve_landmarks(photo.path, landmarks, image=photo.rgb8, face=face, face_box=face_box)
    else:
        found = [f for f in resolve_landmarks(photo.path, landmarks, image=photo.rgb8, all_faces=True)
                 if f.index == face]
        if not found:
            raise InputError(f"face {face} of {photo.path} is no longer found among the faces whose "
                             "landmarks form a face")
    if found[0].source == "beside":
        check_beside(found[0].path, found[0].points, photo.rgb8, str(photo.path))
    check_uncut(found[0], photo)
    return found[0]


def check_uncut(found, photo) -> None:
    """InputError when detected landmarks (fitting.detection.PhotoLandmarks) reach past the
    border of the photo (a Photo): the detector found a face the photo cuts, whose landmarks it
    places where the face would go on. The fit needs every landmark on the photo (a file's
    points are checked as the file is read)."""
    if found.detection is None:
        return
    h, w = photo.rgb8.shape[:2]
    x, y = found.points[:, 0], found.points[:, 1]
    outside = np.flatnonzero((x < -0.5) | (x > w - 0.5) | (y < -0.5) | (y > h - 0.5))
    if outside.size:
        raise InputError(f"face {found.index} found in {photo.path} is cut by the photo's border: its "
                         f"landmarks {_ranges(outside)} lie outside the {w}x{h} photo; fit-face fits whole "
                         "faces: give a photo (or a crop) with the whole face in it, or the face's 68 points "
                         "on the photo as a file (--landmarks)")


def _ranges(indices) -> str:
    """Sorted integers as "0-3, 7, 13-16"."""
    runs, start = [], None
    for i, k in enumerate(indices):
        if start is None:
            start = k
        if i + 1 == len(indices) or indices[i + 1] != k + 1:
            runs.append(f"{start}" if start == k else f"{start}-{k}")
            start = None
    return ", ".join(runs)


class FacePhotoJob(FitJob):
    """A face fit of one photo. ``options``: fit-face's (fitting.run_options.FACE; missing: the
    defaults), checked here, before any file is read. ``landmarks``: a landmark file, or None (a
    file beside the photo, else the detector); ``face``, ``face_box``, ``all_faces``: which
    detected face (see face_landmarks). ``recorded``: what params.json's provenance names as the
    run's options (default ``options``). :meth:`read` reads the inputs; the runners call the rest."""
    command = FACE.command
    required = REQUIRED

    def __init__(self, photo, landmarks=None, options: dict | None = None, *, face: int | None = None,
                 face_box=None, all_faces: bool = False, recorded=None):
        self.path, self.landmarks_file = photo, landmarks
        self.options = FACE.values(options or {})
        check_fov(self.options)
        self.face, self.face_box, self.all_faces = face, face_box, all_faces
        self.config = FACE.config(self.options)
        self.recorded = self.options if recorded is None else recorded
        self.photo = self.landmarks = self.model = self.dense = None
        self.focal_source = None

    def read(self) -> None:
        """Read the photo, find its landmarks (the detection, when detected, is in
        ``self.landmarks.detection``), load the model; ValueError/OSError on bad input,
        ImplausibleFaceError (exit 1) for a detected face that is no face."""
        from softras_cl.fitting.detection import landmarks_beside
        from softras_cl.fitting.recipes.face import check_dense_inputs, detected_dense
        from softras_cl.fitting.run_records import refuse_face_choice

        self.started = time.perf_counter()
        beside = None if self.landmarks_file is not None else landmarks_beside(self.path)
        if beside is not None:          # before the file is checked against the detector's faces
            refuse_face_choice(beside, True, self.face, self.face_box)
        self.photo = read_photo(self.path)
        self.config, self.focal_source = with_focal_prior(self.config, self.options["fov"], self.path,
                                                          self.photo.rgb8.shape[:2])
        self.landmarks = face_landmarks(self.photo, self.landmarks_file, self.face, self.face_box, self.all_faces)
        self.model = face_model(self.options)
        self.dense = detected_dense(self.landmarks.face)
        check_dense_inputs(self.config, self.model, self.dense)

    def record(self) -> dict:
        source = face_landmarks_source(self.path, self.landmarks_file, self.face, self.face_box)
        return face_record(self.path, source, self.options)

    def files(self) -> list[str]:
        return [str(self.path)]

    def fit(self, folder: Path, progress: bool, resume: bool):
        from softras_cl.fitting.recipes.face import fit_face

        if self.photo is None:
            self.read()
        return fit_face(self.photo.linear, self.landmarks.points, self.model, self.config, out_dir=folder,
                        progress=progress, resume=resume, dense=self.dense,
                        face_mesh_landmarks=self.landmarks.on_face_mesh)

    def write(self, fit, folder: Path, metrics: dict, seconds: float) -> dict:
        from softras_cl.fitting.reports.face import write_outputs

        return write_outputs(fit, self.photo.linear, self.landmarks, folder, metrics=metrics,
                             run_config=dict(fit=self.config, options=self.recorded),
                             extra=dict(photo=str(self.path), seconds=seconds, budget=self.options["budget"],
                                        focal_source=self.focal_source))

    def summary(self, metrics: dict) -> str:
        return (f"landmark error {metrics['landmark_error_px_full']:.2f} px, face-region PSNR "
                f"{metrics['psnr_face_db']:.1f} dB (model), {metrics['psnr_face_db_textured']:.1f} dB "
                "(with the detail texture; sRGB)")


class FaceViewsJob(FitJob):
    """One person in several photos (at least two): one identity and albedo fitted to all,
    each photo with its own pose, expression, light and (unless ``same_camera``) focal length.
    ``landmarks``: one file per photo, in order, or None (each photo's file beside it, else the
    detector's largest face). ``options``, ``recorded``: as FacePhotoJob's."""
    command = FACE.command
    required = REQUIRED

    def __init__(self, photos: list, landmarks: list | None = None, options: dict | None = None, *,
                 same_camera: bool = False, recorded=None):
        self.paths, self.landmark_files = list(photos), landmarks or [None] * len(photos)
        self.options = FACE.values(options or {})
        if self.options["fov"] is not None:
            raise InputError("--fov is a single photo's: --same-person starts every photo at 30 degrees across "
                             "its longer side and fits each focal length (or one, with --same-camera)")
        self.config = joint_config(FACE.config(self.options))
        self.same_camera = same_camera
        self.recorded = self.options if recorded is None else recorded
        self.photos = self.landmarks = self.model = None

    def read(self) -> None:
        """Read every photo once and find its landmarks, then load the model."""
        self.started = time.perf_counter()
        self.photos = [read_photo(p) for p in self.paths]
        self.landmarks = [face_landmarks(photo, f) for photo, f in zip(self.photos, self.landmark_files)]
        self.model = face_model(self.options)

    def inputs(self) -> list[dict]:
        """Each photo's input record for params.json: its path and SHA-256, its landmark file and
        what the run record says of its landmarks."""
        from softras_cl.io.outputs import file_sha256

        return [dict(photo=str(p), photo_sha256=file_sha256(p), landmarks=None if f is None else str(f),
                     landmarks_source=face_landmarks_source(p, f)) for p, f in zip(self.paths, self.landmark_files)]

    def record(self) -> dict:
        records = [face_record(p, face_landmarks_source(p, f), self.options)
                   for p, f in zip(self.paths, self.landmark_files)]
        return dict(command="fit-face --same-person", inputs=[r["inputs"] for r in records],
                    options=dict(records[0]["options"], same_camera=self.same_camera))

    def files(self) -> list[str]:
        return [str(p) for p in self.paths]

    def fit(self, folder: Path, progress: bool, resume: bool):
        from softras_cl.fitting.recipes.face_views import fit_face_views

        if self.photos is None:
            self.read()
        return fit_face_views([p.linear for p in self.photos], [f.points for f in self.landmarks], self.model,
                              self.config, out_dir=folder, progress=progress, resume=resume,
                              same_camera=self.same_camera,
                              face_mesh_landmarks=[f.on_face_mesh for f in self.landmarks])

    def write(self, fit, folder: Path, metrics: dict, seconds: float) -> dict:
        from softras_cl.fitting.reports.face_views import write_views_outputs

        return write_views_outputs(fit, [p.linear for p in self.photos], self.landmarks, stable_names(self.paths),
                                   self.inputs(), folder, metrics, run_config=dict(fit=self.config, options=self.recorded),
                                   extra=dict(seconds=seconds, budget=self.options["budget"]))

    def summary(self, metrics: dict) -> str:
        return (f"{len(self.paths)} photos, mean landmark error {metrics['landmark_error_px_full']:.2f} px, "
                f"mean face-region PSNR {metrics['psnr_face_db']:.1f} dB (model, sRGB)")
