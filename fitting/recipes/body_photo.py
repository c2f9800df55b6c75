"""Body fitting to a photo of a person: detected 2D keypoints and the person mask.

Built on fitting.recipes.body (its BodyScene, priors, joint limits, Geman-McClure reprojection
and the solver); what is new here:

- inputs: a PersonDetection (fitting.detection.people: 33 keypoints with visibility and a
  person mask), mapped onto the model by fitting.keypoints.pose33 (KEYPOINT_MAP); each
  keypoint's weight is the map's weight times the detector's visibility, and 0 when the
  visibility is below MIN_VISIBILITY or the point lies outside the photo (a portrait's legs):
  what is not seen is left to the pose and shape priors;
- the camera: the photo's field of view across its shorter side (``fov_deg`` of fit_body_photo:
  fitting.jobs.body_photo reads it from the EXIF 35 mm equivalent focal length when the file has
  one; else the config's fov_deg), and its
  distance from the person's size (:func:`camera_distance`: the model's torso against the
  detected one, in pixels), so that the body stands near the origin, where the translation
  prior and the near/far range expect it;
- terms (sums, as in fitting.recipes.body): ``torso`` (the reprojection of the shoulders and hips
  alone), ``keypoints`` (all mapped keypoints), both ``s^2 rho`` Geman-McClure in working px^2
  with s = ROBUST_FRACTION of the working image's longer side (or the config's robust_px);
  ``depth`` (each keypoint's depth relative to the hips against the detector's rough metric
  estimate, the same kernel, at a small weight: it tells a limb turned towards the camera from
  one turned away, which the image alone leaves open); the ``silhouette`` of the soft render
  against the mask (fitting.recipes.body); where the mask misses part of the person
  (:func:`mask_misses`) the silhouette leaves out the pixels around those limbs outside the
  mask (:func:`limb_care`); the priors;
- stages as data (:func:`photo_stages`): ``torso`` (global rotation and translation from the
  torso keypoints; run first from START_YAWS, and the start whose end is closest to all the
  keypoints kept: the face points tell front from back), ``pose`` (every block from the keypoints and priors, no rendering), then
  ``silhouette-k`` (keypoints + silhouette + priors) under a decreasing sigma/gamma schedule
  (PHOTO_BUDGETS). The ablations of ``softras-cl bench body-photo`` (OBJECTIVES) drop the
  silhouette ("keypoints") or the keypoints ("mask").
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from softras_cl.errors import InputError, ResultError
from softras_cl.scene.camera import Camera
from softras_cl.fitting import losses
from softras_cl.fitting.device.body_objective import DeviceBodyEvaluation
from softras_cl.fitting.device.where import on_device
from softras_cl.fitting.recipes.body import (BodyFit, BodyFitConfig, BodyObjective, BodyScene, body_params,
                                             initial_translation, prepare_target, reprojection, rest_values)
from softras_cl.fitting.keypoints.pose33 import KeypointLayout, keypoint_layout
from softras_cl.fitting.recipes.body_settings import OBJECTIVES, PHOTO_BUDGETS, PHOTO_WEIGHTS
from softras_cl.fitting.solver import Stage, fit

__all__ = ["MIN_VISIBILITY", "BODY_PARTS", "parts_in_view", "in_view_line", "check_enough_in_view",
           "fit_objective", "BodyPhotoObjective", "DeviceBodyPhotoObjective", "photo_objective_class",
           "BodyPhotoFit", "keypoint_weights", "camera_distance", "photo_stages", "photo_params",
           "mask_misses", "PhotoSetup", "photo_setup", "check_in_view", "fit_body_photo"]

MIN_VISIBILITY = 0.3            # a keypoint the detector is less sure of than this is not used
ROBUST_FRACTION = 0.1           # Geman-McClure scale / the working image's longer side
START_YAWS = (0, 90, 180, -90)  # degrees about the vertical: the torso stage's starts
# The mask gate: a keypoint the fit uses (seen, inside the photo) further than MASK_MARGIN of the
# photo's longer side from the person mask says the mask misses part of the person (the
# detector's mask cut a person's legs off over the rocket photo of bench body-photo); with
# MASK_MISSES or more, the silhouette would push those parts into the mask, so it leaves out
# the pixels outside the mask within LIMB_RADIUS torso lengths (shoulder midpoint to hip
# midpoint: about a limb's half-width and room for the fitted limb) of each limb segment
# (LIMB_CHAINS) that ends at a missed keypoint. (Unseen keypoints do not count: they are often
# hidden behind something the mask rightly leaves out, as the cameraman's left leg and the
# astronaut's left hand.) One miss is not enough: more often the keypoint is wrong than the mask
# (the cameraman's left knee, detected on the grass: leaving the mask out around it took the
# README fit's keypoint error from 33 to 49 px). Measured on bench body-photo, docs/body_photos.md.
MASK_MARGIN = 0.03
MASK_MISSES = 2
LIMB_RADIUS = 0.25
LIMB_CHAINS = (("left_shoulder", "left_elbow", "left_wrist", "left_hand"),
               ("right_shoulder", "right_elbow", "right_wrist", "right_hand"),
               ("left_hip", "left_knee", "left_ankle", "left_foot"),
               ("right_hip", "right_knee", "right_ankle", "right_foot"))


# The body's parts as the detector's keypoints (fitting.keypoints.pose33 numbering) tell them:
# what is said to be in view, and what decides how a photo is fitted (fit_objective,
# check_enough_in_view)
BODY_PARTS = (("head", tuple(range(0, 11))), ("shoulders", (11, 12)), ("arms", tuple(range(13, 23))),
              ("hips", (23, 24)), ("legs", tuple(range(25, 33))))


def parts_in_view(keypoints: np.ndarray, visibility: np.ndarray, image_size) -> dict[str, int]:
    """How many of each BODY_PARTS' keypoints (33, 2) pixels the detector saw (visibility (33,)
    at least MIN_VISIBILITY, inside the (H, W) photo), by part name."""
    h, w = image_size
    inside = ((keypoints[:, 0] >= -0.5) & (keypoints[:, 0] <= w - 0.5)
              & (keypoints[:, 1] >= -0.5) & (keypoints[:, 1] <= h - 0.5))
    seen = inside & (visibility >= MIN_VISIBILITY)
    return {name: int(seen[list(index)].sum()) for name, index in BODY_PARTS}


def in_view_line(parts: dict[str, int]) -> str:
    """"in view: head, shoulders, arms; not in view: hips, legs" (a pair with one of two seen:
    "shoulders (one of two)")."""
    sizes = dict((name, len(index)) for name, index in BODY_PARTS)
    shown = [name + (" (one of two)" if sizes[name] == 2 and n == 1 else "") for name, n in parts.items() if n]
    missing = [name for name, n in parts.items() if not n]
    return (f"in view: {', '.join(shown) or 'nothing'}"
            + (f"; not in view: {', '.join(missing)}" if missing else ""))


def check_enough_in_view(parts: dict[str, int], name: str) -> None:
    """InputError when neither both shoulders nor both hips are in view (``parts``:
    parts_in_view): the torso's size and turn, from which the camera and the body's place are
    set, cannot be told (a face close-up: fit-face fits faces)."""
    if parts["shoulders"] < 2 and parts["hips"] < 2:
        raise InputError(f"too little of the body is in view in {name} to fit a body ({in_view_line(parts)}): "
                         "a body fit needs both shoulders or both hips; for a face use fit-face, or give a "
                         "photo that shows the person's upper body")


def fit_objective(parts: dict[str, int], objective: str = "full") -> str:
    """The objective a photo is fitted with: "keypoints" instead of "full" when no hip is in view
    (``parts``: parts_in_view; a portrait or a close-up, cut by the frame above the hips): its
    person mask is the upper body's clothes and hair, cut off by the frame, and the silhouette
    grew the body into it (the astronaut's head fitted at twice its size; keypoints only: the
    head on the photo's head); otherwise ``objective``."""
    return "keypoints" if objective == "full" and parts["hips"] == 0 else objective


def keypoint_weights(layout: KeypointLayout, keypoints: np.ndarray, visibility: np.ndarray,
                     image_size) -> np.ndarray:
    """(K,) float64 weights of the layout's entries: map weight x visibility, 0 below
    MIN_VISIBILITY or outside the (H, W) image. keypoints (33, 2) pixels, visibility (33,)."""
    points, seen = layout.detected(keypoints, visibility)
    h, w = image_size
    inside = (points[:, 0] >= -0.5) & (points[:, 0] <= w - 0.5) & (points[:, 1] >= -0.5) & (points[:, 1] <= h - 0.5)
    return np.where(inside & (seen >= MIN_VISIBILITY), layout.weights * seen, 0.0)


def mask_misses(layout: KeypointLayout, keypoints: np.ndarray, weights: np.ndarray, mask: np.ndarray) -> list[str]:
    """Names of the layout's entries the fit uses (``weights`` (K,) > 0: seen, inside the photo;
    :func:`keypoint_weights`) whose detected point (from the detector's (33, 2) pixel
    ``keypoints``) lies further than MASK_MARGIN of the (H, W) photo's longer side from the
    person ``mask`` (> 0.5)."""
    from scipy import ndimage

    h, w = mask.shape
    points = layout.detected(keypoints, np.ones(len(keypoints)))[0]
    pixel = np.clip(np.round(points).astype(np.int64), 0, [w - 1, h - 1])
    distance = ndimage.distance_transform_edt(mask <= 0.5)[pixel[:, 1], pixel[:, 0]]
    return [name for name, d, used in zip(layout.names, distance, weights > 0) if used and d > MASK_MARGIN * max(h, w)]


def torso_span(layout: KeypointLayout, points: np.ndarray, weights: np.ndarray,
               with_hips: bool | None = None) -> tuple[float, bool] | None:
    """(length, with_hips) of the torso in ``points`` (K, 2 or 3) of the layout's entries: from
    the shoulders' midpoint to the hips' (``with_hips``; None: when both hips have ``weights`` >
    0), else the shoulder width; None when a shoulder has weight 0 or is not in the layout."""
    index = {n: i for i, n in enumerate(layout.names)}
    shoulders, hips = ("left_shoulder", "right_shoulder"), ("left_hip", "right_hip")
    if any(n not in index or weights[index[n]] <= 0 for n in shoulders):
        return None
    s = [index[n] for n in shoulders]
    if with_hips is None:
        with_hips = all(n in index and weights[index[n]] > 0 for n in hips)
    if with_hips:
        h = [index[n] for n in hips]
        return float(np.linalg.norm(points[s].mean(0) - points[h].mean(0))), True
    return float(np.linalg.norm(points[s[0]] - points[s[1]])), False


def camera_distance(model, layout: KeypointLayout, points: np.ndarray, weights: np.ndarray,
                    focal_px: float) -> float | None:
    """Camera distance (m) at which the model's rest torso (shoulder midpoint to hip midpoint,
    else the shoulder width) is as long as the detected one (points (K, 2) pixels of the layout's
    entries, weights (K,)) seen with ``focal_px``; None when shoulders are not seen."""
    image = torso_span(layout, points, weights)
    if image is None:
        return None
    rest = layout.points(model.rest_joints(np.zeros(model.n_betas)), model.v_template)
    model_len, _ = torso_span(layout, rest, np.ones(len(rest)), with_hips=image[1])
    return float(focal_px * model_len / max(image[0], 1.0))


def limb_care(layout: KeypointLayout, points: np.ndarray, weights: np.ndarray, missed, mask: np.ndarray) -> np.ndarray:
    """(h, w) float64 silhouette weights (BodyTarget.care): 0 on the pixels outside the person
    ``mask`` (h, w; > 0.5 inside) within LIMB_RADIUS torso lengths of the limb segments
    (LIMB_CHAINS, both ends used: ``weights`` (K,) > 0) that end at a keypoint named in
    ``missed``, and of those keypoints themselves; 1 elsewhere. points (K, 2) working pixels."""
    span = torso_span(layout, points, weights)
    h, w = mask.shape
    radius = LIMB_RADIUS * (span[0] if span is not None else 4 * MASK_MARGIN * max(h, w))
    index = {n: i for i, n in enumerate(layout.names)}
    used = {n for n, wt in zip(layout.names, weights) if wt > 0}
    segments = [(index[m], index[m]) for m in missed if m in index]
    for chain in LIMB_CHAINS:
        segments += [(index[a], index[b]) for a, b in zip(chain, chain[1:])
                     if {a, b} <= used and (a in missed or b in missed)]
    pixels = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(np.float64)
    near = np.zeros(len(pixels), bool)
    for a, b in segments:
        near |= _segment_distance(pixels, points[a], points[b]) <= radius
    return np.where(near.reshape(h, w) & (mask <= 0.5), 0.0, 1.0)


def _segment_distance(pixels: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distances of pixels (N, 2) from the segment a-b (2,) (a point when a == b)."""
    ab = b - a
    t = np.clip((pixels - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(pixels - (a + t[:, None] * ab), axis=1)


class BodyPhotoObjective(BodyObjective):
    """fitting.recipes.body's objective with the ``torso`` and ``keypoints`` terms.

    keypoints (K, 2) working pixels of the layout's entries, weights (K,) (keypoint_weights),
    robust_px: the Geman-McClure scale of both terms. The target holds the person mask as its
    alpha (no colours, no joints)."""

    def __init__(self, scene: BodyScene, target, layout: KeypointLayout, keypoints: np.ndarray,
                 weights: np.ndarray, robust_px: float, faces=None, depth: np.ndarray | None = None):
        super().__init__(scene, target, None, None, faces)
        self.layout, self.keypoints, self.weights, self.keypoint_px = layout, keypoints, weights, robust_px
        self.hips = np.isin(layout.names, ("left_hip", "right_hip"))
        self.depth = None if depth is None or self.hips.sum() != 2 else depth - depth[self.hips].mean()
        self._layouts: dict[int, tuple[np.ndarray, KeypointLayout]] = {}   # id(vertex_ids) -> layout on them

    def extra_vertices(self) -> np.ndarray:
        """(N,) int64 the layout's surface landmarks (the vertices the keypoint terms read)."""
        return self.layout.vertices[self.layout.vertices >= 0]

    def layout_on(self, state) -> KeypointLayout:
        """The layout with its vertices as rows of ``state.vertices`` (KeypointLayout.on_rows of
        a subset's ``vertex_ids``, made once per subset)."""
        if state.vertex_ids is None:
            return self.layout
        ids, layout = self._layouts.get(id(state.vertex_ids), (None, None))
        if ids is not state.vertex_ids:
            layout = self.layout.on_rows(state.vertex_ids)
            self._layouts[id(state.vertex_ids)] = (state.vertex_ids, layout)
        return layout

    def extra_terms(self, state, w: dict) -> dict:
        terms = {}
        for name, mask in (("torso", self.layout.torso), ("keypoints", np.ones(len(self.weights), bool))):
            if w.get(name):
                terms[name] = self.keypoint_term(state, self.weights * mask)
        if w.get("depth"):         # a detection without depths (or a model without hips): nothing to compare
            terms["depth"] = (0.0, {}) if self.depth is None else self.depth_term(state)
        return terms

    def depth_term(self, state) -> tuple[float, dict]:
        """Geman-McClure ``s^2 rho`` (the keypoints' weights and scale) of each model point's depth
        from the camera, relative to the hips' midpoint, against the detector's estimate (metres),
        both in working pixels (metres times the focal length over the camera distance: what the
        same offset across the view would move in the image); gradients wrt "joints" and
        "vertices". The detector's depth is rough (on the bench's photos it correlates with the
        truth at a median 0.77, its scale off by up to 2x), hence its small weight."""
        layout = self.layout_on(state)
        points = layout.points(state.joints, state.vertices)
        axis = self.scene.camera.rotation_matrix()[2]
        px_per_m = float(self.scene.camera.focal[1]) / self.scene.config.distance
        depth = points @ axis
        relative = (depth - depth[self.hips].mean()) * px_per_m
        value, g = losses.landmarks_2d_unchecked((relative - self.depth * px_per_m)[:, None], self.weights, self.keypoint_px)
        factor = len(relative) * self.keypoint_px ** 2
        g_relative = g[:, 0] * factor
        g_depth = (g_relative - self.hips * g_relative.sum() / 2) * px_per_m
        g_joints, g_vertices = layout.points_vjp(g_depth[:, None] * axis, len(state.joints), len(state.vertices))
        return value * factor, {"joints": g_joints, "vertices": g_vertices}

    def keypoint_term(self, state, weights: np.ndarray) -> tuple[float, dict]:
        """Robust reprojection of the layout's model points of the posed body ``state`` against
        the keypoints, with ``weights`` (K,); gradients wrt "joints" and "vertices"."""
        layout = self.layout_on(state)
        points = layout.points(state.joints, state.vertices)
        value, grad = reprojection(self.scene.camera, points, self.keypoints, weights, self.keypoint_px)
        g_joints, g_vertices = layout.points_vjp(grad, len(state.joints), len(state.vertices))
        return value, {"joints": g_joints, "vertices": g_vertices}


class DeviceBodyPhotoObjective(DeviceBodyEvaluation, BodyPhotoObjective):
    """BodyPhotoObjective with its silhouette stages on the OpenCL device of its scene's renderer
    (fitting.device.body_objective); the numpy BodyPhotoObjective stays the reference."""


def photo_objective_class(where: str, scene: BodyScene) -> type:
    """BodyPhotoObjective or DeviceBodyPhotoObjective for BodyFitConfig.objective ``where``
    (fitting.device.where.on_device)."""
    return DeviceBodyPhotoObjective if on_device(where, scene.renderer.device) else BodyPhotoObjective


def photo_stages(budget: str, objective: str = "full", weights: dict | None = None) -> list[Stage]:
    """The stages (module docstring) of ``budget`` (PHOTO_BUDGETS) for ``objective`` (OBJECTIVES):
    "mask" has no torso or pose stage, "keypoints" no silhouette stages."""
    if budget not in PHOTO_BUDGETS:
        raise InputError(f"budget must be one of {sorted(PHOTO_BUDGETS)}, got {budget!r}")
    if objective not in OBJECTIVES:
        raise InputError(f"objective must be one of {sorted(OBJECTIVES)}, got {objective!r}")
    b, w = PHOTO_BUDGETS[budget], dict(PHOTO_WEIGHTS if weights is None else weights)
    uses = OBJECTIVES[objective]
    priors = {k: w[k] for k in ("pose_prior", "shape_prior", "translation_prior", "limits")}
    everything = ("betas", "body_pose", "global_rotation", "translation")
    stages = []
    if "keypoints" in uses:
        stages += [Stage("torso", ("global_rotation", "translation"),
                         dict(torso=w["torso"], translation_prior=w["translation_prior"]), max_iters=b["torso_iters"]),
                   Stage("pose", everything, dict(keypoints=w["keypoints"], depth=w["depth"], **priors),
                         max_iters=b["pose_iters"])]
    if "silhouette" in uses:
        keypoints = dict(keypoints=w["keypoints"], depth=w["depth"]) if "keypoints" in uses else {}
        iters = [n + (b["pose_iters"] if objective == "mask" and k == 0 else 0)
                 for k, (_, _, n) in enumerate(b["silhouette_stages"])]
        stages += [Stage(f"silhouette-{k + 1}", everything, dict(silhouette=w["silhouette"], **keypoints, **priors),
                         sigma=sigma, gamma=gamma, max_iters=n)
                   for k, ((sigma, gamma, _), n) in enumerate(zip(b["silhouette_stages"], iters))]
    return stages


@dataclass
class BodyPhotoFit(BodyFit):
    """BodyFit of a photo, with the keypoints used: layout, keypoints (K, 2) and weights (K,) in
    working pixels, the detection (PersonDetection), the field of view used with its source and
    the names of the used keypoints the person mask misses (:func:`mask_misses`)."""
    layout: KeypointLayout = None
    keypoints: np.ndarray = None
    weights: np.ndarray = None
    detection: object = None
    fov_source: str = ""
    mask_misses: tuple = ()
    objective: str = "full"

    def metrics(self) -> dict:
        """BodyFit's (silhouette IoU against the person mask) and the mean keypoint error over
        the used keypoints (working and full-size pixels)."""
        doc = super().metrics()
        state, _ = self.scene.pose(self.values)
        uv, _ = self.scene.camera.project_pixels(self.layout.points(state.joints, state.vertices))
        used = self.weights > 0
        err = float(np.linalg.norm(uv - self.keypoints, axis=1)[used].mean()) if used.any() else float("nan")
        doc.update(keypoint_error_px=err, keypoint_error_px_full=err / self.target.scale,
                   keypoints_used=int(used.sum()), mask_misses=len(self.mask_misses))
        return doc

    def fitted_keypoints_full(self) -> np.ndarray:
        """(K, 2) the fitted model points in the full-size photo's pixels."""
        state, _ = self.scene.pose(self.values)
        uv, _ = self.scene.camera.project_pixels(self.layout.points(state.joints, state.vertices))
        return (uv + 0.5) / self.target.scale - 0.5


def _initial_values(model, scene: BodyScene, layout, keypoints, weights, mask, yaw: float = 0.0) -> dict:
    """Mean shape in the rest pose turned by ``yaw`` (rad) about the vertical, moved onto the
    torso keypoints' centre (or the mask's centroid when no torso keypoint is seen)."""
    values = rest_values(model)
    values["global_rotation"] = np.array([0.0, yaw, 0.0])
    torso = layout.torso & (weights > 0)
    if torso.any():
        values["translation"] = _torso_translation(scene, values, layout, keypoints[torso], torso)
    else:
        values["translation"] = initial_translation(scene, values, mask)
    return values


def _oriented_start(model, scene: BodyScene, objective: BodyPhotoObjective, mask, torso_stage: Stage) -> dict:
    """The start of the fit: from each of START_YAWS, the torso stage alone (no rendering);
    kept: the one whose end is closest to all the keypoints (nose and ears tell front from back,
    which the four torso points cannot)."""
    layout, keypoints, weights = objective.layout, objective.keypoints, objective.weights
    judge = Stage("choose", ("global_rotation", "translation"), dict(keypoints=1.0))
    best, best_loss = None, np.inf
    for yaw in START_YAWS:
        values = _initial_values(model, scene, layout, keypoints, weights, mask, np.radians(yaw))
        values = fit(photo_params(model, values, scene), objective, [torso_stage], progress=False).values
        loss = objective(values, judge)[0]
        if loss < best_loss:
            best, best_loss = values, loss
    return best


def photo_params(model, values: dict, scene: BodyScene):
    """fitting.recipes.body's parameters with the translation kept within half the camera
    distance of the origin on each axis (the start clipped into it): a long step of the solver
    from a poor start would otherwise put the body behind the camera, where it cannot be
    projected."""
    bound = scene.config.distance / 2
    return body_params(model, {**values, "translation": np.clip(values["translation"], -bound, bound)}, bound)


def _torso_translation(scene: BodyScene, values: dict, layout, targets: np.ndarray, torso: np.ndarray) -> np.ndarray:
    """(3,) translation moving the model's torso points' centre onto the targets' centre (pixels)."""
    state, _ = scene.pose(values)
    points = layout.points(state.joints, state.vertices)[torso]
    uv, _ = scene.camera.project_pixels(points)
    shift = targets.mean(0) - uv.mean(0)
    depth = scene.config.distance - points[:, 2].mean()
    return values["translation"] + np.array([shift[0], -shift[1], 0.0]) * depth / float(scene.camera.focal[1])


@dataclass(frozen=True)
class PhotoSetup:
    """What a photo fit starts from (:func:`photo_setup`): the config with the camera's field of
    view and distance, the target (the person mask at the working size), the keypoint layout,
    the keypoints (K, 2) in working pixels with their weights (K,) and where the field of view
    came from."""
    config: BodyFitConfig
    data: object
    layout: KeypointLayout
    keypoints: np.ndarray
    seen: np.ndarray
    fov_source: str


def photo_setup(photo_size, detection, model, config: BodyFitConfig = BodyFitConfig(),
                fov_deg: float | None = None) -> PhotoSetup:
    """The camera and the targets of a photo fit (fit_body_photo's arguments); ResultError when
    the detection's mask is empty or full."""
    if not 0.0 < (detection.mask > 0.5).mean() < 1.0:
        raise ResultError("the detector's person mask is empty or fills the whole photo: nothing to fit")
    layout = keypoint_layout(model)
    seen = keypoint_weights(layout, detection.keypoints, detection.visibility, photo_size)
    fov_source = "EXIF 35 mm equivalent focal length" if fov_deg is not None else "--fov (no EXIF focal length)"
    config = replace(config, fov_deg=config.fov_deg if fov_deg is None else fov_deg)
    data = prepare_target(detection.mask, config.size, config.background, None, None, model.n_joints)
    keypoints = (layout.detected(detection.keypoints, detection.visibility)[0] + 0.5) * data.scale - 0.5
    focal = float(Camera.look_at((0, 0, 1), (0, 0, 0), fov_deg=config.fov_deg, image_size=data.alpha.shape).focal[1])
    distance = camera_distance(model, layout, keypoints, seen, focal)
    if distance is not None:
        config = replace(config, distance=distance)
    return PhotoSetup(config, data, layout, keypoints, seen, fov_source)


def check_in_view(setup: PhotoSetup, model) -> None:
    """ResultError when the model in its rest pose at the origin, where the fit starts, reaches
    the camera (BodyScene.too_close): the field of view is so wide (--fov near 180 degrees) that
    the camera distance at which the model's torso is as long as the detected one lies inside
    the body. No fit could put the body in view."""
    scene = BodyScene(model, setup.data.alpha.shape, setup.config)
    state, _ = scene.pose(rest_values(model))
    if scene.too_close(state):
        source = "the photo's EXIF focal length" if setup.fov_source.startswith("EXIF") else "--fov"
        raise ResultError(
            f"the body cannot be fitted in view: with a field of view of {setup.config.fov_deg:g} degrees "
            f"(from {source}) the camera would stand {setup.config.distance:.3g} m from the person "
            "(where the model's torso looks as long as the detected one), inside the body; give the "
            "photo's field of view across its shorter side with a smaller --fov")


def fit_body_photo(photo_size, detection, model, config: BodyFitConfig = BodyFitConfig(), budget: str = "default",
                   fov_deg: float | None = None, objective: str = "full", weights: dict | None = None,
                   out_dir=None, progress: bool = True, resume: bool = False) -> BodyPhotoFit:
    """Fit ``model`` to a detected person (fitting.detection.people.PersonDetection) of a photo
    of ``photo_size`` (H, W).

    config: size, fov_deg (used when ``fov_deg`` is None: no EXIF focal), height, robust_px,
    coarse_mesh, dtype of fitting.recipes.body (its distance is replaced by camera_distance's);
    budget: PHOTO_BUDGETS; objective: OBJECTIVES (the bench's ablations); weights: the terms'
    weights (default PHOTO_WEIGHTS). out_dir / progress / resume: as fitting.recipes.body.fit_body
    (checkpoints, Ctrl-C keeps the best). ResultError when the detection's mask is empty or full,
    or when the camera would stand inside the body (check_in_view). While fitting, a body that
    reaches the camera is refused by the objective (BodyScene.too_close), so the fit keeps it in
    front of the camera.
    """
    setup = photo_setup(photo_size, detection, model, config, fov_deg)
    check_in_view(setup, model)
    chosen = fit_objective(parts_in_view(detection.keypoints, detection.visibility, photo_size), objective)
    if chosen != objective and progress:
        print("no hip in view: the keypoints in view are fitted with the priors, without the person mask's "
              "silhouette (a portrait's mask is clothes and hair cut by the frame)")
    objective = chosen
    config, data, layout = setup.config, setup.data, setup.layout
    keypoints, seen, fov_source = setup.keypoints, setup.seen, setup.fov_source
    scene = BodyScene(model, data.alpha.shape, config)
    robust = config.robust_px if config.robust_px is not None else ROBUST_FRACTION * max(data.alpha.shape)
    faces = None if config.coarse_mesh is None else model.coarse_faces(config.coarse_mesh)
    depth = None if detection.depth is None else detection.depth[layout.detector].mean(1)
    missed = mask_misses(layout, detection.keypoints, seen, detection.mask)
    if objective == "full" and len(missed) >= MASK_MISSES:
        data = replace(data, care=limb_care(layout, keypoints, seen, missed, data.alpha))
        if progress:
            print(f"the person mask misses {', '.join(missed)}: the silhouette leaves out the pixels outside "
                  f"the mask around those limbs ({(data.care == 0).mean():.0%} of the image)")
    objective_fn = photo_objective_class(config.objective, scene)(scene, data, layout, keypoints, seen, robust,
                                                                  faces, depth)
    stages = photo_stages(budget, objective, weights)
    if stages[0].name == "torso" and seen[layout.torso].any():
        init = _oriented_start(model, scene, objective_fn, data.alpha, stages[0])
    else:
        init = _initial_values(model, scene, layout, keypoints, seen, data.alpha)
    result = fit(photo_params(model, init, scene), objective_fn, stages, out_dir=out_dir, progress=progress, resume=resume)
    return BodyPhotoFit(result.values, scene, data, result, layout, keypoints, seen, detection, fov_source,
                        tuple(missed), objective)


# ---------------------------------------------------------------------------------------------
# what a target file is, and a photo's inputs
# ---------------------------------------------------------------------------------------------
