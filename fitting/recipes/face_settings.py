"""The face fit's settings, without the renderer: its schedules (BUDGETS: the landmark stage's
evaluations and the photometric stages' sigma, gamma and evaluations), the limits of its inputs,
and FaceFitConfig, every knob of fitting.recipes.face.fit_face (its term weights included),
checked when made. Plain data on numpy: the command line reads it for its options and --help
without loading OpenCL."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from softras_cl.checks import number
from softras_cl.errors import InputError
from softras_cl.fitting.device.where import PLACES

__all__ = ["FaceFitConfig", "input_check", "joint_config", "LANDMARK_WEIGHT_PHOTO", "DETECTED_LANDMARK_WEIGHT_PHOTO", "DETECTED_LANDMARK_SIGMA_MM", "BUDGETS", "COARSE_MESH", "COARSE_SIGMA", "LANDMARK_MAPS", "CONTOUR_LANDMARKS",
           "MIN_SIZE", "MIN_LANDMARK_SPREAD", "ROBUST_SCALE", "MIN_ROBUST_SCALE"]

# Smallest working image (pixels a side). Measured on astronaut with the fast budget: the face
# region left after the 2-pixel erosion and the eye and mouth cut-outs has 0 pixels at 16 (PSNR
# NaN), 23 at 24, 66 at 32 and 245 at 48. A photo's face must therefore span at least
# MIN_SIZE / 2 pixels (the working image is twice the landmarks' extent).
MIN_SIZE = 32
# Smallest ratio of the landmarks' two singular values (centred): a face spans an area (0.92 on
# both shipped photos); points on a line, or all at one point, fix no pose.
MIN_LANDMARK_SPREAD = 0.05
# Photometric stages whose sigma is at least this render at half the working resolution (see
# FaceObjective.photo_level): the first stage of every budget. FaceFitConfig.coarse_sigma's default.
COARSE_SIGMA = 1e-4
# ... and draw a coarser face list (fitting.models.mesh_lod): the model's vertices clustered in
# cubes of this many median edge lengths (at half size a working pixel spans about two edges of
# the demo face). FaceFitConfig.coarse_mesh's default.
COARSE_MESH = 2.0
# Robust photometric term (FaceObjective.start_stage): Geman-McClure scale = ROBUST_SCALE x the
# median per-pixel linear-RGB error at a stage's start, never below MIN_ROBUST_SCALE (an error
# that small is noise, not something the model cannot explain).
ROBUST_SCALE = 2.0
MIN_ROBUST_SCALE = 0.1
# FaceFitConfig.contour_landmarks: how the jaw-line landmarks find their model points
CONTOUR_LANDMARKS = ("sliding", "fixed")
# FaceFitConfig.landmark_map: which model points the 68 landmarks are tied to (landmark_model)
LANDMARK_MAPS = ("auto", "model", "face-mesh")

# How far MediaPipe's 68 points (fitting.keypoints.face_mesh) lie from the model points the Face Mesh tie puts
# them on (fitting.recipes.face.landmark_model "face-mesh"), per iBUG point: a robust standard deviation per
# axis in mm at the face, sqrt(median |e|^2 / (2 ln 2)) of the 2D error e (a per-axis Gaussian's median
# squared 2D error is 2 ln 2 sigma^2; any bias is counted in), e in pixels over the face's pixels per mm
# (focal / depth). Measured on bench face's synthetic faces (softras_cl.bench.face: draw_faces, then
# detect_photos, 256 px), seeds 100, 101 and 102, 20 faces per bin of |yaw| 0-15, 15-45 and 45-75 each
# (151 faces detected: 60 / 57 / 34), against the tied points of the true face projected (hidden jaw
# points moved to the silhouette as the bench's silhouette_jaw moves them), pooled over the bins, each
# left/right pair given the RMS of its two. Per group, frontal (0-15) / 15-45 / 45-75 degrees: jaw 5.5 /
# 7.6 / 14.1 mm, brows 1.9 / 2.6 / 5.6, nose 2.5 / 3.3 / 5.3, eyes 1.5 / 1.8 / 3.4, lips 2.8 / 3.3 / 8.1:
# the jaw and lip points spread 3-4x and 2x more than the eyes' at every yaw. fit_face weighs landmarks
# a detector found by 1 / sigma^2 (FaceFitConfig.detected_landmark_weights, face.detected_landmark_weights);
# the 11 points the Face Mesh tie leaves at the model's own point (jaw 0-3, 13-16, inner lower lip 65-67)
# weigh 0 whatever their row says. Seeds 0, 5 and 6 were kept for choosing and evaluating.
DETECTED_LANDMARK_SIGMA_MM = np.array([
    9.9, 9.6, 7.4, 8.6, 6.1, 5.8, 6.3, 6.7, 6.5, 6.7, 6.3, 5.8, 6.1, 8.6, 7.4, 9.6, 9.9,   # jaw 0-16
    2.6, 2.7, 2.9, 2.6, 2.1, 2.1, 2.6, 2.9, 2.7, 2.6,                                    # brows 17-26
    2.2, 3.3, 3.6, 3.7, 3.5, 3.2, 3.4, 3.2, 3.5,                                         # nose 27-35
    1.9, 2.2, 1.9, 2.0, 1.6, 1.6, 2.0, 1.9, 2.2, 1.9, 1.6, 1.6,                          # eyes 36-47
    2.2, 3.0, 3.3, 3.6, 3.3, 3.0, 2.2, 3.2, 3.8, 4.0, 3.8, 3.2,                          # outer lips 48-59
    2.4, 3.3, 3.4, 3.3, 2.4, 5.7, 4.6, 5.7])                                             # inner lips 60-67

# FaceFitConfig.detected_landmark_weight_photo: a detector's landmarks weigh this much in the photometric
# stages relative to the landmark stage (a landmark file's weigh landmark_weight_photo, 5). A detector's
# points carry its biases (on bench face's 256 px faces 4-9 px at 45-75 degrees of yaw, the jaw and lips most),
# which at 5 the photometric stages could not undo; lighter, the photo decides the shape (docs/face_fitting.md,
# "How much a detector's landmarks count in the photometric stages").
DETECTED_LANDMARK_WEIGHT_PHOTO = 0.2

# FaceFitConfig.detected_landmark_robust: a detector's landmarks through Geman-McClure at this many of
# each point's standard deviations (losses.landmarks_2d_robust): a point the detector put far off (a
# turned face's jaw on the cheek) counts less than its square. Chosen on bench face, detected landmarks,
# seeds 9 and 10 (docs/face_fitting.md, "A robust landmark term for a detector's landmarks").
DETECTED_LANDMARK_ROBUST = 2.0

# Schedules: (sigma, gamma, evaluations) per photometric stage, and the landmark stage's budget.
BUDGETS = {
    "fast": dict(landmark_iters=100, photo_stages=((1e-4, 3e-3, 40), (1e-5, 1e-3, 60))),
    "default": dict(landmark_iters=150,
                    photo_stages=((1e-4, 3e-3, 100), (3e-5, 1e-3, 20), (1e-5, 1e-3, 100))),
    "thorough": dict(landmark_iters=200,
                     photo_stages=((1e-4, 3e-3, 80), (3e-5, 1e-3, 100), (1e-5, 1e-3, 150),
                                   (3e-6, 1e-3, 100))),
}


@dataclass(frozen=True)
class FaceFitConfig:
    """Every knob of :func:`fit_face`.

    size: the working image is a square around the landmarks (see :func:`prepare_photo`)
        shrunk to at most this many pixels a side (never enlarged).
    focal: focal length in pixels of the full photo, or None to fit it (initial guess from
        ``fov_deg`` across the longer side).
    landmark_iters / photo_stages: the schedule (see BUDGETS; photo_stages holds
        (sigma, gamma, evaluations) or (sigma, gamma, evaluations, stall_rel) per stage: the
        evaluations are the stage's cap, stall_rel its convergence stop, see stall_window).
    weights: loss-term weights by name (see the module docstring for their meaning).
    mask_erosion / forehead: the face region (see FaceObjective.face_region).
    robust_scale: the photometric term's Geman-McClure scale in multiples of the median
        per-pixel colour error at each photometric stage's start (see FaceObjective), or None
        for the plain sum of squared errors.
    stall_window: the window of the photometric stages' convergence stop, in evaluations
        (fitting.solver.Stage: a stage given a stall_rel ends once its best loss improved by at
        most stall_rel relative over stall_window evaluations; 0: run every stage's whole
        budget). The landmark stage, cheap and the start of everything after it, always runs
        to nlopt's own stop or its budget.
    coarse_sigma: photometric stages whose sigma is at least this compare the photo at half
        the working resolution (FaceObjective.photo_level; None: never).
    coarse_mesh: those stages draw the model's faces clustered in cubes of this many median
        edge lengths (fitting.models.mesh_lod.coarse_faces; None: the model's own faces).
    contour_landmarks: "sliding": each jaw-line landmark (iBUG 0-16) whose fixed model point
        is turned away from the camera is the model's occluding contour point nearest to it,
        re-chosen at every evaluation (fitting.recipes.contour); "fixed": every landmark is a fixed
        point of the model.
    landmark_map: which model points the 68 landmarks are tied to. "model": the model's own
        iBUG 300-W points, where an annotator (and dlib) puts them; "face-mesh": where MediaPipe
        Face Mesh puts the mesh points that stand for them (fitting.keypoints.face_mesh), from the
        model's Face Mesh correspondence (its dense points; a point the correspondence does not
        use keeps the model's own, with no weight: tied_landmarks); "auto": "face-mesh" for landmarks MediaPipe found
        (fit_face's ``face_mesh_landmarks``) on a model with that correspondence, else "model". On the
        demo face MediaPipe's points lie a mean 0.06 and up to 0.18 eye distances from the model's own (brows
        and jaw most): tied to the model's own, the fit takes that offset for shape.
    detected_landmark_weights: weigh landmarks a detector found on Face Mesh's points (fit_face's
        ``face_mesh_landmarks``, tied to them by landmark_map) by their measured noise, 1 / sigma^2 of
        DETECTED_LANDMARK_SIGMA_MM scaled to the same total weight (face.detected_landmark_weights);
        False, and always for landmarks from a file: the jaw line half, the other points 1.
    detected_landmark_robust: for landmarks a detector found (fit_face's ``face_mesh_landmarks``),
        the landmark term's Geman-McClure scale in each point's standard deviations
        (DETECTED_LANDMARK_ROBUST; FaceObjective's landmark_robust); None: squared distances, as
        always for landmarks from a file.
    landmark_weight_photo / detected_landmark_weight_photo: the landmark term's weight in the
        photometric stages, relative to its weight in the landmark stage, for landmarks from a
        file and for landmarks a detector found on Face Mesh's points (fit_face's
        ``face_mesh_landmarks``; DETECTED_LANDMARK_WEIGHT_PHOTO).
    dense_weight: weight of each dense landmark (MediaPipe Face Mesh's 468 points, those the
        model's dense_use marks) relative to one of the 68 landmarks, in every stage that has
        the landmarks; 0: no dense term. Needs a model with dense points (FaceModel.has_dense)
        and the photo's dense points (fit_face's ``dense``).
    n_id / n_exp / n_albedo: use only the first components of the model (None: all).
    dtype: rasteriser precision; float64 keeps line searches clean.
    objective: where the objective runs. "host": numpy around the rasteriser's kernels (the
        reference); "device": the model, render, photometric term and their vjps in OpenCL
        buffers (fitting.device; needs a device with float64); "auto": "device" on a GPU with
        float64, else "host" (on a CPU the device is the host's own cores: measured slower,
        docs/speed.md).
    """
    size: int = 256
    focal: float | None = None
    fov_deg: float = 30.0
    landmark_iters: int = BUDGETS["default"]["landmark_iters"]
    photo_stages: tuple = BUDGETS["default"]["photo_stages"]
    stall_window: int = 0
    coarse_sigma: float | None = COARSE_SIGMA
    coarse_mesh: float | None = COARSE_MESH
    weights: dict = field(default_factory=lambda: dict(
        landmarks=1.0 / 4.0, photo=100.0, id_prior=1.0, exp_prior=1.0,
        albedo_prior=1.0, sh_white=1000.0, focal_prior=1.0))
    landmark_weight_photo: float = 5.0    # landmark weight in the photometric stages, relative
    detected_landmark_weight_photo: float = DETECTED_LANDMARK_WEIGHT_PHOTO    # the same for a detector's
    robust_scale: float | None = ROBUST_SCALE
    mask_erosion: int = 2
    forehead: float = 0.15
    contour_landmarks: str = "sliding"
    landmark_map: str = "auto"
    detected_landmark_weights: bool = True
    detected_landmark_robust: float | None = DETECTED_LANDMARK_ROBUST
    dense_weight: float = 0.0
    n_id: int | None = None
    n_exp: int | None = None
    n_albedo: int | None = None
    dtype: str = "float64"
    objective: str = "auto"

    def __post_init__(self):
        _check_face_config(self)

    @classmethod
    def from_budget(cls, name: str, photo_weight: float | None = None, **changes) -> "FaceFitConfig":
        """The config of a schedule budget (BUDGETS), optionally with another photo weight."""
        if name not in BUDGETS:
            raise InputError(f"budget must be one of {sorted(BUDGETS)}, got {name!r}")
        config = cls(**{**BUDGETS[name], **changes})
        if photo_weight is None:
            return config
        input_check(lambda: number("photo_weight", photo_weight, positive=True))
        return dataclasses.replace(config, weights={**config.weights, "photo": float(photo_weight)})


def input_check(fn):
    """Run a softras_cl.checks check, turning its ValueError into InputError (exit 2)."""
    try:
        return fn()
    except InputError:
        raise
    except ValueError as e:
        raise InputError(str(e)) from None


def _int_at_least(name: str, value, low: int, why: str = "") -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"{name} must be an integer >= {low}{why}, got {value!r}")


def _check_face_config(c: FaceFitConfig) -> None:
    """InputError naming the first bad field of a FaceFitConfig."""
    _int_at_least("size", c.size, MIN_SIZE, f" (pixels a side of the working image; below {MIN_SIZE} "
                  "the face region left to fit the photo is a few pixels or none)")
    if c.focal is not None:
        input_check(lambda: number("focal", c.focal, positive=True))
    fov = input_check(lambda: number("fov_deg", c.fov_deg))
    if not 0 < fov < 180:
        raise InputError(f"fov_deg must be in (0, 180) degrees, got {c.fov_deg!r}")
    _int_at_least("landmark_iters", c.landmark_iters, 0)
    for i, stage in enumerate(c.photo_stages):
        if len(stage) not in (3, 4):
            raise InputError(f"photo_stages[{i}] must be (sigma, gamma, evaluations) or (sigma, gamma, "
                             f"evaluations, stall_rel), got {stage!r}")
        input_check(lambda: number(f"photo_stages[{i}] sigma", stage[0], positive=True))
        input_check(lambda: number(f"photo_stages[{i}] gamma", stage[1], positive=True))
        _int_at_least(f"photo_stages[{i}] evaluations", stage[2], 0)
        if len(stage) == 4 and input_check(lambda: number(f"photo_stages[{i}] stall_rel", stage[3])) < 0:
            raise InputError(f"photo_stages[{i}] stall_rel must be >= 0, got {stage[3]!r}")
    for name, w in c.weights.items():
        if input_check(lambda: number(f"weights[{name!r}]", w)) < 0:
            raise InputError(f"weights[{name!r}] must be >= 0, got {w!r}")
    for name in ("landmark_weight_photo", "detected_landmark_weight_photo"):
        if input_check(lambda: number(name, getattr(c, name))) < 0:
            raise InputError(f"{name} must be >= 0, got {getattr(c, name)!r}")
    _int_at_least("mask_erosion", c.mask_erosion, 0)
    _int_at_least("stall_window", c.stall_window, 0, " (evaluations; 0: no convergence stop)")
    if c.coarse_sigma is not None:
        input_check(lambda: number("coarse_sigma", c.coarse_sigma, positive=True))
    if c.coarse_mesh is not None:
        input_check(lambda: number("coarse_mesh", c.coarse_mesh, positive=True))
    if c.robust_scale is not None:
        input_check(lambda: number("robust_scale", c.robust_scale, positive=True))
    if c.detected_landmark_robust is not None:
        input_check(lambda: number("detected_landmark_robust", c.detected_landmark_robust, positive=True))
    if input_check(lambda: number("forehead", c.forehead)) < 0:
        raise InputError(f"forehead must be >= 0, got {c.forehead!r}")
    for name in ("n_id", "n_exp", "n_albedo"):
        if getattr(c, name) is not None:
            _int_at_least(name, getattr(c, name), 0)
    if c.contour_landmarks not in CONTOUR_LANDMARKS:
        raise InputError(f"contour_landmarks must be one of {', '.join(map(repr, CONTOUR_LANDMARKS))}, "
                         f"got {c.contour_landmarks!r}")
    if c.landmark_map not in LANDMARK_MAPS:
        raise InputError(f"landmark_map must be one of {', '.join(map(repr, LANDMARK_MAPS))}, "
                         f"got {c.landmark_map!r}")
    if not isinstance(c.detected_landmark_weights, (bool, np.bool_)):
        raise InputError(f"detected_landmark_weights must be True or False, got {c.detected_landmark_weights!r}")
    if input_check(lambda: number("dense_weight", c.dense_weight)) < 0:
        raise InputError(f"dense_weight must be >= 0 (0: no dense landmark term), got {c.dense_weight!r}")
    if c.dtype not in ("float32", "float64"):
        raise InputError(f"dtype must be 'float32' or 'float64', got {c.dtype!r}")
    if c.objective not in PLACES:
        raise InputError(f"objective must be one of {', '.join(map(repr, PLACES))}, got {c.objective!r}")


# FaceFitConfig.landmark_weight_photo of the joint fit. The single fit's 5 (10 before) keeps one
# photo's unexplained pixels from bending the shape; over several photos 10 made the landmarks'
# noise the limit (docs/face_views.md: bench face-views at 128 px, 10 against 1 and 5 against 1).
LANDMARK_WEIGHT_PHOTO = 1.0


def joint_config(config: FaceFitConfig) -> FaceFitConfig:
    """The config of a joint fit of several photos (fitting.recipes.face_views): ``config``
    with the joint fit's landmark weight in the photometric stages (LANDMARK_WEIGHT_PHOTO, for
    a file's landmarks and a detector's alike); everything else as given."""
    return dataclasses.replace(config, landmark_weight_photo=LANDMARK_WEIGHT_PHOTO,
                               detected_landmark_weight_photo=LANDMARK_WEIGHT_PHOTO)
