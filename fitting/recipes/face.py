"""Face fitting from one photo and its 68 landmarks (paper sec. 5.3, figure 14).

The scene (float64 throughout)::

    shape  = model.shape(id, exp)[0]                      (V, 3) model frame: y up, face along +z
    world  = shape @ rodrigues(rotation).T + translation  (V, 3) metres
    camera : fixed at the origin looking down -z (OpenCV R = diag(1, -1, -1), t = 0), square
             pixels of focal length ``focal``, principal point at the image centre
    colour : model.albedo(albedo)[0] lit per vertex by the SH light ``sh`` (3, 9), linear RGB

Parameter blocks: id (K_id,), exp (K_exp,), albedo (K_alb,) in units of one standard
deviation; sh (3, 9); rotation (3,) axis-angle; translation (3,); focal (1,) pixels.

The fit, as the paper and its anchors do it, in stages given as data (:func:`default_stages`):

1. ``landmarks``: pose, focal (unless given; a log-normal prior keeps it within about a
   factor 2 of a 30 degree field of view: landmarks barely tell focal length from distance),
   identity and expression from the 68 landmarks and the coefficient priors, starting from
   a closed-form scaled-orthographic alignment of the mean face's landmarks
   (:func:`initial_pose`).
2. The SH light, frozen until then, starts from a linear least-squares fit to the visible
   vertices at the initial pose (:func:`initial_light`).
3. ``photo-k``: identity, expression, albedo, SH light, pose and focal (unless given, with its
   prior: the photo's perspective corrects what the landmarks left open) from the photometric
   term in linear RGB over the face region + landmarks + priors + an SH term keeping the light
   near white, under a decreasing sigma/gamma schedule. The face region is the rendered alpha
   (> 0.5, eroded by ``mask_erosion`` pixels) at the start of each stage, held fixed within
   the stage so that every stage minimises one fixed function: hair and background outside
   the rendered face never pull the fit. Likewise near/far are fitted to the face's distance
   (:func:`depth_range`), so that gamma means the same at any distance, and the robust
   term's scale is set from the residuals (:meth:`FaceObjective.start_stage`), at each stage
   start.

Every term is a sum, not a mean (nlopt's L-BFGS sizes its first step from the gradient; see
fitting/rigid.py): ``photo`` = sum over face-region pixels of the pixel's squared colour error
e (summed over channels), or with ``robust_scale`` of its Geman-McClure kernel
``e / (1 + e / s^2)`` (losses.image_geman_mcclure): the same for errors well below s, at most
s^2 for what the model cannot explain (cast shadows, highlights, hair strands, glasses),
``landmarks`` = sum over points of weighted squared pixel distances (the jaw line's points that
are turned away from the camera slide on the mesh's occluding contour, FaceFitConfig's
contour_landmarks, see fitting/recipes/contour.py), optionally ``dense`` = the same over MediaPipe Face
Mesh's points (FaceFitConfig's dense_weight, off by default), priors = sum of squared
coefficients. Read as negative log-likelihoods, ``w_landmarks = 1 / noise_px^2`` (2 px) and
``w_photo = 1 / noise_rgb^2``; the priors have weight 1. The defaults, chosen by measurement
on synthetic faces and the shipped photos (docs/face_fitting.md): photo weight 100 (noise
0.1) with the robust term (scale 2x the median error, at least 0.1) and the landmarks 5x
heavier in the photometric stages than in the landmark stage. With squared errors a weight of
100 let what the model cannot represent (hair, glasses, wrinkles: large errors, correlated
over many pixels) bend the shape (Grace Hopper: landmark error 7.0 px at 10, 9.8 px at 100);
the robust term and the heavier landmarks keep the photo's pull to what the model explains,
while the higher weight lets the photo, not the priors, set the shape. The landmark factor
trades the two kinds of photo: heavier landmarks follow a real photo's annotated points more
closely, lighter ones let the photo correct the landmarks' noise (on the bench's synthetic
faces the shape error falls from 10x to 1x; 5x is the lightest that keeps the shipped photos'
landmark errors within their earlier figures). The SH term (weight 1000) keeps the light grey
so that colour goes into the albedo.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pyopencl.array as cla

from softras_cl.checks import check_finite
from softras_cl.errors import InputError
from softras_cl.scene.camera import Camera
from softras_cl.scene.rotation import RodriguesContext, matrix_to_axis_angle, rodrigues, rodrigues_vjp
from softras_cl.scene.renderer import SHARP, Renderer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.shading import SH_A, SHLight, sh_ambient, sh_basis, vertex_normals
from softras_cl.fitting import losses
from softras_cl.fitting.device.face_objective import DeviceFaceEvaluation
from softras_cl.fitting.device.where import on_device
from softras_cl.fitting.keypoints import face_mesh, ibug68
from softras_cl.fitting.keypoints.plausibility import check_distinct_landmarks, check_landmark_layout
from softras_cl.fitting.metrics import psnr
from softras_cl.fitting.models.face_model import LinearContext
from softras_cl.fitting.models.mesh_lod import coarse_faces
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.recipes.face_settings import (BUDGETS, COARSE_MESH, COARSE_SIGMA, DETECTED_LANDMARK_SIGMA_MM,
                                                      MIN_LANDMARK_SPREAD,
                                                      MIN_ROBUST_SCALE, MIN_SIZE, ROBUST_SCALE, FaceFitConfig,
                                                      input_check)
from softras_cl.fitting.recipes.contour import ContourChoice, ContourLandmarks, jaw_candidates
from softras_cl.fitting.solver import MIN_DEPTH, FitResult, Stage, fit, too_close_result

__all__ = ["Crop", "FaceScene", "FaceFit", "landmark_weights", "detected_landmark_weights", "default_stages",
           "depth_range", "half_resolution", "initial_pose", "initial_light", "prepare_photo", "face_params", "FaceObjective",
           "prepare_fit", "fit_face", "check_dense_inputs", "detected_dense", "landmark_robust", "psnr"]

CAMERA_ROTATION = np.diag([1.0, -1.0, -1.0])   # world (y up, camera looks down -z) -> OpenCV
HALF = 0.5                  # the half-resolution copy's pixels per working pixel (photo_level)
PHOTO_GRADS = ("vertices", "albedo", "light", "focal")     # what the photometric term's render gives


def landmark_weights() -> np.ndarray:
    """(68,) per-landmark weights: the jaw line counts half. With fixed jaw points
    (contour_landmarks "fixed") their 3D points only approximate the photo's outline, which
    slides over the cheek as the head turns; with the sliding contour they follow it, but the
    full weight measured no better (landmark stage alone, 6 faces per yaw bin: shape error
    2.80 / 2.66 mm at half weight against 2.80 / 2.69 mm at full weight for |yaw| 0-15 / 45-75
    degrees), so the half weight stays for both."""
    w = np.ones(ibug68.COUNT)
    w[ibug68.JAW] = 0.5
    return w


def detected_landmark_weights(used) -> np.ndarray:
    """(68,) per-landmark weights for landmarks a detector found on Face Mesh's points, tied to them:
    1 / sigma^2 of their measured noise (face_settings.DETECTED_LANDMARK_SIGMA_MM: MediaPipe's
    eye points spread about 1.9 mm at the face, its brows 2.6, nose 3.3, lips 3.5, jaw 4-12 6.3), 0 where
    ``used`` (68,) bool is False, scaled so that the used points weigh as much in all as
    :func:`landmark_weights` gives them: the landmark term keeps its total weight against the
    photo and the priors, shared out by how far each point can be trusted."""
    used = np.asarray(used, bool)
    w = np.where(used, 1.0 / DETECTED_LANDMARK_SIGMA_MM ** 2, 0.0)
    return w * (landmark_weights()[used].sum() / w.sum())


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Crop:
    """Full photo -> working image: ``u_work = (u_full + 0.5 - x0) * scale - 0.5`` (and v with
    y0), pixel centres at integers in both."""
    x0: float
    y0: float
    scale: float

    def to_work(self, points) -> np.ndarray:
        """(N, 2) full-photo pixels -> working-image pixels."""
        return (np.asarray(points, np.float64) + 0.5 - [self.x0, self.y0]) * self.scale - 0.5

    def to_full(self, points) -> np.ndarray:
        """(N, 2) working-image pixels -> full-photo pixels."""
        return (np.asarray(points, np.float64) + 0.5) / self.scale - 0.5 + [self.x0, self.y0]


def _check_inputs(photo, landmarks) -> tuple[np.ndarray, np.ndarray]:
    """Checked (photo (H, W, 3) float64, landmarks (68, 2) float64); InputError naming what is
    wrong: shape, non-finite values, a landmark outside the photo, landmarks that are (nearly)
    all one point, or that span no area (collinear) or less than MIN_SIZE / 2 pixels."""
    img = np.asarray(photo, np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"photo must be an (H, W, 3) RGB image, got shape {img.shape}")
    input_check(lambda: check_finite("photo", img))
    pts = np.asarray(landmarks, np.float64)
    if pts.shape != (ibug68.COUNT, 2):
        raise InputError(f"landmarks must have shape ({ibug68.COUNT}, 2), got {pts.shape}")
    input_check(lambda: check_finite("landmarks", pts))
    h, w = img.shape[:2]
    outside = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
    if outside.any():
        i = int(np.argmax(outside))
        raise InputError(f"landmark {i} at {pts[i].tolist()} is outside the {w}x{h} photo "
                         "(do the landmarks belong to this photo?)")
    check_distinct_landmarks(pts)
    extent = float(np.ptp(pts, axis=0).max())
    if extent < MIN_SIZE / 2:
        raise InputError(f"the landmarks span {extent:.3g} pixels of the {w}x{h} photo; fitting needs "
                         f"a face at least {MIN_SIZE // 2} pixels across (a working image of "
                         f"{MIN_SIZE} pixels); use a larger photo")
    spread = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    if spread[1] < MIN_LANDMARK_SPREAD * spread[0]:
        raise InputError(f"the landmarks lie on a line (spread ratio {spread[1] / spread[0]:.2g}, "
                         f"smallest over largest singular value; a face gives about 0.9, at least "
                         f"{MIN_LANDMARK_SPREAD} is needed): are they the 68 points of a face?")
    return img, pts


def prepare_photo(photo, landmarks, size: int, margin: float = 2.0) -> tuple[np.ndarray, np.ndarray, Crop]:
    """Check the inputs and cut the working image: a square around the landmarks, ``margin``
    times their extent (forehead and some background included), shrunk to at most ``size``
    pixels a side; parts outside the photo repeat its edge pixels.

    photo (H, W, 3) linear RGB float; landmarks (68, 2) pixels (u right, v down, 0 = centre of
    the first pixel). Returns (image (s, s, 3) float64, landmarks (68, 2) float64 in working
    pixels, the Crop).
    """
    from skimage.transform import resize

    img, pts = _check_inputs(photo, landmarks)
    lo, hi = pts.min(0), pts.max(0)
    side = max(int(np.ceil(margin * np.max(hi - lo))), 8)
    x0, y0 = (np.round((lo + hi) / 2 - side / 2)).astype(int)
    h, w = img.shape[:2]
    pad = max(0, -x0, -y0, x0 + side - w, y0 + side - h)
    padded = np.pad(img, ((pad, pad), (pad, pad), (0, 0)), mode="edge") if pad else img
    window = padded[y0 + pad:y0 + pad + side, x0 + pad:x0 + pad + side]
    out = min(int(size), side)
    image = resize(window, (out, out), order=1, anti_aliasing=True) if out < side else window.copy()
    crop = Crop(float(x0), float(y0), out / side)
    return image, crop.to_work(pts), crop


# ---------------------------------------------------------------------------------------------
# scene
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GeometryContext:
    """What FaceScene.geometry_vjp needs: shape (V, 3) float64 model-frame vertices and
    shape_ctx the model's context for them; R (3, 3) float64 the rotation and rot_ctx its
    RodriguesContext."""
    shape: np.ndarray
    shape_ctx: LinearContext
    R: np.ndarray
    rot_ctx: RodriguesContext


class Geometry(NamedTuple):
    """FaceScene.geometry's result: world (V, 3) float64 vertices and the context of its vjp."""
    world: np.ndarray
    ctx: GeometryContext


class FaceScene:
    """The model, the fixed camera frame and a renderer for one working image size.

    model: a fitting.models.face_model.FaceModel; image_size (H, W); dtype of the rasteriser;
    alpha_agg: "occupancy" (soft, for fitting) or "hard" (1 wherever the face is: for
    compositing a render over a photo, where occupancy alpha would let the background show
    through the seams between triangles, docs/conventions.md); depth_range (near, far) in
    metres: gamma acts on depth normalised by far - near (eq. 10), so a range fitted to the
    face (see :func:`depth_range`) makes a gamma mean the same at any distance (set it again
    with :meth:`set_depth_range`: the renderer stays, the range goes to each render); principal
    (cx, cy): the principal point in pixels (default: the image centre); faces (F', 3) int32:
    the triangles drawn, over the model's vertices (default the model's own; a coarser list
    from fitting.models.mesh_lod for a low-resolution image).
    """

    def __init__(self, model, image_size, dtype: str = "float64", alpha_agg: str = "occupancy",
                 depth_range=(0.01, 20.0), principal=None, faces=None):
        self.model = model
        self.faces = model.faces if faces is None else faces
        self.image_size = tuple(int(n) for n in image_size)
        h, w = self.image_size
        self.principal = (w / 2.0 - 0.5, h / 2.0 - 0.5) if principal is None else tuple(map(float, principal))
        near, far = (float(d) for d in depth_range)
        # settings: the renderer's, with the depth range the renders use now (set_depth_range)
        self.settings = RasterSettings(image_size=self.image_size, outputs=("rgb", "alpha"),
                                       near=near, far=far, dtype=dtype, alpha_agg=alpha_agg)
        self.renderer = Renderer(self.settings, shading="vertex")
        self._camera: tuple[float, Camera] | None = None

    def set_depth_range(self, translation) -> None:
        """Fit near/far to a face at ``translation`` (see :func:`depth_range`) for the renders
        that follow."""
        near, far = depth_range(translation)
        self.settings = self.settings.replace(near=near, far=far)

    def half_size(self, faces=None) -> "FaceScene":
        """This scene at half its resolution (:func:`half_resolution`): image (h // 2, w // 2),
        the principal point mapped as pixel centres are, the same model, dtype, alpha and depth
        range; faces (F', 3) int32: the triangles drawn (default the model's)."""
        s, (h, w) = self.settings, self.image_size
        return FaceScene(self.model, (h // 2, w // 2), s.dtype, s.alpha_agg, (s.near, s.far),
                         principal=half_pixels(np.array([self.principal]))[0], faces=faces)

    def camera(self, focal: float) -> Camera:
        """The Camera of this focal length (pixels); the last one is kept (Cameras are frozen):
        the landmark and photo terms of one evaluation share it. Later ones are copies of the
        first with another focal length (its pose and principal point never change)."""
        focal = float(focal)
        if self._camera is None:
            cx, cy = self.principal
            K = [[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]]
            self._camera = (focal, Camera.from_opencv(K, CAMERA_ROTATION, np.zeros(3), self.image_size))
        elif self._camera[0] != focal:
            self._camera = (focal, self._camera[1].with_params(fx=focal, fy=focal))
        return self._camera[1]

    def geometry(self, values: dict) -> Geometry:
        """-> Geometry: world vertices (V, 3) float64 and the GeometryContext for geometry_vjp."""
        shape, shape_ctx = self.model.shape(values["id"], values["exp"])
        R, rot_ctx = rodrigues(values["rotation"])
        return Geometry(shape @ R.T + values["translation"], GeometryContext(shape, shape_ctx, R, rot_ctx))

    def too_close(self, values: dict) -> bool:
        """Whether a vertex of the face placed by values lies nearer the camera than MIN_DEPTH,
        or behind it, where it cannot be projected (fitting.solver.too_close_result). The model's
        radius bound settles it without the shape (the face is metres away); only near the camera
        is the shape placed."""
        depth = -float(values["translation"][2])         # the camera looks down -z from the origin
        if depth - self.model.radius_bound(values["id"], values["exp"]) >= MIN_DEPTH:
            return False
        return float(-self.geometry(values)[0][:, 2].max()) < MIN_DEPTH

    def geometry_vjp(self, ctx: GeometryContext, g_world: np.ndarray) -> dict:
        """dL/d(world vertices) (V, 3) -> dict id, exp, rotation, translation (float64)."""
        g_shape = self.model.shape_vjp(ctx.shape_ctx, g_world @ ctx.R)
        return dict(id=g_shape["id_coeffs"], exp=g_shape["exp_coeffs"], translation=g_world.sum(axis=0),
                    rotation=rodrigues_vjp(ctx.rot_ctx, g_world.T @ ctx.shape)["omega"])

    def render(self, values: dict, sigma: float, gamma: float, grads=(), albedo=None,
               light=None, world=None, roi=None, faces=None, check_values: bool = True):
        """Render the face; albedo (V, 3) / light: the model's if already computed, or others
        (for the report); world: the world vertices if already computed; roi: None or an (H, W)
        bool mask, the only pixels needed (Renderer.forward: other screen tiles are not
        rasterised); faces: this scene's faces as a device copy (with device-resident world and
        albedo: Renderer.forward's device path), None for self.faces; check_values:
        Renderer.forward's (False: a device caller's own arrays)."""
        world = self.geometry(values)[0] if world is None else world
        albedo = self.model.albedo(values["albedo"])[0] if albedo is None else albedo
        light = SHLight(values["sh"]) if light is None else light
        faces = self.faces if faces is None else faces
        return self.renderer.forward(world, faces, self.camera(values["focal"][0]),
                                     albedo=albedo, light=light, grads=grads, roi=roi, sigma=sigma,
                                     gamma=gamma, near=self.settings.near, far=self.settings.far,
                                     check_values=check_values)


def half_resolution(image: np.ndarray):
    """(image (h // 2, w // 2, 3): the mean of each 2x2 block of pixels, :func:`half_pixels`
    mapping (N, 2) working pixels to its pixels); an odd last row or column is left out."""
    h, w = (n // 2 for n in image.shape[:2])
    blocks = np.asarray(image, np.float64)[:2 * h, :2 * w].reshape(h, 2, w, 2, -1)
    half = blocks.mean(axis=(1, 3))
    return half, half_pixels


def half_pixels(points) -> np.ndarray:
    """(N, 2) pixels -> the same points in pixels of the half-resolution image: pixel centres
    map as ``u_half = (u + 0.5) / 2 - 0.5``."""
    return (np.asarray(points, np.float64) + 0.5) * 0.5 - 0.5


def depth_range(translation) -> tuple[float, float]:
    """(near, far) = (0.5, 2) x the face's distance: room for the fit to move the face while a
    face's own depth (~0.1 m) spans a good part of the normalised depth."""
    distance = float(np.linalg.norm(translation))
    return 0.5 * distance, 2.0 * distance


# ---------------------------------------------------------------------------------------------
# initialisation
# ---------------------------------------------------------------------------------------------

def initial_pose(points_3d, points_2d, focal: float, principal) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form pose from 3D model points (N, 3) and their pixels (N, 2), N >= 4.

    Fits a scaled-orthographic (affine) camera by least squares, takes the nearest rotation
    (SVD) and the depth at which the scale matches ``focal``; principal (cx, cy) pixels.
    Returns (rotation (3,) axis-angle, translation (3,)) of the model in the world frame of
    :class:`FaceScene`.
    """
    X = np.asarray(points_3d, np.float64)
    x = np.asarray(points_2d, np.float64)
    cx, cy = principal
    Xc, xc = X - X.mean(0), x - x.mean(0)
    M = np.linalg.lstsq(Xc, xc, rcond=None)[0].T                 # (2, 3): xc ~ M Xc
    U, S, Vt = np.linalg.svd(M, full_matrices=False)
    rows = U @ Vt
    R_cam = np.stack([rows[0], rows[1], np.cross(rows[0], rows[1])])
    depth = focal / S.mean()
    centre = np.array([(x[:, 0].mean() - cx) * depth / focal, (x[:, 1].mean() - cy) * depth / focal, depth])
    t_cam = centre - R_cam @ X.mean(0)
    return matrix_to_axis_angle(CAMERA_ROTATION @ R_cam), CAMERA_ROTATION @ t_cam


def initial_light(scene: FaceScene, values: dict, image: np.ndarray, ridge: float = 1e-2) -> np.ndarray:
    """SH coefficients (3, 9) by linear least squares, channel by channel: the photo's colour
    (bilinear) at each visible vertex ~ albedo * sum_i L_i A_i Y_i(n). Visible: facing the
    camera (cosine > 0.3) and at least 2 px inside the rendered face (silhouette vertices would
    sample the background). Over a face the normals barely span the sphere,
    so the constant and z terms are nearly collinear: the ridge pulls towards a uniform light
    of the photo's mean level, and the result is a starting point, not an identification."""
    from scipy.ndimage import binary_erosion, map_coordinates

    world, _ = scene.geometry(values)
    normals = vertex_normals(world[None], scene.model.faces)[0][0]
    uv, _ = scene.camera(values["focal"][0]).project_pixels(world)
    h, w = scene.image_size
    facing = np.einsum("vi,vi->v", normals, -world / np.linalg.norm(world, axis=1, keepdims=True))
    inside = binary_erosion(scene.render(dict(values, sh=sh_ambient(1.0)), *SHARP).alpha[0] > 0.5,
                            iterations=2)
    px = np.clip(np.round(uv).astype(int), 0, [w - 1, h - 1])
    keep = (facing > 0.3) & inside[px[:, 1], px[:, 0]]
    if keep.sum() < 9:
        return sh_ambient(0.5)
    seen = np.stack([map_coordinates(image[..., c], uv[keep, ::-1].T, order=1) for c in range(3)], -1)
    albedo = scene.model.albedo(values["albedo"])[0][keep]
    basis = sh_basis(normals[keep]) * SH_A                        # (N, 9)
    level = np.clip(seen.mean() / max(albedo.mean(), 1e-3), 0.05, 10.0)
    prior = sh_ambient(level)
    coeffs = np.empty((3, 9))
    for c in range(3):
        A = albedo[:, c:c + 1] * basis
        lhs = A.T @ A + ridge * len(A) * np.eye(9)
        coeffs[c] = np.linalg.solve(lhs, A.T @ seen[:, c] + ridge * len(A) * prior[c])
    return coeffs


def face_params(model, focal: float, rotation, translation, sh) -> ParamSet:
    """The parameter blocks, scaled so one optimiser unit is a sensible step of each."""
    return ParamSet([
        Block("id", np.zeros(model.n_id), -4.0, 4.0),
        Block("exp", np.zeros(model.n_exp), -4.0, 4.0),
        Block("albedo", np.zeros(model.n_albedo), -4.0, 4.0),
        Block("sh", np.asarray(sh, np.float64), scale=0.1),
        Block("rotation", np.asarray(rotation, np.float64), scale=0.05),
        Block("translation", np.asarray(translation, np.float64), scale=0.01),
        Block("focal", np.array([float(focal)]), 0.2 * focal, 5.0 * focal, scale=0.05 * focal),
    ])


def default_stages(config: FaceFitConfig, fit_focal: bool, detected: bool = False) -> list[Stage]:
    """The landmark stage, then one photometric stage per photo_stages entry (sigma, gamma,
    evaluations[, stall_rel]); detected: the landmarks are a detector's on Face Mesh's points
    (their weight in the photometric stages is config.detected_landmark_weight_photo)."""
    w = config.weights
    photo_landmarks = w["landmarks"] * (config.detected_landmark_weight_photo if detected
                                        else config.landmark_weight_photo)
    priors = dict(id_prior=w["id_prior"], exp_prior=w["exp_prior"])
    pose = ("rotation", "translation") + (("focal",) if fit_focal else ())
    focal_prior = dict(focal_prior=w["focal_prior"]) if fit_focal else {}
    stages = [Stage("landmarks", pose + ("id", "exp"),
                    dict(_landmark_weights(config, w["landmarks"]), **priors, **focal_prior),
                    max_iters=config.landmark_iters)]
    for k, (sigma, gamma, iters, *stall_rel) in enumerate(config.photo_stages):
        weights = dict(_landmark_weights(config, photo_landmarks), photo=w["photo"],
                       albedo_prior=w["albedo_prior"], sh_white=w["sh_white"], **priors, **focal_prior)
        stages.append(Stage(f"photo-{k + 1}", ("id", "exp", "albedo", "sh") + pose,
                            weights, sigma=sigma, gamma=gamma, max_iters=iters,
                            stall_window=config.stall_window if stall_rel else 0,
                            stall_rel=stall_rel[0] if stall_rel else 0.0))
    return stages


def _landmark_weights(config: FaceFitConfig, landmarks: float) -> dict:
    """A stage's landmark term weights: the 68 points' ``landmarks`` and, with a dense_weight,
    the dense points' ("dense") relative to it."""
    if not config.dense_weight:
        return dict(landmarks=landmarks)
    return dict(landmarks=landmarks, dense=landmarks * config.dense_weight)


# ---------------------------------------------------------------------------------------------
# objective
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LandmarkContext:
    """What FaceObjective.landmark_term's gradient needs from landmark_points: the Camera and
    its projection context, the model's landmark context, and where the sliding contour points
    are (None without a sliding contour)."""
    camera: Camera
    camera_ctx: object
    model_ctx: LinearContext
    choice: ContourChoice | None


class FaceObjective:
    """``(values, stage) -> (loss, grads, terms)`` for fitting.solver.fit.

    image (H, W, 3) linear RGB; landmarks (68, 2) pixels; focal0: the focal length the
    focal prior is centred on; forehead: how far above the brows the face region reaches, in
    chin-to-nose-bridge distances; robust_scale: see :meth:`start_stage` (None: plain squared
    errors); contour: the landmarks that slide on the occluding contour (fitting.recipes.contour; None:
    every landmark is the model's fixed point); dense: the photo's dense points (468, 2) pixels
    for the "dense" term (None: none; the model must have dense points); point_weights: (68,) the
    landmark term's weights (None: :func:`landmark_weights`); landmark_robust: None (squared
    distances), or the scale c, in each point's standard deviations (1 / sqrt(weight)), of a
    Geman-McClure landmark term (losses.landmarks_2d_robust: points a detector put more than a
    few deviations away count less). At the first evaluation of each photometric
    stage the depth range is fitted to the face and the face-region mask and the robust scale
    are taken from the render; all stay fixed within the stage (see the module docstring).
    """

    def __init__(self, scene: FaceScene, image, landmarks, mask_erosion: int = 2, focal0: float = 1.0,
                 forehead: float = 0.15, coarse_sigma: float | None = COARSE_SIGMA,
                 robust_scale: float | None = ROBUST_SCALE, coarse_mesh: float | None = COARSE_MESH,
                 contour: ContourLandmarks | None = None, dense=None, point_weights=None,
                 landmark_robust: float | None = None):
        self.scene, self.image, self.target = scene, image, np.asarray(landmarks, np.float64)
        self.dense_target = None if dense is None else np.asarray(dense, np.float64)
        self.contour = contour
        self.focal0, self.forehead = float(focal0), float(forehead)
        self.landmark_weights = landmark_weights() if point_weights is None else np.asarray(point_weights, np.float64)
        self.landmark_robust = None if landmark_robust is None else float(landmark_robust)
        self.mask_erosion = mask_erosion
        self.mask, self._mask_stage = None, None
        self.robust_scale, self.photo_scale = robust_scale, None
        self._robust_loss: losses.GemanMcClure | None = None
        self.coarse_sigma, self.coarse_mesh = coarse_sigma, coarse_mesh
        self._coarse: FaceObjective | None = None

    def photo_level(self, sigma: float) -> "FaceObjective":
        """The objective whose image the photometric term of a stage with this sigma compares:
        this one, or (sigma >= coarse_sigma, working image at least 2 * MIN_SIZE a side) its
        half-resolution copy (see :func:`half_resolution`): the stage's blur already spans about
        a working pixel, and the half-size render costs a quarter of the pixel-face pairs. The
        copy draws the faces of coarse_mesh (fitting.models.mesh_lod.coarse_faces) when set:
        most triangles would cover less than a pixel there, and every one costs host and
        kernel work whatever its size."""
        if (self.coarse_sigma is None or sigma < self.coarse_sigma
                or min(self.image.shape[:2]) < 2 * MIN_SIZE):
            return self
        if self._coarse is None:
            self._coarse = self._half_size()
        return self._coarse

    def _half_size(self) -> "FaceObjective":
        """This objective on the half-resolution image (the scene's half_size, drawing the
        coarse_mesh faces when set): landmarks, focal and mask erosion halved; it has no
        half-resolution copy of its own."""
        model = self.scene.model
        faces = None if self.coarse_mesh is None else coarse_faces(model.mean_shape, model.faces, self.coarse_mesh)
        image, to_half = half_resolution(self.image)
        return type(self)(self.scene.half_size(faces), image, to_half(self.target),
                          mask_erosion=max(1, self.mask_erosion // 2) if self.mask_erosion else 0,
                          focal0=self.focal0 * 0.5, forehead=self.forehead, coarse_sigma=None,
                          robust_scale=self.robust_scale, contour=self.contour,
                          dense=None if self.dense_target is None else to_half(self.dense_target),
                          point_weights=self.landmark_weights, landmark_robust=self.landmark_robust,
                          **self._level_options())

    def _level_options(self) -> dict:
        """Keyword arguments a half-resolution copy of this objective is made with beyond
        FaceObjective's own (a subclass's shared resources)."""
        return {}

    def set_depth_range(self, translation) -> None:
        """Fit near/far to a face at ``translation`` (:func:`depth_range`) in this objective's
        scene and in its half-resolution copy's, for the renders that follow."""
        for objective in (self, self._coarse):
            if objective is not None:
                objective.scene.set_depth_range(translation)

    def __call__(self, values: dict, stage: Stage):
        if self.scene.too_close(values):
            return too_close_result()
        geometry = self.geometry(values)
        photo = self.photo(values, geometry.world, stage) if stage.weights.get("photo") else None
        return self.combine(values, stage, geometry, photo)

    def geometry(self, values: dict) -> Geometry:
        """The placed shape of values (FaceScene.geometry): ``.world`` (V, 3) is what
        :meth:`photo` and :meth:`combine` take."""
        return self.scene.geometry(values)

    def combine(self, values: dict, stage: Stage, geometry: Geometry, photo: tuple | None):
        """``(loss, grads, terms)`` of the stage from the geometry (:meth:`geometry`) and the
        photometric term, (value, grads) as :meth:`photo` gives it, or None when the stage does
        not weigh it."""
        world, geometry_ctx = geometry
        terms = self.point_terms(values, world, stage.weights)
        if photo is not None:
            terms["photo"] = photo
        loss, grads, weighted = losses.weighted_sum(terms | self.prior_terms(values, stage.weights), stage.weights)
        g_world = grads.pop("world", None)
        if g_world is not None:                     # one pass through the model for all terms
            for name, g in self.scene.geometry_vjp(geometry_ctx, g_world).items():
                grads[name] = grads.get(name, 0.0) + g
        return loss, grads, weighted

    def point_terms(self, values: dict, world: np.ndarray, weights: dict) -> dict:
        """The landmark and dense terms of positive weight, {name: (value, grads)}, on world
        vertices (V, 3) float64 numpy."""
        terms = {}
        if weights.get("landmarks"):
            terms["landmarks"] = self.landmark_term(values, world)
        if weights.get("dense"):
            terms["dense"] = self.dense_term(values, world)
        return terms

    def prior_terms(self, values: dict, weights: dict) -> dict:
        """The prior terms of positive weight (coefficients, light, focal), {name: (value, grads)}."""
        terms = {}
        for name, block in (("id_prior", "id"), ("exp_prior", "exp"), ("albedo_prior", "albedo")):
            if weights.get(name):
                value, g = losses.gaussian_prior(values[block], 1.0)
                terms[name] = (value, {block: g["coeffs"]})
        if weights.get("sh_white"):
            value, g = losses.sh_white(values["sh"])
            terms["sh_white"] = (value, {"sh": g["coeffs"]})
        if weights.get("focal_prior"):
            terms["focal_prior"] = self.focal_prior(values["focal"])
        return terms

    def photo(self, values: dict, world, stage: Stage) -> tuple[float, dict]:
        """The photometric term of a stage, (value, grads) in working pixels, at the resolution
        :meth:`photo_level` picks (its stage set-up on the stage's first call); world: the world
        vertices (V, 3), as :meth:`photo_term` takes them."""
        level, level_values = self.photo_start(values, stage)
        return self.in_working_pixels(level, *level.photo_term(level_values, world, stage.sigma, stage.gamma))

    def photo_start(self, values: dict, stage: Stage) -> tuple["FaceObjective", dict]:
        """(the objective at the resolution :meth:`photo_level` picks for the stage, the values
        in its pixels): its stage set up (depth range, face region, robust scale) at the
        stage's first call."""
        level = self.photo_level(stage.sigma)
        level_values = values if level is self else dict(values, focal=values["focal"] * HALF)
        if level._mask_stage != stage.name:
            self.set_depth_range(values["translation"])
            level.start_stage(level_values, stage)
        return level, level_values

    def in_working_pixels(self, level: "FaceObjective", value: float, g: dict) -> tuple[float, dict]:
        """A photometric term (value, grads) of :meth:`photo_start`'s ``level`` in this
        objective's working pixels: a half-size pixel stands for 4 working pixels."""
        if level is self:
            return value, g
        area = 1.0 / (HALF * HALF)
        value, g = value * area, {k: v * area for k, v in g.items()}
        g["focal"] = g["focal"] * HALF
        return value, g

    def landmark_points(self, values: dict, world: np.ndarray) -> tuple[np.ndarray, LandmarkContext]:
        """The model's 68 landmarks projected, (68, 2) working pixels, with the sliding contour
        points (``contour``) re-chosen for these world vertices (V, 3); and the context for
        landmark_term's gradient."""
        camera = self.scene.camera(values["focal"][0])
        points_3d, model_ctx = self.scene.model.landmarks(world)
        choice = None
        if self.contour is not None:      # depth along the optical axis: the camera looks down -z
            choice = self.contour.choose(world, lambda p: (camera.project_pixels(p)[0], -p[:, 2]), self.target)
            points_3d = self.contour.points_3d(world, points_3d, choice)
        points, camera_ctx = camera.project_pixels(points_3d)
        return points, LandmarkContext(camera, camera_ctx, model_ctx, choice)

    def landmark_term(self, values: dict, world: np.ndarray) -> tuple[float, dict]:
        """Sum over the 68 points of weighted squared pixel distances (through Geman-McClure with
        landmark_robust); gradients wrt the world vertices ("world") and focal (a sliding
        point's gradient goes to its chosen vertex)."""
        points, ctx = self.landmark_points(values, world)
        if self.landmark_robust is None:
            value, g = losses.landmarks_2d(points, self.target, self.landmark_weights)
            g_points = g["points"]
        else:
            value, g_points = losses.landmarks_2d_robust(points - self.target, self.landmark_weights,
                                                         self.landmark_robust)
        n = len(points)
        g_cam = ctx.camera.project_pixels_vjp(ctx.camera_ctx, g_points * n, camera="focal")
        g_points, g_world = g_cam["vertices"], 0.0
        if ctx.choice is not None:
            g_points, g_world = self.contour.points_3d_vjp(g_points, ctx.choice)
        g_world = self.scene.model.landmarks_vjp(ctx.model_ctx, g_points)["vertices"] + g_world
        return value * n, dict(world=g_world, focal=np.array([g_cam["focal"].sum()]))

    def dense_term(self, values: dict, world: np.ndarray) -> tuple[float, dict]:
        """Sum over the model's used dense points (dense_use) of squared pixel distances to the
        photo's (dense_target); gradients wrt the world vertices ("world") and focal."""
        if self.dense_target is None:
            raise InputError("the dense landmark term needs the photo's dense points (none were given)")
        camera = self.scene.camera(values["focal"][0])
        model = self.scene.model
        points_3d, model_ctx = model.dense_points(world)
        points, camera_ctx = camera.project_pixels(points_3d)
        value, g = losses.landmarks_2d(points, self.dense_target, model.dense_use.astype(np.float64))
        n = len(points)
        g_cam = camera.project_pixels_vjp(camera_ctx, g["points"] * n, camera="focal")
        g_world = model.dense_points_vjp(model_ctx, g_cam["vertices"])["vertices"]
        return value * n, dict(world=g_world, focal=np.array([g_cam["focal"].sum()]))

    def focal_prior(self, focal) -> tuple[float, dict]:
        """``(ln(f / f0) / ln 2)^2``: halving or doubling the initial focal length f0 costs 1."""
        r = math.log(focal[0] / self.focal0) / math.log(2.0)
        return r * r, dict(focal=np.array([2.0 * r / (math.log(2.0) * focal[0])]))

    def start_stage(self, values: dict, stage: Stage) -> None:
        """Fix what a photometric stage's function depends on, from one render at its start
        (after set_depth_range): the face region (``mask``) and the robust scale
        (``photo_scale``: robust_scale x the median per-pixel linear-RGB error over the face
        region, at least MIN_ROBUST_SCALE; None without robust_scale)."""
        out = self.scene.render(values, stage.sigma, stage.gamma)
        self.mask = self._region(out.alpha[0])
        self._mask_stage = stage.name
        if self.robust_scale is not None:
            errors = np.linalg.norm(out.rgb[0] - self.image, axis=-1)[self.mask]
            median = float(np.median(errors)) if errors.size else 0.0
            self.photo_scale = max(self.robust_scale * median, MIN_ROBUST_SCALE)
            self._robust_loss = losses.GemanMcClure(self.image, self.photo_scale, self.mask)

    def face_region(self, values: dict, sigma: float, gamma: float) -> np.ndarray:
        """(H, W) bool: where the face is rendered (alpha > 0.5) and the photo's landmarks
        outline the face (jaw line and brows raised by ``forehead``), eroded by mask_erosion pixels, less the eyes and
        the inside of the mouth (grown by as much). The landmark outline keeps hair, hats and
        background out even when the rendered face grows over them, and open mouths, teeth
        and eyes are not skin: a skin model would bend the shape trying to explain them."""
        return self._region(self.scene.render(values, sigma, gamma).alpha[0])

    def _region(self, alpha: np.ndarray) -> np.ndarray:
        """face_region from the render's alpha (H, W)."""
        from scipy.ndimage import binary_dilation, binary_erosion

        region = (alpha > 0.5) & self._outlined([ibug68.FACE_OUTLINE], self._forehead_points())
        holes = self._outlined(ibug68.OPENINGS, self.target)       # what a skin model cannot explain
        if self.mask_erosion > 0:
            region = binary_erosion(region, iterations=self.mask_erosion)
            holes = binary_dilation(holes, iterations=self.mask_erosion)
        return region & ~holes

    def _forehead_points(self) -> np.ndarray:
        """The landmarks with the brows (17-26) raised by ``forehead`` times the chin (8) to
        nose-bridge (27) distance, along that direction: the outline then takes in the forehead."""
        pts = self.target.copy()
        pts[ibug68.BROWS] += self.forehead * (pts[ibug68.NOSE_BRIDGE_TOP] - pts[ibug68.CHIN])
        return pts

    def _outlined(self, outlines, points) -> np.ndarray:
        """(H, W) bool: inside any of the polygons through the given indices of points (68, 2)."""
        from skimage.draw import polygon

        inside = np.zeros(self.image.shape[:2], bool)
        for outline in outlines:
            pts = points[list(outline)]
            inside[polygon(pts[:, 1], pts[:, 0], inside.shape)] = True
        return inside

    def photo_term(self, values: dict, world: np.ndarray, sigma: float, gamma: float) -> tuple[float, dict]:
        """Sum over the face region of each pixel's squared linear-RGB error (summed over the
        channels), or of its Geman-McClure kernel at ``photo_scale`` (losses.GemanMcClure, set
        up by start_stage) when that is set; gradients wrt the world vertices ("world"), albedo,
        sh and focal."""
        return photo_terms_together([self], [values], [world], sigma, gamma)[0]

    # what photo_terms_together asks of each objective (the device objective has its own)
    check_render_values = True        # the renderer checks the world vertices and albedo

    def drawn_faces(self):
        """The faces the photometric render draws, as the renderer takes them."""
        return self.scene.faces

    def photo_albedo(self, values: dict) -> tuple:
        """(the render's albedo (V, 3) float64, the context for :meth:`photo_grads`)."""
        return self.scene.model.albedo(values["albedo"])

    def photo_loss(self, rgb: np.ndarray) -> tuple:
        """(photo_term's value, its gradient wrt the render (1, H, W, 3)) of a render rgb (1, H,
        W, 3) float64; the value as :meth:`photo_value` reads it."""
        pixels = max(int(self.mask.sum()), 1)
        if self._robust_loss is None:
            value, g = losses.image_l2(rgb[0], self.image, self.mask)
            count = 3.0 * pixels
            return value * count, g["pred"][None] * count
        count = float(pixels)
        value, g = self._robust_loss(rgb[0], grad_scale=count)
        return value * count, g["pred"][None]

    def photo_value(self, value) -> float:
        """:meth:`photo_loss`'s value as a float."""
        return value

    def photo_grads(self, albedo_ctx, g_world, g_albedo, g_sh: np.ndarray, g_focal: np.ndarray) -> dict:
        """photo_term's gradients from the render's: world (V, 3), albedo through the model
        (albedo_ctx: :meth:`photo_albedo`'s; g_albedo (V, 3)), sh (3, 9) and focal ((2,)
        [dL/dfx, dL/dfy] -> (1,))."""
        return dict(world=g_world, albedo=self.scene.model.albedo_vjp(albedo_ctx, g_albedo)["coeffs"], sh=g_sh,
                    focal=np.array([g_focal.sum()]))


def photo_terms_together(levels: list[FaceObjective], values: list[dict], worlds: list, sigma: float,
                         gamma: float) -> list[tuple]:
    """Each objective's FaceObjective.photo_term (value, grads) from one render and one backward
    of all of them (with the first one's renderer): objectives of one class whose scenes share
    image size, drawn faces and renderer settings, their stages set up; each view drawn with its
    own camera, SH light, depth range and face region (only the regions' tiles are rasterised:
    the loss and its gradient are the same). values, worlds: per objective, its values and world
    vertices (V, 3) (numpy, or device arrays for the device objective)."""
    first = levels[0]
    albedos = [level.photo_albedo(v) for level, v in zip(levels, values)]
    out = first.scene.renderer.forward(
        _stack(worlds), first.drawn_faces(), [level.scene.camera(v["focal"][0]) for level, v in zip(levels, values)],
        albedo=_stack([albedo for albedo, _ in albedos]), light=[SHLight(v["sh"]) for v in values], grads=PHOTO_GRADS,
        roi=np.stack([level.mask for level in levels]), sigma=sigma, gamma=gamma,
        near=[level.scene.settings.near for level in levels], far=[level.scene.settings.far for level in levels],
        check_values=first.check_render_values)
    photo = [level.photo_loss(out.rgb[k:k + 1]) for k, level in enumerate(levels)]
    g_img = first.scene.renderer.backward(out, grad_rgb=_stack([g_rgb[0] for _, g_rgb in photo]))
    return [(level.photo_value(value), level.photo_grads(ctx, g_img["vertices"][k], g_img["albedo"][k],
                                                         g_img["light"]["coefficients"][k], g_img["focal"][k]))
            for k, (level, (value, _), (_, ctx)) in enumerate(zip(levels, photo, albedos))]


def _stack(arrays: list):
    """(B, ...) from B arrays of one shape (...), numpy or pyopencl (one of them: a view)."""
    if len(arrays) == 1:
        return arrays[0].reshape((1,) + arrays[0].shape)
    return cla.stack(arrays) if isinstance(arrays[0], cla.Array) else np.stack(arrays)


class DeviceFaceObjective(DeviceFaceEvaluation, FaceObjective):
    """FaceObjective evaluated on the OpenCL device of its scene's renderer, in buffers that
    live across evaluations (fitting.device.face_objective); the numpy FaceObjective stays the
    reference it is tested against. Extra argument: device_model (see DeviceFaceEvaluation)."""


# ---------------------------------------------------------------------------------------------
# the fit
# ---------------------------------------------------------------------------------------------

@dataclass
class FaceFit:
    """What :func:`fit_face` returns.

    values: the fitted blocks (focal in working-image pixels); scene: the FaceScene used;
    image (s, s, 3) / landmarks (68, 2): the working inputs; crop: full photo -> working image;
    mask (s, s) bool: the face region of the last stage; result: the solver's FitResult
    (history, outcomes, interrupted); objective: the FaceObjective used (its face-region
    settings serve the metrics).
    """
    values: dict
    scene: FaceScene
    image: np.ndarray
    landmarks: np.ndarray
    crop: Crop
    mask: np.ndarray
    result: FitResult
    objective: FaceObjective

    def fitted_landmarks(self) -> np.ndarray:
        """(68, 2) fitted landmarks in working-image pixels (the sliding contour points, when the
        fit has them, chosen for the fitted face)."""
        world, _ = self.scene.geometry(self.values)
        return self.objective.landmark_points(self.values, world)[0]

    def metrics(self) -> dict:
        """Landmark error (mean pixel distance, working and full resolution, over the landmarks
        the fit weighs: a Face Mesh tie gives 11 no weight, tied_landmarks) and the PSNR of the
        final render in the face region, in sRGB (what a viewer sees), dB."""
        from softras_cl.srgb import to_srgb

        used = self.objective.landmark_weights > 0
        err = float(np.linalg.norm(self.fitted_landmarks()[used] - self.landmarks[used], axis=1).mean())
        rgb = self.scene.render(self.values, *SHARP).rgb[0]
        mask = self.objective.face_region(self.values, *SHARP)
        return dict(landmark_error_px=err, landmark_error_px_full=err / self.crop.scale,
                    psnr_face_db=psnr(to_srgb(np.clip(rgb, 0, 1)), to_srgb(np.clip(self.image, 0, 1)), mask),
                    face_pixels=int(mask.sum()))


def fit_face(photo, landmarks, model, config: FaceFitConfig = FaceFitConfig(), out_dir=None,
             progress: bool = True, resume: bool = False, dense=None, face_mesh_landmarks: bool = False) -> FaceFit:
    """Fit ``model`` to a photo (H, W, 3) linear RGB and its 68 landmarks (68, 2) pixels.

    face_mesh_landmarks: the landmarks are Face Mesh's points (a detector such as MediaPipe's put
    them there: fitting.detection.PhotoLandmarks.on_face_mesh), not an annotator's iBUG points,
    for config.landmark_map "auto" (see :func:`landmark_model`).

    dense: the photo's dense points (N, 2) pixels, MediaPipe Face Mesh's 468 (see
    :func:`detected_dense`), for config.dense_weight > 0 (ignored at 0); InputError, before any
    fitting, when the weight asks for them and they or the model's dense points are missing.

    With ``out_dir`` the solver writes checkpoint.npz (best values so far) as it goes,
    history.json and loss_curve.png; Ctrl-C stops and keeps the best values (result.interrupted);
    ``resume`` continues from the checkpoint in ``out_dir`` (see softras_cl.fitting.solver).
    """
    if model.n_landmarks != ibug68.COUNT:
        raise ValueError(f"the face model defines {model.n_landmarks} landmarks; fitting needs the "
                         f"{ibug68.COUNT} iBUG points (pass a landmark mapping file with the model)")
    check_dense_inputs(config, model, dense)
    model, point_weights = tied_landmarks(model, config.landmark_map, face_mesh_landmarks,
                                          config.detected_landmark_weights)
    model = model.truncated(config.n_id, config.n_exp, config.n_albedo)
    objective, crop, params = prepare_fit(photo, landmarks, model, config, dense, point_weights,
                                          landmark_robust(config, face_mesh_landmarks))
    check_landmark_layout(landmarks)      # after prepare_fit's input checks (shape, area, size)
    stages = default_stages(config, fit_focal=config.focal is None, detected=face_mesh_landmarks)
    result = fit(params, objective, stages, out_dir=out_dir, progress=progress, resume=resume)
    if objective.mask is None:      # no photometric stage ran here (e.g. resuming a finished fit)
        objective.set_depth_range(result.values["translation"])
    mask = objective.mask if objective.mask is not None else objective.face_region(result.values, *SHARP)
    return FaceFit(result.values, objective.scene, objective.image, objective.target, crop, mask, result, objective)


def prepare_fit(photo, landmarks, model, config: FaceFitConfig, dense=None, point_weights=None,
                landmark_robust: float | None = None) -> tuple[FaceObjective, Crop, ParamSet]:
    """Where :func:`fit_face` starts: photo (H, W, 3) linear RGB and its landmarks (68, 2)
    pixels -> (the FaceObjective of the working image, the Crop from the photo, the ParamSet at
    the initial pose, focal and light). ``model`` is used as given (not truncated); dense: the
    photo's dense points (N, 2) pixels, used when config.dense_weight > 0; point_weights: the
    landmark term's (68,) weights (None: :func:`landmark_weights`; see :func:`tied_landmarks`);
    landmark_robust: FaceObjective's (see :func:`landmark_robust`)."""
    image, target, crop = prepare_photo(photo, landmarks, config.size)
    h, w = np.shape(photo)[:2]
    principal = crop.to_work([[w / 2.0 - 0.5, h / 2.0 - 0.5]])[0]
    if config.focal is None:
        focal = 0.5 * max(h, w) / math.tan(math.radians(config.fov_deg) / 2.0) * crop.scale
    else:
        focal = float(config.focal) * crop.scale
    zero = dict(id=np.zeros(model.n_id), exp=np.zeros(model.n_exp), albedo=np.zeros(model.n_albedo))
    mean_landmarks, _ = model.landmarks(model.shape(zero["id"], zero["exp"])[0])
    rotation, translation = initial_pose(mean_landmarks, target, focal, principal)
    scene = FaceScene(model, image.shape[:2], config.dtype, depth_range=depth_range(translation),
                      principal=principal)
    objective = objective_class(config.objective, scene)(
        scene, image, target, config.mask_erosion, focal0=focal, forehead=config.forehead,
        coarse_sigma=config.coarse_sigma, robust_scale=config.robust_scale, coarse_mesh=config.coarse_mesh,
        contour=jaw_candidates(model) if config.contour_landmarks == "sliding" else None,
        dense=crop.to_work(dense) if config.dense_weight else None, point_weights=point_weights,
        landmark_robust=landmark_robust)
    values = dict(zero, rotation=rotation, translation=translation, focal=np.array([focal]))
    sh = initial_light(scene, values, image)
    return objective, crop, face_params(model, focal, rotation, translation, sh)



def landmark_robust(config: FaceFitConfig, face_mesh_landmarks: bool) -> float | None:
    """The landmark term's Geman-McClure scale (FaceObjective's landmark_robust) for landmarks a
    detector found (config.detected_landmark_robust), or None (squared distances) for a file's."""
    return config.detected_landmark_robust if face_mesh_landmarks else None


def objective_class(where: str, scene: FaceScene) -> type:
    """The objective class of FaceFitConfig.objective ``where`` for a scene: FaceObjective (the
    numpy reference, "host") or DeviceFaceObjective ("device"; "auto" picks it on a GPU with
    float64: fitting.device.where.on_device). InputError for "device" on a device without float64."""
    return DeviceFaceObjective if on_device(where, scene.renderer.device) else FaceObjective


def landmark_model(model, landmark_map: str, face_mesh_landmarks: bool = False):
    """``model`` with its 68 landmarks tied as FaceFitConfig.landmark_map says, for landmarks that
    are Face Mesh's points (``face_mesh_landmarks``) or an annotator's: the model itself for "model", or a model
    whose landmark i is the model's Face Mesh point MP468_TO_IBUG68[i] (dense_faces/dense_bary)
    where its correspondence uses that point (dense_use), the model's own landmark elsewhere.
    InputError for "face-mesh" on a model without a Face Mesh correspondence."""
    check_landmark_map(landmark_map, model)
    has_face_mesh = model.n_dense == face_mesh.COUNT
    if landmark_map == "model" or (landmark_map == "auto" and not (face_mesh_landmarks and has_face_mesh)):
        return model
    mesh_points = face_mesh.MP468_TO_IBUG68
    used = model.dense_use[mesh_points]
    faces = np.where(used, model.dense_faces[mesh_points], model.landmark_faces)
    bary = np.where(used[:, None], model.dense_bary[mesh_points], model.landmark_bary)
    return model.with_landmarks(faces, bary)


def tied_landmarks(model, landmark_map: str, face_mesh_landmarks: bool = False,
                   measured: bool = True) -> tuple[object, np.ndarray]:
    """(:func:`landmark_model`'s model, the landmark term's (68,) weights for its landmarks):
    :func:`landmark_weights`, with 0 for the points a Face Mesh tie leaves at the model's own
    point (the correspondence does not use their Face Mesh vertex: jaw 0-3 and 13-16, inner
    lower lip 65-67): MediaPipe puts most of them 0.05-0.17 eye distances away, and weighted they bent
    the shape (bench face, detected landmarks, 10 faces per bin, paired: shape error 11% +- 4%
    lower at |yaw| 0-15 without them, 5% +- 2% at 15-45). ``measured`` (FaceFitConfig's
    detected_landmark_weights): for landmarks a detector found (``face_mesh_landmarks``) tied to Face
    Mesh's points, the used points weigh by their measured noise instead
    (:func:`detected_landmark_weights`); a file's landmarks keep :func:`landmark_weights`."""
    tied = landmark_model(model, landmark_map, face_mesh_landmarks)
    weights = landmark_weights()
    if tied is not model:
        used = model.dense_use[face_mesh.MP468_TO_IBUG68]
        weights = detected_landmark_weights(used) if measured and face_mesh_landmarks else np.where(used, weights, 0.0)
    return tied, weights


def check_landmark_map(landmark_map: str, model) -> None:
    """InputError unless ``model`` has what landmark_map (FaceFitConfig) needs: MediaPipe Face
    Mesh's points for "face-mesh"."""
    if landmark_map == "face-mesh" and model.n_dense != face_mesh.COUNT:
        raise InputError(f"landmark_map 'face-mesh' needs a face model with MediaPipe Face Mesh's {face_mesh.COUNT} "
                         f"points (dense_faces / dense_bary); face model {model.name or '(unnamed)'} has "
                         f"{model.n_dense} (the shipped demo model has them)")


def check_dense_inputs(config: FaceFitConfig, model, dense) -> None:
    """InputError unless a config with a dense_weight has what the dense term needs: a model with
    dense points and the photo's (model.n_dense, 2) finite points. Nothing to check at weight 0."""
    if not config.dense_weight:
        return
    if not model.has_dense:
        raise InputError(f"the dense landmark term ({_dense_option(config)}) needs a face model with dense points; "
                         f"face model {model.name or '(unnamed)'} has none (the shipped demo model has "
                         "MediaPipe Face Mesh's 468)")
    if dense is None:
        raise InputError(f"the dense landmark term ({_dense_option(config)}) needs the photo's dense points: MediaPipe "
                         "Face Mesh's 468, which only the MediaPipe detector gives (landmarks read from a "
                         "file or found by dlib have none)")
    points = np.asarray(dense, np.float64)
    if points.shape != (model.n_dense, 2):
        raise InputError(f"dense points must have shape ({model.n_dense}, 2), got {points.shape}")
    input_check(lambda: check_finite("dense points", points))


def _dense_option(config: FaceFitConfig) -> str:
    return f"dense_weight {config.dense_weight:g}, fit-face --dense-landmarks"


def detected_dense(face) -> np.ndarray | None:
    """The Face Mesh points (468, 2) pixels of a detected face (fitting.detection's
    FaceCandidate, a PhotoLandmarks' ``face``; its 10 iris points left out), or None (no
    candidate: landmarks from a file; dlib's candidates have none)."""
    if face is None or face.dense is None:
        return None
    return np.asarray(face.dense[:face_mesh.COUNT], np.float64)
