"""One face fitted to several photos of the same person (`fit-face A B C --same-person`).

Every photo has the scene of the single-photo fit (fitting.recipes.face): its own working image,
landmarks, camera, FaceScene and FaceObjective. What is shared and what is not:

- shared by all photos: identity ``id`` (K_id,) and albedo ``albedo`` (K_alb,);
- per photo k: expression ``exp.k``, SH light ``sh.k`` (3, 9), ``rotation.k`` (3,),
  ``translation.k`` (3,) and ``focal.k`` (1,) in that photo's working pixels;
- with ``same_camera`` (photos of one size taken with one camera and zoom), one ``focal`` (1,)
  instead of ``focal.k``: the focal length in the first photo's working pixels, photo k's
  being ``focal * focal_scales[k]`` (the ratio of the photos' working-image scales).

The objective is the sum of the photos' single-photo objectives at their own values, with the
identity and albedo priors (and with a shared focal its prior) counted once (in the first
photo's objective only; the expression and light terms stay per photo). The gradient of a shared block is the sum of the photos'
gradients of it. With one photo the objective, the parameter layout and so the whole fit are
those of :func:`~softras_cl.fitting.recipes.face.fit_face`.

The photos' photometric terms are rendered together where their renders can share a call
(:func:`photo_terms`: one rasteriser call with a camera, light, depth range and face region per
view), with the same images and gradients as one render per photo.

The stages are the single fit's (:func:`~softras_cl.fitting.recipes.face.default_stages`), each
run jointly over all photos: a block free in the single fit's stage is free here in every photo.
The weights too, but for one (:func:`joint_config`): the landmarks weigh in the photometric
stages what they weigh in the landmark stage (LANDMARK_WEIGHT_PHOTO = 1, i.e. 2 px noise),
not 5x more as in the single fit (docs/face_views.md has the measurements).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.keypoints.plausibility import check_landmark_layout
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.recipes.face import (FaceFit, FaceFitConfig, FaceObjective, default_stages, landmark_robust,
                                             photo_terms_together, prepare_fit, tied_landmarks)
from softras_cl.fitting.recipes.face_settings import joint_config
from softras_cl.fitting.solver import FitResult, Stage, fit, too_close_result
from softras_cl.scene.renderer import SHARP

__all__ = ["SHARED", "PRIORS_ONCE", "view_block", "focal_scales", "FaceViewsObjective", "photo_terms", "FaceViewsFit",
           "joint_params", "joint_stages", "prepare_view", "fit_face_views"]

SHARED = ("id", "albedo")                  # blocks common to every photo of the person
PRIORS_ONCE = ("id_prior", "albedo_prior")  # their priors: counted in the first photo's objective only
CAMERA = ("focal",)                         # shared too with same_camera, its prior counted once
CAMERA_PRIORS = ("focal_prior",)
def view_block(name: str, k: int, shared=SHARED) -> str:
    """The joint fit's name of photo k's block ``name`` ("exp" -> "exp.0"; shared blocks keep
    their name)."""
    return name if name in shared else f"{name}.{k}"


def focal_scales(views: list[FaceObjective]) -> np.ndarray:
    """(N,) photo k's focal length in working pixels per unit of the first photo's: the ratio of
    the focal lengths each photo's fit starts from (the same full-photo focal at every photo's
    working-image scale)."""
    return np.array([v.focal0 / views[0].focal0 for v in views])


class FaceViewsObjective:
    """``(values, stage) -> (loss, grads, terms)`` for fitting.solver.fit: the sum over the
    photos of their FaceObjective (``views``, one per photo) at their own values.

    terms: each weighted term summed over the photos (``photo`` is the photometric term of all
    photos together). same_camera: one focal block for all photos (see the module docstring).
    """

    BLOCKS = ("id", "exp", "albedo", "sh", "rotation", "translation", "focal")

    def __init__(self, views: list[FaceObjective], same_camera: bool = False):
        if not views:
            raise InputError("views must hold at least one FaceObjective, got none")
        self.views = list(views)
        self.shared = SHARED + (CAMERA if same_camera else ())
        self.priors_once = PRIORS_ONCE + (CAMERA_PRIORS if same_camera else ())
        self.focal_scales = focal_scales(self.views) if same_camera else None

    def view_values(self, values: dict, k: int) -> dict:
        """Photo k's single-photo values (block names as in fit_face) out of the joint values."""
        view = {name: values[view_block(name, k, self.shared)] for name in self.BLOCKS}
        if self.focal_scales is not None:
            view["focal"] = view["focal"] * self.focal_scales[k]
        return view

    def view_stage(self, stage: Stage, k: int) -> Stage:
        """The stage photo k's objective sees: the shared priors weigh 0 after the first photo."""
        if k == 0:
            return stage
        return dataclasses.replace(stage, weights={n: (0.0 if n in self.priors_once else w)
                                                   for n, w in stage.weights.items()})

    def __call__(self, values: dict, stage: Stage):
        views = [self.view_values(values, k) for k in range(len(self.views))]
        if any(objective.scene.too_close(v) for objective, v in zip(self.views, views)):
            return too_close_result()
        loss, grads, terms = 0.0, {}, {}
        for k, (value, g, t) in enumerate(self._evaluate_views(views, stage)):
            loss += value
            for name, grad in g.items():
                key = view_block(name, k, self.shared)
                if name == "focal" and self.focal_scales is not None:
                    grad = grad * self.focal_scales[k]
                grads[key] = grads[key] + grad if key in grads else grad
            for name, v in t.items():
                terms[name] = terms.get(name, 0.0) + v
        return loss, grads, terms

    def _evaluate_views(self, views: list[dict], stage: Stage) -> list[tuple]:
        """Each photo's (loss, grads, terms) at its values (views: :meth:`view_values` of each),
        the photometric terms of the photos that can share a render rendered together
        (:func:`photo_terms`)."""
        stages = [self.view_stage(stage, k) for k in range(len(self.views))]
        geometries = [objective.geometry(v) for objective, v in zip(self.views, views)]
        photos = ([None] * len(views) if not stage.weights.get("photo") else
                  photo_terms(self.views, views, [g.world for g in geometries], stage))
        return [objective.combine(*args) for objective, *args in zip(self.views, views, stages, geometries, photos)]


def photo_terms(objectives: list[FaceObjective], values: list[dict], worlds: list, stage: Stage) -> list[tuple]:
    """Each photo's FaceObjective.photo (value, grads): the photos whose renders can share one
    call (objectives of one class on one queue, the same size, drawn faces and renderer settings
    at the stage's resolution) rendered as one batch (face.photo_terms_together): the same
    images and gradients as one render per photo (tests/fitting/recipes/test_face_views.py).
    objectives, values, worlds: per photo, its objective, values and world vertices (V, 3)."""
    starts = [objective.photo_start(v, stage) for objective, v in zip(objectives, values)]
    groups: dict = {}
    for k, (level, _) in enumerate(starts):
        s = level.scene.settings
        key = (type(level), level.scene.renderer.queue, level.scene.image_size, s.dtype, s.alpha_agg,
               level.scene.faces.tobytes())
        groups.setdefault(key, []).append(k)
    terms = [None] * len(objectives)
    for members in groups.values():
        together = photo_terms_together([starts[k][0] for k in members], [starts[k][1] for k in members],
                                        [worlds[k] for k in members], stage.sigma, stage.gamma)
        for k, (value, g) in zip(members, together):
            terms[k] = objectives[k].in_working_pixels(starts[k][0], value, g)
    return terms


def _block(params: ParamSet, name: str, new_name: str) -> Block:
    """Block ``name`` of params (current value, bounds, scale) under another name."""
    lower, upper = params.block_bounds(name)
    value = params.values()[name]
    scale = params.pack_grad({name: np.ones_like(value)}, [name]).reshape(value.shape)  # d/dx = d/dvalue * scale
    return Block(new_name, value, lower, upper, scale)


def joint_params(views: list[ParamSet], shared=SHARED) -> ParamSet:
    """The joint blocks from each photo's single-photo ParamSet (face_params): the ``shared``
    blocks (bounds, scale and start) of the first photo, every other block once per photo, in
    the single fit's block order (so one photo gives its layout exactly)."""
    blocks = []
    for name in views[0].names:
        if name in shared:
            blocks.append(_block(views[0], name, name))
        else:
            blocks += [_block(v, name, view_block(name, k)) for k, v in enumerate(views)]
    return ParamSet(blocks)


def joint_stages(stages: list[Stage], n_views: int, shared=SHARED) -> list[Stage]:
    """The single fit's stages run over all photos: each free per-photo block in every photo."""
    return [dataclasses.replace(s, free=tuple(dict.fromkeys(
        view_block(name, k, shared) for name in s.free for k in range(n_views)))) for s in stages]


@dataclass
class View:
    """One photo prepared for fitting: its FaceObjective (scene, working image, landmarks), the
    crop from the full photo and its single-photo ParamSet at the starting point."""
    objective: FaceObjective
    crop: object
    params: ParamSet


def prepare_view(photo, landmarks, model, config: FaceFitConfig, face_mesh_landmarks: bool = False) -> View:
    """Photo (H, W, 3) linear RGB and its landmarks (68, 2) pixels, Face Mesh's points or not (as
    fit_face's ``face_mesh_landmarks``) -> the View fit_face would start from (working image, camera, initial pose and
    light; the landmarks tied as config.landmark_map says). ResultError when the landmarks
    cannot be a face's (fitting.keypoints.plausibility.check_landmark_layout)."""
    tied, point_weights = tied_landmarks(model, config.landmark_map, face_mesh_landmarks,
                                         config.detected_landmark_weights)
    view = View(*prepare_fit(photo, landmarks, tied, config, point_weights=point_weights,
                             landmark_robust=landmark_robust(config, face_mesh_landmarks)))
    check_landmark_layout(landmarks)      # after prepare_fit's input checks (shape, area, size)
    return view


@dataclass
class FaceViewsFit:
    """What :func:`fit_face_views` returns.

    values: the joint blocks (see the module docstring); views: one FaceFit per photo (its
    values, scene, working image, crop, face region; all share ``result``); result: the
    solver's FitResult of the joint fit.
    """
    values: dict
    views: list[FaceFit]
    result: FitResult

    def metrics(self) -> dict:
        """Each photo's FaceFit.metrics() under ``views``, and their means (landmark error,
        face-region PSNR) under the single fit's names."""
        per_view = [v.metrics() for v in self.views]
        means = {k: float(np.mean([m[k] for m in per_view]))
                 for k in ("landmark_error_px", "landmark_error_px_full", "psnr_face_db")}
        return dict(means, views=per_view)


def _check_views(photos, landmarks, config: FaceFitConfig, same_camera: bool) -> None:
    if len(photos) < 1:
        raise InputError("photos must hold at least one photo, got none")
    if len(landmarks) != len(photos):
        raise InputError(f"landmarks must hold one (68, 2) array per photo: {len(photos)} photos, "
                         f"got {len(landmarks)} landmark arrays")
    if not same_camera:
        return
    if config.focal is not None:
        raise InputError(f"same_camera fits one focal length for all photos; config.focal gives it "
                         f"({config.focal}) for every photo already: use one or the other")
    sizes = {tuple(sorted(np.shape(p)[:2])) for p in photos}
    if len(sizes) > 1:
        raise InputError(f"same_camera needs photos of one size (one camera, uncropped: portrait or "
                         f"landscape), got sizes {sorted(sizes)}")


def fit_face_views(photos, landmarks, model, config: FaceFitConfig | None = None, out_dir=None,
                   progress: bool = True, resume: bool = False, same_camera: bool = False,
                   face_mesh_landmarks=None) -> FaceViewsFit:
    """Fit one identity and albedo of ``model`` to several photos of a person, each with its
    own pose, expression, light and (unless ``same_camera``) focal length.

    photos: sequence of (H_k, W_k, 3) linear RGB; landmarks: one (68, 2) pixel array per photo;
    config: used as given (None: ``joint_config(FaceFitConfig())``, the joint fit's defaults);
    out_dir, progress, resume: as for fit_face (one checkpoint.npz of the joint blocks);
    same_camera: the photos (all of one size, portrait or landscape) share one focal length,
    fitted (config.focal must be None); face_mesh_landmarks: whether each photo's landmarks are
    Face Mesh's points, as fit_face's (None: none are): each view ties its landmarks as
    config.landmark_map says for its own; their weight in the photometric stages is
    config.detected_landmark_weight_photo when every photo's are, else landmark_weight_photo
    (joint_config gives both the joint fit's LANDMARK_WEIGHT_PHOTO).
    """
    config = joint_config(FaceFitConfig()) if config is None else config
    _check_views(photos, landmarks, config, same_camera)
    if model.n_landmarks != ibug68.COUNT:
        raise ValueError(f"the face model defines {model.n_landmarks} landmarks; fitting needs the "
                         f"{ibug68.COUNT} iBUG points (pass a landmark mapping file with the model)")
    model = model.truncated(config.n_id, config.n_exp, config.n_albedo)
    on_mesh = [False] * len(photos) if face_mesh_landmarks is None else face_mesh_landmarks
    views = [prepare_view(p, lm, model, config, m) for p, lm, m in zip(photos, landmarks, on_mesh)]
    objective = FaceViewsObjective([v.objective for v in views], same_camera)
    stages = joint_stages(default_stages(config, fit_focal=config.focal is None, detected=all(on_mesh)),
                          len(views), objective.shared)
    result = fit(joint_params([v.params for v in views], objective.shared), objective, stages, out_dir=out_dir,
                 progress=progress, resume=resume)
    fits = []
    for k, view in enumerate(views):
        obj, values = view.objective, objective.view_values(result.values, k)
        mask = obj.mask if obj.mask is not None else obj.face_region(values, *SHARP)
        fits.append(FaceFit(values, obj.scene, obj.image, obj.target, view.crop, mask, result, obj))
    return FaceViewsFit(result.values, fits, result)
