"""Every fit's stages and term weights in one table per fit and budget, as the recipes build them
(fitting.recipes: face.default_stages, face_settings.joint_config, body.default_stages,
body_photo.photo_stages, track_settings.TrackConfig), written as Markdown: docs/fit_stages.md is
this module's output (scripts/write_fit_stages.py; a test checks the page is current)."""
from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace

from softras_cl.fitting.recipes import body, body_settings, face, face_settings
from softras_cl.fitting.recipes.body_photo import photo_stages
from softras_cl.fitting.recipes.body_settings import BodyFitConfig
from softras_cl.fitting.recipes.face_settings import FaceFitConfig, joint_config
from softras_cl.fitting.recipes.track_settings import TrackConfig

__all__ = ["stage_rows", "fit_stages_markdown"]

HEADER = ("stage", "free blocks", "sigma", "gamma", "evaluations", "term weights")


def _number(value) -> str:
    return "" if value is None else f"{value:g}"


def stage_rows(stages) -> list[tuple[str, ...]]:
    """One row of HEADER per fitting.solver.Stage."""
    return [(s.name, ", ".join(s.free), _number(s.sigma), _number(s.gamma), str(s.max_iters),
             ", ".join(f"{k} {w:g}" for k, w in s.weights.items())) for s in stages]


def _table(rows) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _face_sections() -> list[str]:
    out = ["## fit-face (fitting.recipes.face)",
           "One photo; the focal length is free unless --focal gives it (then no focal block or prior)."]
    for budget in face_settings.BUDGETS:
        config = FaceFitConfig.from_budget(budget)
        out += [f"### --budget {budget}", _table(stage_rows(face.default_stages(config, fit_focal=True)))]
    joint = joint_config(FaceFitConfig.from_budget("default"))
    out += ["## fit-face --same-person (fitting.recipes.face_views), --budget default",
            "Each photo's blocks are its own (exp.k, sh.k, rotation.k, translation.k, focal.k); id and "
            "albedo are shared and their priors counted once.",
            _table(stage_rows(face.default_stages(joint, fit_focal=True)))]
    return out


def _track_sections() -> list[str]:
    config = TrackConfig()
    identity = config.face_config()
    knobs = ", ".join(f"{f.name} {getattr(config, f.name)}" for f in fields(config))
    return ["## track-face (fitting.recipes.face_track)",
            f"The identity on {config.keyframes} keyframes (the joint fit above at --budget "
            f"{config.identity_budget}, its identity prior weighed once per keyframe):",
            _table(stage_rows(face.default_stages(identity, fit_focal=True))),
            "Then one stage per frame: rotation, translation, exp for --frame-iters evaluations of the "
            "landmark term, the expression prior and the temporal terms (TrackConfig: " + knobs + ")."]


def _body_sections() -> list[str]:
    targets = {"a part-coloured target with --joints": SimpleNamespace(rgb=True, joints=True),
               "a mask (--silhouette)": SimpleNamespace(rgb=None, joints=None)}
    out = ["## fit-body on a rendered target (fitting.recipes.body)",
           "Terms without data are dropped: the image term for a mask, the joints without --joints."]
    for budget in body_settings.BUDGETS:
        config = BodyFitConfig.from_budget(budget)
        for what, target in targets.items():
            out += [f"### --budget {budget}, {what}", _table(stage_rows(body.default_stages(config, target)))]
    sigmas = ", ".join(f"{name} {sigma:g}" for name, sigma in body_settings.POSE_SIGMA.items())
    return out + [f"The pose prior weighs each joint's axis-angle by 1 / sigma^2, sigma in rad by joint (POSE_SIGMA; "
                  f"others {body_settings.DEFAULT_POSE_SIGMA:g}): {sigmas}."]


def _body_photo_sections() -> list[str]:
    out = ["## fit-body on a photo of a person (fitting.recipes.body_photo)",
           "The torso stage runs from four start yaws and keeps the best; keypoint weights are the map's "
           "times the detector's visibility."]
    for budget in body_settings.PHOTO_BUDGETS:
        out += [f"### --budget {budget}", _table(stage_rows(photo_stages(budget)))]
    return out


def fit_stages_markdown() -> str:
    """docs/fit_stages.md: every fit's stages per budget (free blocks, sigma, gamma, evaluations,
    term weights)."""
    parts = ["# The fits' stages and weights",
             "Generated from the recipes by `python scripts/write_fit_stages.py` (fitting.reports.stages): "
             "each fit's stages in order, per budget. sigma and gamma are the rasteriser's for a stage "
             "that renders (blank: no render); evaluations cap the stage's objective evaluations; the "
             "weights multiply the terms named in each recipe's docstring."]
    for section in (_face_sections, _track_sections, _body_sections, _body_photo_sections):
        parts += section()
    return "\n\n".join(parts) + "\n"
