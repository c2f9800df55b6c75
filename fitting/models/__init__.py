"""Shape models for fitting, installed as ``softras_cl.fitting.models``.

Morphable face models and skinned body models, their file-format loaders, and the demo models
that ship with the project under ``data/`` (built by scripts in ``scripts/``; attribution in
``data/demo_face.md`` and ``data/demo_body.md``). Import the submodules directly.
"""
