"""A small face-like FaceModel for fast tests of the fitting recipe: a bulged grid with a nose,
smooth random bases and 68 landmark vertices (not in the iBUG layout)."""
from __future__ import annotations

import numpy as np

from softras_cl.fitting.models.face_model import FaceModel


def _smooth_basis(rng, u, v, k: int) -> np.ndarray:
    """(k, V, 3) unit-norm low-frequency displacement fields over the grid (u, v)."""
    fields = []
    for _ in range(k):
        f = rng.normal(size=(3, 3, 3))
        disp = np.stack([sum(f[c, i, j] * np.cos(1.5 * i * u) * np.cos(1.2 * j * v)
                             for i in range(3) for j in range(3)) for c in range(3)], -1)
        fields.append(disp.reshape(-1, 3))
    basis = np.array(fields)
    return basis / np.linalg.norm(basis.reshape(k, -1), axis=1)[:, None, None]


def toy_face_model(n: int = 24, k: int = 4, seed: int = 0) -> FaceModel:
    """n x n vertex grid about 14 x 22 cm, k components per block, metres, facing +z."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(1.2, -1.2, n))
    z = 0.06 * np.sqrt(np.clip(1 - 0.6 * u ** 2 - 0.6 * (v / 1.2) ** 2, 0.05, None))
    z = z + 0.012 * np.exp(-((u / 0.15) ** 2 + ((v + 0.1) / 0.3) ** 2))
    mean = np.stack([0.07 * u, 0.09 * v, z], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, d], 1), np.stack([a, d, b], 1)]).astype(np.int32)
    inner = np.where((np.abs(u.ravel()) < 0.8) & (np.abs(v.ravel()) < 0.9))[0]
    lmk_vertices = rng.choice(inner, 68, replace=False)
    lmk_faces = np.array([np.nonzero((faces == i).any(1))[0][0] for i in lmk_vertices], np.int32)
    bary = (faces[lmk_faces] == lmk_vertices[:, None]).astype(float)
    return FaceModel(mean, _smooth_basis(rng, u, v, k), np.full(k, 0.15),
                     _smooth_basis(rng, u, v, k), np.full(k, 0.1),
                     np.tile([0.45, 0.3, 0.22], (n * n, 1)), _smooth_basis(rng, u, v, k), np.full(k, 3.0),
                     faces, lmk_faces, bary, name="toy face")


def spread_landmarks(size: int) -> np.ndarray:
    """68 points whose face outline (jaw 0-16, brows 17-26) covers the whole image and whose
    eyes (36-47) and inner lips (60-67) outline small boxes."""
    pts = np.full((68, 2), size / 2.0)
    pts[0:17] = np.column_stack([np.linspace(-1, size, 17), np.full(17, size)])
    pts[17:27] = np.column_stack([np.linspace(-1, size, 10), np.full(10, -1.0)])
    box = np.array([[0, 0], [1, 0], [4, 0], [4, 3], [1, 3], [0, 3], [0, 2], [0, 1]])
    pts[36:42] = box[:6] + [8, 10]
    pts[42:48] = box[:6] + [26, 10]
    pts[60:68] = box + [16, 28]
    return pts
