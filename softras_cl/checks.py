"""Input checks shared by every public entry point (numpy only).

Each check takes the argument's name first and raises ValueError (TypeError where a caller asks
for it) with a message that starts with that name and says what was expected: a dtype, a shape,
a range, or finite values. Checks return the argument converted (float64 / int64 arrays,
Python floats) so callers never convert twice.
"""
from __future__ import annotations

import math
import numbers

import numpy as np

_REAL_KINDS = "biuf"     # bool, signed and unsigned integers, floats


def shape_text(shape: tuple) -> str:
    """(None, 3) -> "(*, 3)", (4,) -> "(4,)": a shape pattern as text."""
    dims = ["*" if s is None else str(s) for s in shape]
    return f"({dims[0]},)" if len(dims) == 1 else "(" + ", ".join(dims) + ")"


def check_shape(name: str, arr: np.ndarray, shape: tuple, expected: str | None = None) -> np.ndarray:
    """`arr` itself if its shape matches `shape` (None entries match any size), else ValueError
    "{name} must have shape {expected}" (`expected` defaults to shape_text(shape))."""
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {expected or shape_text(shape)}, got {arr.shape}")
    return arr


def check_finite(name: str, arr: np.ndarray, what: str = "NaN or Inf") -> np.ndarray:
    """`arr` itself if every entry is finite, else ValueError "{name} contains {what}" with the
    count of non-finite values and the index of the first.

    One pass over the data when all is well: a NaN or Inf anywhere makes the sum NaN or Inf, so
    a finite sum proves every value finite (half the time of isfinite + any on a 1024^2 image);
    a sum that is not finite (also when finite values overflow) falls back to the full check."""
    with np.errstate(all="ignore"):      # inf - inf, overflow: what the full check is for
        if np.isfinite(arr.sum()):
            return arr
    bad = ~np.isfinite(arr)
    if bad.any():
        where = "" if arr.ndim == 0 else f", first at index {tuple(int(i) for i in np.argwhere(bad)[0])}"
        raise ValueError(f"{name} contains {what} ({int(bad.sum())} non-finite value(s){where})")
    return arr


def real_array(name: str, value, shape: tuple | None = None, expected: str | None = None,
               what: str = "numeric", error: type = ValueError,
               nonfinite: str = "NaN or Inf") -> np.ndarray:
    """`value` as a finite float64 array (bool, int and float inputs; a float64 array comes back
    as itself), optionally shape-checked. Anything else raises `error` "{name} must be {what}";
    non-finite values raise ValueError "{name} contains {nonfinite}"."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{name} must be {what}, got {value!r}") from exc
    if arr.dtype.kind not in _REAL_KINDS:
        raise error(f"{name} must be {what}, got dtype {arr.dtype}")
    if shape is not None:
        check_shape(name, arr, shape, expected)
    return check_finite(name, arr.astype(np.float64, copy=False), nonfinite)


def float_array(name: str, value, error: type = ValueError) -> np.ndarray:
    """`value` as it is if it is a float array (float16/32/64), else `error` naming its dtype.
    Finite values are not checked here (callers check after reshaping)."""
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.floating):
        raise error(f"{name} must be a float array, got dtype {arr.dtype}")
    return arr


def index_array(name: str, value, upper: int, what: str = "vertices",
                shape: tuple | None = None, expected: str | None = None) -> np.ndarray:
    """`value` as an int64 array of indices in [0, upper) (an empty array may have any dtype),
    optionally shape-checked; ValueError naming `name` otherwise."""
    arr = np.asarray(value)
    if arr.size and arr.dtype.kind not in "iu":
        raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if shape is not None:
        check_shape(name, arr, shape, expected)
    if arr.size and (arr.min() < 0 or arr.max() >= upper):
        raise ValueError(f"{name} must index {what} in [0, {upper}), "
                         f"got values in [{arr.min()}, {arr.max()}]")
    return arr


def number(name: str, value, positive: bool = False) -> float:
    """A finite real scalar (> 0 if `positive`) -> float; ValueError naming `name` otherwise."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return float(value)


def nonnegative(name: str, arr: np.ndarray) -> np.ndarray:
    """`arr` itself if every entry is >= 0, else ValueError with its minimum."""
    if arr.size and arr.min() < 0:
        raise ValueError(f"{name} must be >= 0, got a minimum of {arr.min():g}")
    return arr


def positive(name: str, arr: np.ndarray) -> np.ndarray:
    """`arr` itself if every entry is > 0, else ValueError with its minimum."""
    if arr.size and arr.min() <= 0:
        raise ValueError(f"{name} must be > 0, got a minimum of {arr.min():g}")
    return arr
