"""fit-face on landmarks that cannot be a face's exits 1 before fitting and says why; a mirrored or
rolled photo with its own landmarks fits (exit 0); a corrupt checkpoint is named on --resume."""
import numpy as np
import pytest

from softras_cl.errors import EXIT_INPUT, EXIT_OK, EXIT_RESULT
from softras_cl.io.images import read_image, write_image
from softras_cl.io.landmarks import read_landmarks, write_pts
from support.landmark_layouts import mirrored, shuffled

FAST = ("--budget", "fast", "--size", "32", "--no-progress")


def one_line(result) -> str:
    return " ".join(result.err.split())


def test_shuffled_landmarks_exit_1_naming_the_cause(run_cli, examples_data, examples_landmarks, tmp_path):
    write_pts(tmp_path / "shuffled.pts", shuffled(read_landmarks(examples_landmarks / "astronaut.pts"), 0))
    result = run_cli("fit-face", examples_data / "astronaut.png", "--landmarks", tmp_path / "shuffled.pts",
                     "--out", tmp_path / "fit", *FAST)
    assert result.code == EXIT_RESULT
    assert "the landmarks cannot be a face's" in one_line(result)
    assert "not in the iBUG 300-W 68-point order (shuffled" in one_line(result)
    assert not (tmp_path / "fit" / "params.npz").exists() and not (tmp_path / "fit" / "checkpoint.npz").exists()


def _mirror(photo, points):
    return photo[:, ::-1], mirrored(points, photo.shape[1])


def _roll_90(photo, points):
    """np.rot90 (a quarter turn counter-clockwise): pixel (x, y) goes to (y, W - 1 - x)."""
    return np.rot90(photo), np.column_stack([points[:, 1], photo.shape[1] - 1 - points[:, 0]])


@pytest.mark.slow
@pytest.mark.parametrize("turn", [_mirror, _roll_90], ids=["mirrored", "roll 90"])
def test_a_mirrored_or_rolled_photo_with_its_landmarks_fits(run_cli, examples_data, examples_landmarks, tmp_path, turn):
    photo, points = turn(read_image(examples_data / "astronaut.png")[..., :3],
                         read_landmarks(examples_landmarks / "astronaut.pts"))
    write_image(tmp_path / "photo.png", np.ascontiguousarray(photo))
    write_pts(tmp_path / "photo.pts", points)
    result = run_cli("fit-face", tmp_path / "photo.png", "--landmarks", tmp_path / "photo.pts",
                     "--out", tmp_path / "fit", *FAST)
    assert result.code == EXIT_OK, result.err
    assert (tmp_path / "fit" / "complete.json").is_file()


@pytest.mark.slow
def test_resume_from_a_corrupt_checkpoint_names_the_file(run_cli, examples_data, examples_landmarks, tmp_path):
    args = ("fit-face", examples_data / "astronaut.png", "--landmarks", examples_landmarks / "astronaut.pts",
            "--out", tmp_path / "fit", *FAST)
    assert run_cli(*args).code == EXIT_OK
    checkpoint = tmp_path / "fit" / "checkpoint.npz"
    checkpoint.write_bytes(checkpoint.read_bytes()[:300])
    result = run_cli(*args, "--resume")
    assert result.code == EXIT_INPUT
    assert f"checkpoint {checkpoint} is corrupt (truncated or damaged: BadZipFile" in one_line(result)
    assert "start the fit again without --resume" in one_line(result)
