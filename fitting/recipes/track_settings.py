"""The face tracker's settings, without the renderer: TrackConfig, every knob of
fitting.recipes.face_track (the identity fit's budget and size, the per-frame fit's evaluations,
weights and temporal terms, the smoothing), checked when made. Plain data on numpy: the command
line reads it for its options and --help without loading OpenCL."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.recipes.face_settings import FaceFitConfig, joint_config

__all__ = ["TrackConfig"]


@dataclass(frozen=True)
class TrackConfig:
    """Every knob of the tracker.

    keyframes: frames of the identity fit; identity_passes: its joint fits (see fit_identity: the
        second on landmarks corrected by the first's detector offsets); identity_budget / size:
        its schedule (fitting.recipes.face BUDGETS) and working size.
    frame_iters: L-BFGS evaluations per frame.
    landmark_weight: the landmark term's w (1 / noise^2, noise in working pixels).
    exp_prior: the expression prior's weight.
    rotation_speed (rad), translation_speed (m), exp_speed (std): the random-walk speed per
        square-root second of the temporal terms (smaller: steadier and slower to follow).
    momentum: in [0, 1], how much of the last frame's velocity the temporal terms expect to
        carry on (0: a random walk around the last values).
    light_speed: each frame's light (FrameLight) as a random walk of this fraction of the
        identity's ambient light per square-root second; 0: the identity's light for every frame.
    smooth_lag: frames of the fixed-lag smoothing pass (FixedLagSmoother; 0: none).

    The speeds' defaults: on bench track's trajectories (60 frames at 30 fps, true identity,
    1.5 px landmark noise) translation 0.005 m lagged the head's depth by 11 mm (vertex error 9 mm);
    0.02 m with rotation 0.2 rad and momentum 1 gave 1.7 mm at a third of the jitter of the
    temporal terms left out (2.1 against 6.2 mm/frame^2); momentum 1 beat 0 at every setting.
    """
    keyframes: int = 4
    identity_passes: int = 2
    identity_budget: str = "fast"
    size: int = 256
    frame_iters: int = 30
    landmark_weight: float = 0.25
    exp_prior: float = 1.0
    rotation_speed: float = 0.2
    translation_speed: float = 0.02
    exp_speed: float = 1.0
    momentum: float = 1.0
    light_speed: float = 0.1
    smooth_lag: int = 3

    def __post_init__(self):
        for name in ("keyframes", "identity_passes", "frame_iters", "smooth_lag"):
            value, least = getattr(self, name), 0 if name == "smooth_lag" else 1
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise InputError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("landmark_weight", "exp_prior", "rotation_speed", "translation_speed", "exp_speed"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number, got {value!r}")
        if not (isinstance(self.momentum, (int, float)) and 0.0 <= self.momentum <= 1.0):
            raise InputError(f"momentum must be a number in [0, 1], got {self.momentum!r}")
        if not (isinstance(self.light_speed, (int, float)) and math.isfinite(self.light_speed)
                and self.light_speed >= 0):
            raise InputError(f"light_speed must be a number >= 0, got {self.light_speed!r}")
        FaceFitConfig.from_budget(self.identity_budget, size=self.size)     # checks both

    def face_config(self) -> FaceFitConfig:
        """The identity fit's config: the joint fit's landmark weight (face_views.joint_config)
        and the identity prior times the keyframes. The keyframes' landmarks come from one
        detector on one face and share its errors, so N keyframes do not hold N times the
        evidence of one photo; the prior weighs against them as against a single photo's. On
        bench track's path-traced frames (textured, shadowed faces, whose detected landmarks
        bend the shape) the identity's error ratio went 1.41 -> 1.18 and 1.73 -> 1.39 on two
        sequences, on softras-cl's frames 0.20 -> 0.22 (docs/face_tracking.md)."""
        config = joint_config(FaceFitConfig.from_budget(self.identity_budget, size=self.size))
        weights = dict(config.weights, id_prior=config.weights["id_prior"] * self.keyframes)
        return dataclasses.replace(config, weights=weights)
