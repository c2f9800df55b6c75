"""MediaPipe's 33 pose keypoints: their order and names, and the point of the body model each
stands for.

:data:`NAMES` are the pose model's keypoints in its order ("left"/"right": the subject's own
sides). :data:`KEYPOINT_MAP` lists, per used keypoint (its index in NAMES), the model point it
is compared with and a weight that says how well the two agree on the skeleton (multiplied by the
detector's visibility in the fit). Model points are SMPL joint names (the demo body and
SMPL-layout models share them) or a surface landmark found on the model's head
(:func:`head_landmarks`), so the face keypoints turn the head. docs/body_photos.md explains each
choice:

- shoulders, elbows, wrists, knees, ankles -> the joints of the same names (weight 1): the
  detector marks the joint centres of these, as the model's joints are;
- hips -> ``left_hip`` / ``right_hip`` at weight HIP_WEIGHT: MediaPipe marks the hip on the
  surface's outline at the pelvis' widest point, SMPL's hip joints are the femoral heads,
  further in (the demo body's hip joints are 0.17 m apart, a person's outline there ~0.3 m);
- the midpoint of the pinky and index knuckles (17/19, 18/20) -> ``left_hand`` / ``right_hand``
  at HAND_WEIGHT: SMPL's hand joint, and the demo body's (the mean of the finger 2-5 knuckles),
  sit between them; thumbs are not used;
- foot_index -> ``left_foot`` / ``right_foot`` (the ball of the foot; the detector's point
  is the toe tip, a few cm further) at FOOT_WEIGHT; heels are not used;
- nose -> the head's most forward vertex (``nose``), ears -> the head's widest vertices
  level with the head joint (``left_ear``, ``right_ear``): these give the head's turn; eyes,
  eye corners, mouth and thumbs are not used (the model has no eyes, fingers or mouth
  that a keypoint could pin).

A model without a joint (or without a ``head`` joint for the face points) leaves that entry out.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["COUNT", "NAMES", "TORSO", "KEYPOINT_MAP", "HIP_WEIGHT", "FOOT_WEIGHT", "KeypointLayout",
           "keypoint_layout", "head_landmarks"]

NAMES = ("nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
         "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
         "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
         "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
         "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
         "right_heel", "left_foot_index", "right_foot_index")
COUNT = len(NAMES)

HIP_WEIGHT = 0.5
FOOT_WEIGHT = 0.5
FACE_WEIGHT = 0.5
HAND_WEIGHT = 0.5

#: (MediaPipe keypoint index, or a pair whose midpoint is the keypoint; model point name; weight)
KEYPOINT_MAP = (
    (11, "left_shoulder", 1.0), (12, "right_shoulder", 1.0),
    (13, "left_elbow", 1.0), (14, "right_elbow", 1.0),
    (15, "left_wrist", 1.0), (16, "right_wrist", 1.0),
    ((17, 19), "left_hand", HAND_WEIGHT), ((18, 20), "right_hand", HAND_WEIGHT),
    (23, "left_hip", HIP_WEIGHT), (24, "right_hip", HIP_WEIGHT),
    (25, "left_knee", 1.0), (26, "right_knee", 1.0),
    (27, "left_ankle", 1.0), (28, "right_ankle", 1.0),
    (31, "left_foot", FOOT_WEIGHT), (32, "right_foot", FOOT_WEIGHT),
    (0, "nose", FACE_WEIGHT), (7, "left_ear", FACE_WEIGHT), (8, "right_ear", FACE_WEIGHT),
)
TORSO_POINTS = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")
#: the shoulders' and hips' keypoints (indices in NAMES)
TORSO = tuple(NAMES.index(name) for name in TORSO_POINTS)


def head_landmarks(model) -> dict[str, int]:
    """Vertex indices of ``nose`` (the head's most forward vertex, +z) and ``left_ear`` /
    ``right_ear`` (the head's vertices furthest out at +x / -x within 3 cm of the head joint's
    height) on the template; {} for a model without a ``head`` joint. "Head" vertices: those whose
    largest skinning weight is the head joint."""
    if "head" not in model.joint_names:
        return {}
    head = model.joint_names.index("head")
    verts = np.nonzero(np.asarray(model.weights).argmax(1) == head)[0]
    template = model.v_template[verts]
    joint = model.rest_joints(np.zeros(model.n_betas))[head]
    level = verts[np.abs(template[:, 1] - joint[1]) < 0.03]
    if len(level) == 0:
        level = verts
    return dict(nose=int(verts[template[:, 2].argmax()]),
                left_ear=int(level[model.v_template[level, 0].argmax()]),
                right_ear=int(level[model.v_template[level, 0].argmin()]))


@dataclass(frozen=True)
class KeypointLayout:
    """The keypoint map resolved on one model.

    detector (K, 2) int: the MediaPipe indices whose midpoint is each keypoint (a single index
    twice); names (K,) model point names; weights (K,) float64;
    joints (K,) int: the model joint of each entry, -1 for a surface landmark; vertices (K,)
    int: the vertex of each surface landmark, -1 for a joint; torso (K,) bool: shoulders and hips.
    """
    detector: np.ndarray
    names: tuple
    weights: np.ndarray
    joints: np.ndarray
    vertices: np.ndarray
    torso: np.ndarray

    def detected(self, keypoints: np.ndarray, visibility: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) keypoints and (K,) visibility of the layout's entries from the detector's (33, 2)
        and (33,): a pair's midpoint, seen as well as the less visible of the two."""
        return keypoints[self.detector].mean(1), visibility[self.detector].min(1)

    def points(self, joints: np.ndarray, vertices: np.ndarray) -> np.ndarray:
        """(K, 3) model points of a posed body: joints (J, 3), vertices (V, 3)."""
        out = np.empty((len(self.names), 3))
        is_joint = self.joints >= 0
        out[is_joint] = joints[self.joints[is_joint]]
        out[~is_joint] = vertices[self.vertices[~is_joint]]
        return out

    def on_rows(self, vertex_ids: np.ndarray) -> KeypointLayout:
        """This layout for a body posed on some of its vertices: each surface landmark
        renumbered as its row in ``vertex_ids`` (S,) sorted int64 (BodyPose.vertex_ids);
        ValueError when one is not among them."""
        surface = self.vertices >= 0
        if not np.isin(self.vertices[surface], vertex_ids).all():
            raise ValueError("vertex_ids must hold the layout's surface landmarks "
                             f"{self.vertices[surface].tolist()}")
        vertices = self.vertices.copy()
        vertices[surface] = np.searchsorted(vertex_ids, self.vertices[surface])
        return replace(self, vertices=vertices)

    def points_vjp(self, grad: np.ndarray, n_joints: int, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
        """(d/d joints (J, 3), d/d vertices (V, 3)) of a gradient (K, 3) wrt :meth:`points`."""
        g_joints, g_vertices = np.zeros((n_joints, 3)), np.zeros((n_vertices, 3))
        is_joint = self.joints >= 0
        np.add.at(g_joints, self.joints[is_joint], grad[is_joint])
        np.add.at(g_vertices, self.vertices[~is_joint], grad[~is_joint])
        return g_joints, g_vertices


def keypoint_layout(model) -> KeypointLayout:
    """KEYPOINT_MAP on ``model``: the entries whose joint (or head landmark) the model has."""
    landmarks = head_landmarks(model)
    rows = [(k, name, w) for k, name, w in KEYPOINT_MAP if name in model.joint_names or name in landmarks]
    names = tuple(name for _, name, _ in rows)
    return KeypointLayout(
        detector=np.array([np.broadcast_to(k, 2) for k, _, _ in rows], np.int64).reshape(-1, 2), names=names,
        weights=np.array([w for _, _, w in rows], np.float64),
        joints=np.array([model.joint_names.index(n) if n in model.joint_names else -1 for n in names], np.int64),
        vertices=np.array([landmarks.get(n, -1) for n in names], np.int64),
        torso=np.array([n in TORSO_POINTS for n in names]))
