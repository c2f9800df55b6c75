"""Hostile photos for the detectors: two people side by side (one is chosen, the largest, and
said), a portrait (which body parts are in view) and a photo larger than the detectors need
(searched on a reduced copy, the results in the photo's pixels). docs/reliability.md."""
import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.detect


def rgb(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Two photos side by side, the shorter one padded at its top with its own top row."""
    height = max(left.shape[0], right.shape[0])
    pad = [np.pad(p, ((height - p.shape[0], 0), (0, 0), (0, 0)), mode="edge") for p in (left, right)]
    return np.ascontiguousarray(np.concatenate(pad, 1))


def test_two_people_side_by_side_are_found_and_the_larger_is_chosen(examples_data):
    from softras_cl.fitting.detection.people import detect_person

    person = rgb(examples_data / "people" / "cameraman.png")
    smaller = np.asarray(Image.fromarray(person).resize((341, 341), Image.BOX))
    found = detect_person(side_by_side(person, smaller), "two.png")       # "no person found" before
    assert found.box[0] + found.box[2] < 512, found.box       # the larger, on the left
    assert found.box[3] > 300 and found.score > 0.8
    assert "2 people found" in found.note and "the largest" in found.note, found.note
    twins = detect_person(side_by_side(person, person), "twins.png")
    assert "2 people found" in twins.note and twins.box[3] > 300, twins.note


def test_a_portraits_body_parts_in_view(examples_data):
    from softras_cl.fitting.detection.people import detect_person
    from softras_cl.fitting.recipes.body_photo import fit_objective, in_view_line, parts_in_view

    photo = rgb(examples_data / "astronaut.png")
    found = detect_person(photo)
    parts = parts_in_view(found.keypoints, found.visibility, photo.shape[:2])
    assert in_view_line(parts) == "in view: head, shoulders, arms; not in view: hips, legs"
    assert fit_objective(parts) == "keypoints"
    whole = rgb(examples_data / "people" / "cameraman.png")
    found = detect_person(whole)
    parts = parts_in_view(found.keypoints, found.visibility, whole.shape[:2])
    assert fit_objective(parts) == "full" and parts["hips"] == 2


class Spy:
    """Wraps a function, recording the shape of the image each call gets (its first argument)."""

    def __init__(self, function):
        self.function, self.shapes = function, []

    def __call__(self, image, *args, **kwargs):
        self.shapes.append(np.asarray(image).shape)
        return self.function(image, *args, **kwargs)


def enlarged(photo: np.ndarray, factor: int) -> np.ndarray:
    """The photo ``factor`` times larger (each pixel a factor x factor block)."""
    return np.ascontiguousarray(photo.repeat(factor, 0).repeat(factor, 1))


@pytest.mark.slow
def test_a_large_photos_person_is_found_on_a_reduced_copy(examples_data, monkeypatch):
    from softras_cl.fitting.detection import people

    photo = rgb(examples_data / "people" / "cameraman.png")
    normal = people.detect_person(photo)
    spy = Spy(people._pose_in)
    monkeypatch.setattr(people, "_pose_in", spy)
    large = people.detect_person(enlarged(photo, 5))               # 2560 x 2560
    assert spy.shapes and max(max(s[:2]) for s in spy.shapes) <= 2048, spy.shapes
    assert large.mask.shape == (2560, 2560) and "reduced" in large.note
    seen = normal.visibility > 0.5                 # the pose model sees the 2048 px copy, not the 512 px photo
    offsets = np.linalg.norm(large.keypoints - ((normal.keypoints + 0.5) * 5 - 0.5), axis=1)[seen]
    assert np.median(offsets) < 5 * 5, offsets


@pytest.mark.slow
def test_a_large_photos_face_is_found_on_a_reduced_copy(examples_data, monkeypatch):
    from softras_cl.fitting.detection import find, mediapipe_backend

    photo = rgb(examples_data / "astronaut.png")
    normal = find.find_faces(photo)[0]
    spy = Spy(mediapipe_backend.find)
    monkeypatch.setattr(mediapipe_backend, "find", spy)
    large = find.find_faces(enlarged(photo, 5))[0]                 # 2560 x 2560
    assert spy.shapes == [(2048, 2048, 3)], spy.shapes
    assert np.abs(large.landmarks - ((normal.landmarks + 0.5) * 5 - 0.5)).max() < 5 * 4
    assert "reduced" in large.found_by


def test_normal_photos_are_searched_as_they_are(examples_data):
    from softras_cl.fitting.detection.find import reduced_copy

    photo = rgb(examples_data / "astronaut.png")
    same, factor = reduced_copy(photo)
    assert same is photo and factor == 1.0
    small, factor = reduced_copy(np.zeros((6000, 8000, 3), np.uint8))
    assert small.shape == (1536, 2048, 3) and factor == pytest.approx(8000 / 2048)
