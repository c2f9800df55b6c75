"""Central differences of a fitting objective, for the gradient tests of the recipes."""
from __future__ import annotations

import numpy as np


def central_differences(objective, values: dict, stage, name: str, step: float = 1e-6) -> np.ndarray:
    """d loss / d values[name] by central differences, array of values[name]'s shape (float64).

    objective(values, stage) -> (loss, grads, terms) as fitting.solver.fit calls it; each element
    is stepped by ``step * max(1, |value|)``.
    """
    v = values[name]
    fd = np.zeros_like(v, dtype=np.float64)
    for i in np.ndindex(v.shape):
        h = step * max(1.0, abs(v[i]))
        plus, minus = {**values, name: v.copy()}, {**values, name: v.copy()}
        plus[name][i] += h
        minus[name][i] -= h
        fd[i] = (objective(plus, stage)[0] - objective(minus, stage)[0]) / (2 * h)
    return fd
