"""fit-body on hostile real photos: two people side by side (the largest fitted, said on
stdout), a portrait (the parts in view said, the keypoints in view fitted without the mask's
silhouette) and a face close-up (refused, naming what is missing). docs/reliability.md."""
import json

import numpy as np
import pytest
from PIL import Image

from softras_cl.errors import EXIT_INPUT

FAST = ["--size", "64", "--budget", "fast", "--no-progress"]
pytestmark = pytest.mark.detect


@pytest.mark.slow
def test_fit_body_of_two_people_fits_the_larger_and_says_so(run_cli, tmp_path, examples_data):
    person = np.asarray(Image.open(examples_data / "people" / "cameraman.png").convert("RGB"))
    Image.fromarray(np.concatenate([person, person], 1)).save(tmp_path / "two.png")
    result = run_cli("fit-body", tmp_path / "two.png", "--out", tmp_path / "fit", *FAST)
    assert result.code == 0, result.err                       # exit 1 "no person found" before
    assert "2 people found" in result.out and "fitted person 0, the largest" in result.out, result.out
    doc = json.loads((tmp_path / "fit" / "params.json").read_text())
    assert "2 people found" in doc["detection"]["note"] and doc["detection"]["people"] == 2


@pytest.mark.slow
def test_fit_body_of_a_portrait_says_what_is_in_view_and_fits_it(run_cli, tmp_path, examples_data):
    result = run_cli("fit-body", examples_data / "astronaut.png", "--out", tmp_path / "fit", *FAST)
    assert result.code == 0, result.err
    assert "in view: head, shoulders, arms; not in view: hips, legs" in result.out, result.out
    doc = json.loads((tmp_path / "fit" / "params.json").read_text())
    assert doc["objective"] == "keypoints"
    assert doc["metrics"]["keypoint_error_px_full"] < 40      # 53.7 px with the silhouette: the head fitted twice its size


def test_fit_body_of_a_face_close_up_is_refused_naming_what_is_missing(run_cli, tmp_path, examples_data):
    person = Image.open(examples_data / "people" / "cameraman.png").convert("RGB")
    person.crop((120, 40, 300, 180)).save(tmp_path / "head.png")
    result = run_cli("fit-body", tmp_path / "head.png", "--out", tmp_path / "fit", *FAST)
    assert result.code == EXIT_INPUT, (result.out, result.err)
    assert "too little of the body is in view" in result.err and "not in view:" in result.err, result.err
    assert "hips" in result.err and "both shoulders or both hips" in result.err
    assert not (tmp_path / "fit").exists()
