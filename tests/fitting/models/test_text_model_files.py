"""A text file given as a body or face model is refused with an error that says what the loader
expected."""
import pytest

from softras_cl.fitting.models.body_loaders import load_body_model
from softras_cl.fitting.models.face_loaders import load_face_model


@pytest.mark.parametrize("load, name, match", [
    (load_body_model, "notes.txt", "neither a pickle"),
    (load_face_model, "model.npz", "unknown face model layout.*project .npz"),
], ids=["body", "face"])
def test_a_text_file_is_not_a_model(tmp_path, load, name, match):
    path = tmp_path / name
    path.write_text("this is not a model\n")
    with pytest.raises(ValueError, match=match):
        load(path)
