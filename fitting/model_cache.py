"""The face and body models of the fits, loaded once per process (a batch worker fits many
items with the same model)."""
from __future__ import annotations

import functools

__all__ = ["load_model"]


@functools.lru_cache(maxsize=8)
def load_model(kind: str, path: str | None = None, landmarks: str | None = None):
    """The face or body model (``kind``; the shipped demo model when ``path`` is None; a face
    model's ``landmarks`` mapping file), loaded once per process."""
    if kind == "face":
        from softras_cl.fitting.models.face_loaders import load_demo_face_model, load_face_model
        return load_demo_face_model() if path is None else load_face_model(path, landmarks=landmarks)
    from softras_cl.fitting.models.body_loaders import load_body_model, load_demo_body_model
    return load_demo_body_model() if path is None else load_body_model(path)
