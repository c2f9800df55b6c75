"""The options of each fit, declared once (:data:`FACE`, :data:`BODY`, :data:`FITS`).

An :class:`Option` says everything the rest of the package needs about one option of
`softras-cl fit-face` or `fit-body`: its flag and help (softras_cl.cli builds the argparse
arguments from it), how a manifest cell is read (fitting.batch.items), which field of the fit's
config it sets (:meth:`FitOptions.config`, used by the single-photo command and by a batch
item alike), and what the run record holds of it (fitting.run_records). A new option of a fit,
or a new fit, is one entry here.

``values`` below is a dict option name -> value with every option of the fit
(:meth:`FitOptions.values` fills the defaults).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from softras_cl.errors import InputError
from softras_cl.fitting.device.where import PLACES
from softras_cl.fitting.detection.faces import ORDER
from softras_cl.fitting.recipes import body_settings, face_settings
from softras_cl.fitting.recipes.body_settings import BodyFitConfig
from softras_cl.fitting.recipes.face_settings import (COARSE_MESH, DETECTED_LANDMARK_ROBUST, LANDMARK_MAPS,
                                                      FaceFitConfig)
from softras_cl.fitting.recipes.track_settings import TrackConfig

__all__ = ["Option", "FitOptions", "FACE", "BODY", "TRACK", "FITS", "yes_no", "FACE_HELP", "FACE_BOX_HELP"]


def yes_no(text: str) -> bool:
    """A switch's manifest cell: 1/0, true/false, yes/no (any case) -> bool; ValueError otherwise."""
    word = str(text).strip().lower()
    if word not in ("1", "0", "true", "false", "yes", "no"):
        raise ValueError(f"expected true/false, got {text!r}")
    return word in ("1", "true", "yes")


def _same(value):
    return value


@dataclass(frozen=True)
class Option:
    """One option of a fit.

    name: its key in batch items, manifest columns and run records; the flag is ``--name``
        with dashes.
    parse: text -> value (argparse's type and a manifest cell's reader); :func:`yes_no` makes
        a switch (``action="store_true"``).
    default, help, choices, metavar: as argparse has them.
    field: the keyword of the config's ``from_budget`` the option sets (None: it is not a
        config knob); to_config: option value -> that keyword's value.
    recorded: the run record's "options" hold it (it changes the fit).
    record_default: the record holds it at its default too; False for an option added after
        records were first written, so the complete.json files written before it still match
        a run at its default.
    file: a model file: the record's "inputs" hold its SHA-256, and a manifest cell is relative
        to the manifest's folder.
    """
    name: str
    parse: Callable[[str], Any]
    default: Any
    help: str
    field: str | None = None
    to_config: Callable[[Any], Any] = _same
    recorded: bool = True
    record_default: bool = True
    file: bool = False
    choices: tuple | None = None
    metavar: str | None = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def switch(self) -> bool:
        return self.parse is yes_no


@dataclass(frozen=True)
class FitOptions:
    """The options of one fit (every fit has a ``budget``) and how its config is made:
    ``make_config(budget, **changes)``, the config class's ``from_budget``."""
    command: str
    options: tuple[Option, ...]
    make_config: Callable[..., Any]

    def __getitem__(self, name: str) -> Option:
        for option in self.options:
            if option.name == name:
                return option
        raise KeyError(name)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.options)

    def values(self, given: dict) -> dict:
        """Every option's value: ``given``'s where it holds one that is not None, else the
        default. InputError for a name that is not an option."""
        unknown = sorted(set(given) - set(self.names))
        if unknown:
            raise InputError(f"unknown {self.command} options {unknown} "
                             f"(options: {', '.join(sorted(self.names))})")
        return {o.name: o.default if given.get(o.name) is None else given[o.name] for o in self.options}

    def config(self, given: dict):
        """The fit's config (FaceFitConfig, BodyFitConfig) of the options ``given`` (the
        defaults for the rest); InputError naming the option whose value is out of range."""
        values = self.values(given)
        changes = {o.field: o.to_config(values[o.name]) for o in self.options
                   if o.field is not None and values[o.name] is not None}
        with self.named_as_options():
            return self.make_config(values["budget"], **changes)

    @contextlib.contextmanager
    def named_as_options(self) -> Iterator[None]:
        """Reword a config's InputError ("fov_deg must be ...") with the option's flag ("--fov
        must be ...")."""
        flags = {o.field: o.flag for o in self.options if o.field is not None}
        try:
            yield
        except InputError as e:
            field, _, rest = str(e).partition(" ")
            if field not in flags:
                raise
            raise InputError(f"{flags[field]} {rest}") from None

    def parse_cell(self, column: str, text: str) -> tuple[str, Any]:
        """(option name, value) of a manifest cell; InputError naming the column."""
        name = column.strip().replace("-", "_")
        if name not in self.names:
            raise InputError(f"manifest column {column!r} is not an option of {self.command} "
                             f"(options: {', '.join(sorted(self.names))})")
        parse = self[name].parse
        try:
            return name, parse(text.strip())
        except ValueError as e:
            reason = str(e) if parse is yes_no else f"{text!r} is not a {parse.__name__}"
            raise InputError(f"manifest column {column!r}: {reason}") from None

    def record_options(self, values: dict) -> dict:
        """The run record's "options": the recorded options (see Option.record_default)."""
        return {o.name: values[o.name] for o in self.options
                if o.recorded and (o.record_default or values[o.name] != o.default)}


def _coarse_mesh(edges: float) -> float | None:
    """--coarse-mesh 0 means the model's own faces (the config's None)."""
    return edges or None


def _landmark_robust(deviations: float) -> float | None:
    """--landmark-robust 0 means plain squares (the config's None)."""
    return deviations or None


# the help of --face and --face-box, wherever a command chooses among the detected faces
FACE_HELP = (f"use face N (0 = the first; faces are numbered {ORDER}; the default is the largest; "
             "detect-landmarks lists them)")
FACE_BOX_HELP = ("use the face in this box (pixels: top-left corner, width, height): the detected face "
                 "that overlaps it best, else the landmarks found in the box itself")


def parse_background(text: str) -> tuple[float, float, float]:
    """'r,g,b' -> (r, g, b) floats; ValueError naming the option otherwise."""
    try:
        background = tuple(float(c) for c in str(text).split(","))
    except ValueError:
        background = ()
    if len(background) != 3:
        raise ValueError(f"--background must be 'r,g,b', got {text!r}")
    return background


def _face_options() -> tuple[Option, ...]:
    return (
        Option("model", str, None, "face model file: the project's .npz, BFM 2009 .mat, BFM 2017 .h5 or "
               "FLAME .pkl (default: the demo model shipped with softras-cl)", recorded=False, file=True),
        Option("model_landmarks", str, None, "landmark mapping for a model without the 68 iBUG landmarks: "
               "vertex indices or 'face b0 b1 b2' rows (.txt/.npy), or a FLAME landmark embedding",
               recorded=False, file=True),
        Option("budget", str, "default", "schedule: evaluations and sigma/gamma steps (default: default); "
               "`softras-cl bench face` shows what each costs and gains", choices=tuple(sorted(face_settings.BUDGETS))),
        Option("size", int, 256, "longest side in pixels of the working image the fit runs at (default 256)",
               field="size"),
        Option("photo_weight", float, None, "weight of the photometric term (default 100, i.e. pixel noise "
               "~0.1, with a robust kernel that caps what hair, glasses or shadows can pull; higher trusts "
               "the photo more; see docs/face_fitting.md and `softras-cl bench face`)", field="photo_weight"),
        Option("coarse_mesh", float, COARSE_MESH, "the first, half-resolution photometric stage draws the "
               "model's faces merged into cubes of EDGES median edge lengths: most of the full mesh's "
               f"triangles cover less than a pixel there (default {COARSE_MESH:g}; 0: the model's own "
               "faces; docs/face_fitting.md shows what the choices cost and gain)",
               field="coarse_mesh", to_config=_coarse_mesh, record_default=False, metavar="EDGES"),
        Option("focal", float, None, "focal length in pixels of the photo, if known (default: fitted)",
               field="focal"),
        Option("fov", float, None, "field of view in degrees across the shorter image side, if known roughly "
               "(a phone's main camera: about 50-55): the fit starts its focal length there and centres its "
               "prior on it, and still fits it; it wins over the photo's EXIF, which the fit uses otherwise "
               "(default: the EXIF, else 30 degrees across the longer side; --focal, which fixes the focal "
               "length, wins over it)", record_default=False, metavar="DEG"),
        Option("landmark_map", str, "auto", "which points of the model the 68 landmarks are tied to: 'model' "
               "(the model's own iBUG 300-W points, where an annotator or dlib puts them), 'face-mesh' (where "
               "MediaPipe Face Mesh puts them, read from the model's Face Mesh correspondence, as the demo "
               "model has it), 'auto' (the default: face-mesh for landmarks MediaPipe found, model for a "
               "landmark file or dlib; docs/face_fitting.md shows what it gains)",
               field="landmark_map", choices=LANDMARK_MAPS, record_default=False),
        Option("landmark_robust", float, DETECTED_LANDMARK_ROBUST, "a detector's landmarks: a point more than "
               "about C of its measured standard deviations off counts less than its square, so a gross miss "
               f"(a turned face's jaw on the cheek) stops pulling the shape (Geman-McClure; default "
               f"{DETECTED_LANDMARK_ROBUST:g}; 0: plain squares; a landmark file's points are always squared; "
               "docs/face_fitting.md shows what it gains)",
               field="detected_landmark_robust", to_config=_landmark_robust, metavar="C"),
        Option("dense_landmarks", float, 0.0, "add MediaPipe Face Mesh's 468 points as a landmark term, each "
               "point weighing WEIGHT times one of the 68 landmarks (default 0: off; needs landmarks "
               "detected by MediaPipe and a model with dense points, such as the demo model; not with "
               "--same-person; docs/face_fitting.md shows what it gains)",
               field="dense_weight", record_default=False, metavar="WEIGHT"),
        Option("n_id", int, None, "identity components to use (default: all)", field="n_id"),
        Option("n_exp", int, None, "expression components to use (default: all)", field="n_exp"),
        Option("n_albedo", int, None, "albedo components to use (default: all)", field="n_albedo"),
        Option("objective", str, "auto", "where the fit's objective runs: 'host' (numpy around the OpenCL "
               "rasteriser), 'device' (the model, render, photometric term and gradients in OpenCL buffers; "
               "needs float64) or 'auto' (the default: device on a GPU, host on a CPU; docs/speed.md)",
               field="objective", choices=PLACES, recorded=False),
    )


def _body_options() -> tuple[Option, ...]:
    d = BodyFitConfig()
    return (
        Option("model", str, None, "body model file: SMPL .pkl/.npz or the project's .npz "
               "(default: the demo model shipped with softras-cl)", recorded=False, file=True),
        Option("silhouette", yes_no, False, "the target is a mask of the body (alpha channel, or mean of "
               "the channels); the same as --input mask"),
        Option("input", str, "auto", "what the target is: 'photo' (a photo of a person: its keypoints and "
               "person mask are detected, docs/body_photos.md), 'parts' (part colours on --background, RGBA, "
               "or a grey mask), 'mask' (a mask of the body); 'auto' (the default): a target with --joints, "
               ".npy and RGBA images are parts, an RGB image is parts when a fifth of its pixels are the "
               "--background colour (a grey one: black), else a photo", choices=("auto", "photo", "parts", "mask"), record_default=False),
        Option("background", str, "0,0,0", "background colour of a part-coloured target, linear RGB "
               "'r,g,b' (default 0,0,0)", field="background", to_config=parse_background),
        Option("budget", str, "default", "schedule: evaluations and sigma/gamma steps (default: default); "
               "`softras-cl bench body` shows what each costs and gains", choices=tuple(sorted(body_settings.BUDGETS))),
        Option("size", int, d.size, f"longest side in pixels of the working image (default {d.size})",
               field="size"),
        Option("distance", float, d.distance, f"camera distance from the body in metres (default "
               f"{d.distance})", field="distance"),
        Option("height", float, d.height, f"camera and aim height in metres (default {d.height})",
               field="height"),
        Option("fov", float, d.fov_deg, f"field of view in degrees across the shorter image side (default "
               f"{d.fov_deg}; a photo's EXIF 35 mm equivalent focal length, when it has one, is used instead)",
               field="fov_deg"),
        Option("coarse_mesh", float, d.coarse_mesh, "the image stages draw the model's faces merged into "
               "cubes of EDGES median edge lengths of its template: most of the full mesh's triangles cover "
               f"less than a pixel at the working size (default {d.coarse_mesh:g}; 0: the model's own "
               "faces; the fitted body, its joints and every output use the full mesh; "
               "docs/body_fitting.md shows what the choices cost and gain)",
               field="coarse_mesh", to_config=_coarse_mesh, record_default=False, metavar="EDGES"),
        Option("robust_joints", float, None, "Geman-McClure scale in pixels (of the working image) for the "
               "joint term (default: plain squares; for a photo's keypoints 10%% of the working image's "
               "longer side)", field="robust_px", metavar="PX"),
        Option("objective", str, "auto", "where the image stages' objective runs: 'host' (numpy around the "
               "OpenCL rasteriser), 'device' (posing, render, silhouette and image terms and gradients in "
               "OpenCL buffers; needs float64) or 'auto' (the default: device on a GPU, host on a CPU; "
               "docs/speed.md)", field="objective", choices=PLACES, recorded=False),
    )


def _track_config(budget: str, **changes) -> TrackConfig:
    return TrackConfig(identity_budget=budget, **changes)


def _track_options() -> tuple[Option, ...]:
    d = TrackConfig()
    return (
        Option("model", str, None, "face model file, as for fit-face (default: the demo model shipped with "
               "softras-cl)", recorded=False, file=True),
        Option("fps", float, None, "frames per second of a folder of frames (frame k at k / FPS s); a video "
               "file's frames carry their own times"),
        Option("face", int, None, FACE_HELP + "; in the first frame with a face, then followed", metavar="N"),
        Option("face_box", str, None, FACE_BOX_HELP + "; in the first frame with a face, then followed",
               metavar="X,Y,W,H"),
        Option("chunk", int, 100, "frames per chunk of outputs: each chunk is written when done and "
               "--resume goes on at the first unfinished one (default 100)", metavar="FRAMES"),
        Option("scan", int, 150, "the identity's keyframes are chosen among the first FRAMES frames "
               "(default 150)", metavar="FRAMES"),
        Option("keyframes", int, d.keyframes, f"frames of the identity fit, chosen for pose variety (default "
               f"{d.keyframes})", field="keyframes"),
        Option("identity_passes", int, d.identity_passes, "joint fits of the identity: each after the first "
               "on the landmarks corrected by the detector offsets the one before found (default "
               f"{d.identity_passes}; 1: one fit on the landmarks as detected, in about half the time, for a "
               "worse identity; docs/face_tracking.md shows what each costs)", field="identity_passes", metavar="N"),
        Option("budget", str, d.identity_budget, f"schedule of the identity fit on the keyframes (default: "
               f"{d.identity_budget}; see fit-face --budget)", choices=tuple(sorted(face_settings.BUDGETS))),
        Option("size", int, d.size, f"working size in pixels of the identity fit (default {d.size})", field="size"),
        Option("frame_iters", int, d.frame_iters, f"evaluations of each frame's fit (default {d.frame_iters})",
               field="frame_iters"),
        Option("rotation_speed", float, d.rotation_speed, "temporal term: the head's rotation as a random walk "
               f"of this many radians per square-root second (smaller: steadier, slower to follow; default "
               f"{d.rotation_speed:g})", field="rotation_speed", metavar="RAD"),
        Option("translation_speed", float, d.translation_speed, "the same for its position, metres per "
               f"square-root second (default {d.translation_speed:g})", field="translation_speed", metavar="M"),
        Option("exp_speed", float, d.exp_speed, "the same for the expression, standard deviations per "
               f"square-root second (default {d.exp_speed:g})", field="exp_speed", metavar="STD"),
        Option("momentum", float, d.momentum, "how much of the last frame's motion the temporal terms expect "
               f"to go on, 0-1 (default {d.momentum:g})", field="momentum"),
        Option("light_speed", float, d.light_speed, "each frame's light, fitted to the frame's pixels on the face, "
               "as a random walk of this fraction of the video's ambient light per square-root second (default "
               f"{d.light_speed:g}; 0: the identity fit's light for every frame)", field="light_speed",
               metavar="FRACTION"),
        Option("smooth_lag", int, d.smooth_lag, "fixed-lag smoothing: each frame's pose and expression from a "
               "quadratic in time fitted to its own fit and those of FRAMES frames before and after it (each "
               f"frame comes out FRAMES frames later; default {d.smooth_lag}; 0: none)", field="smooth_lag",
               metavar="FRAMES"),
        Option("export_meshes", str, None, "also write the fitted face of every frame, in the camera's frame "
               "with albedo colours, to meshes/frame_NNNNNN.FORMAT as each frame is done (default: none)",
               choices=("ply", "obj"), metavar="{ply,obj}", record_default=False),
    )


FACE = FitOptions("fit-face", _face_options(), FaceFitConfig.from_budget)
BODY = FitOptions("fit-body", _body_options(), BodyFitConfig.from_budget)
FITS = {"face": FACE, "body": BODY}      # batch item kind -> its fit's options
TRACK = FitOptions("track-face", _track_options(), _track_config)
