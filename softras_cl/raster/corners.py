"""Per-vertex values at face corners, and the adjoint (sums back onto vertices)."""
from __future__ import annotations

import numpy as np


def gather_corners(per_vertex: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(B, V, K) values and (B, F, 3) int faces -> (B, F, 3, K) values at each face's corners."""
    return per_vertex[np.arange(per_vertex.shape[0])[:, None, None], faces]


def scatter_corners(values: np.ndarray, faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Adjoint of gather_corners: (B, F, 3, K) corner values summed onto (B, V, K).

    Sums with np.bincount, in a fixed order, so results are bit-identical run to run.
    """
    batch, k = faces.shape[0], values.shape[-1]
    flat = (np.arange(batch)[:, None, None] * n_vertices + faces).ravel()
    cols = [np.bincount(flat, weights=values[..., j].ravel(), minlength=batch * n_vertices)
            for j in range(k)]
    return np.stack(cols, -1).reshape(batch, n_vertices, k)
