"""Named parameter blocks mapped to one flat float64 vector for nlopt (docs/fitting.md).

A :class:`Block` is one named array (a rotation, a translation, shape coefficients, SH lighting,
mesh vertices...) with optional bounds and a scale. A :class:`ParamSet` holds the blocks' current
values and converts between the dict-of-arrays view the objective works with and the flat vector
``x`` the optimiser works with, for any subset of *free* blocks (the others stay frozen):

    x = value / scale          (free blocks only, each flattened in C order)
    d loss / d x = (d loss / d value) * scale
    bounds on x = bounds on value / scale

``scale`` conditions the problem: choose it as the typical size of a block's change (e.g. radians
for a rotation, scene units for a translation) so that all entries of ``x`` move by O(1).

Layout: the free blocks appear in ``x`` in the order the blocks were given to ``ParamSet``,
whatever the order of the ``free`` sequence, so ``pack``/``unpack``/``pack_grad``/``bounds`` agree
for any spelling of the same set of free blocks.

Bad input raises ``ValueError`` naming the block (or the unknown name).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

__all__ = ["Block", "ParamSet"]


@dataclass
class Block:
    """One named parameter array.

    name:  unique name of the block.
    init:  starting value, any shape (stored as float64).
    lower, upper: bounds in value units, a scalar or an array broadcast to ``init``'s shape;
        ``None`` means unbounded (-inf / +inf).
    scale: optimiser variable = value / scale; scalar or array broadcast to ``init``'s shape,
        every entry finite and > 0.
    """
    name: str
    init: np.ndarray
    lower: float | np.ndarray | None = None
    upper: float | np.ndarray | None = None
    scale: float | np.ndarray = 1.0


class _Spec:
    """A validated block: float64 arrays of the block's shape for bounds and scale."""
    __slots__ = ("name", "shape", "size", "lower", "upper", "scale")

    def __init__(self, name, shape, lower, upper, scale):
        self.name, self.shape = name, shape
        self.size = int(np.prod(shape, dtype=np.int64))
        self.lower, self.upper, self.scale = lower, upper, scale


def _broadcast(block_name: str, what: str, value, shape, default: float) -> np.ndarray:
    if value is None:
        return np.full(shape, default, dtype=np.float64)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"block {block_name!r}: {what} is not numeric ({exc})") from None
    try:
        return np.array(np.broadcast_to(arr, shape), dtype=np.float64)
    except ValueError:
        raise ValueError(f"block {block_name!r}: {what} of shape {arr.shape} does not broadcast "
                         f"to the block's shape {shape}") from None


class ParamSet:
    """Named blocks, their current values and the flat-vector view of any subset of them."""

    def __init__(self, blocks: Sequence[Block]):
        if isinstance(blocks, Block):
            blocks = [blocks]
        blocks = list(blocks)
        if not blocks:
            raise ValueError("ParamSet needs at least one block")
        self._specs: dict[str, _Spec] = {}
        self._values: dict[str, np.ndarray] = {}
        for b in blocks:
            if not isinstance(b, Block):
                raise ValueError(f"ParamSet takes Block objects, got {type(b).__name__}")
            name = b.name
            if not isinstance(name, str) or not name:
                raise ValueError(f"block name must be a non-empty string, got {name!r}")
            if name in self._specs:
                raise ValueError(f"duplicate block name {name!r}")
            try:
                init = np.array(b.init, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"block {name!r}: init is not numeric ({exc})") from None
            if not np.all(np.isfinite(init)):
                raise ValueError(f"block {name!r}: init is not finite")
            shape = init.shape
            lower = _broadcast(name, "lower", b.lower, shape, -np.inf)
            upper = _broadcast(name, "upper", b.upper, shape, np.inf)
            scale = _broadcast(name, "scale", b.scale, shape, 1.0)
            if np.any(np.isnan(lower)) or np.any(np.isnan(upper)):
                raise ValueError(f"block {name!r}: bounds contain NaN")
            if np.any(lower == np.inf) or np.any(upper == -np.inf):
                raise ValueError(f"block {name!r}: lower bound +inf or upper bound -inf")
            if np.any(lower > upper):
                i = np.argwhere(lower > upper)[0]
                raise ValueError(f"block {name!r}: lower > upper at index {tuple(int(j) for j in i)} "
                                 f"({lower[tuple(i)]} > {upper[tuple(i)]})")
            if not np.all(np.isfinite(scale)) or np.any(scale <= 0):
                raise ValueError(f"block {name!r}: scale must be finite and > 0")
            spec = _Spec(name, shape, lower, upper, scale)
            self._check_in_bounds(spec, init, "init")
            self._specs[name] = spec
            self._values[name] = init

    # ---- introspection ---------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        """Block names in the order given (the order of the blocks in every flat vector)."""
        return tuple(self._specs)

    def shape(self, name: str) -> tuple[int, ...]:
        return self._spec(name).shape

    def size(self, free: Sequence[str] | str | None = None) -> int:
        """Length of ``x`` for these free blocks (all blocks when ``free`` is None)."""
        return sum(self._specs[n].size for n in self._free(free))

    def slices(self, free: Sequence[str] | str | None = None) -> dict[str, slice]:
        """Where each free block sits in ``x``."""
        out, at = {}, 0
        for n in self._free(free):
            out[n] = slice(at, at + self._specs[n].size)
            at += self._specs[n].size
        return out

    def block_bounds(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) of one block in value units, block-shaped (copies)."""
        s = self._spec(name)
        return s.lower.copy(), s.upper.copy()

    def __repr__(self):
        parts = ", ".join(f"{n}{list(s.shape)}" for n, s in self._specs.items())
        return f"ParamSet({parts})"

    # ---- current values ---------------------------------------------------------------------
    def values(self) -> dict[str, np.ndarray]:
        """Copies of the current values, name -> array."""
        return {n: v.copy() for n, v in self._values.items()}

    def set(self, values: Mapping[str, np.ndarray]) -> None:
        """Replace the current value of each named block (others unchanged); checks shape,
        finiteness and bounds before changing anything."""
        new = {}
        for name, v in dict(values).items():
            spec = self._spec(name)
            arr = self._as_block(spec, v, "value")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"block {name!r}: value is not finite")
            self._check_in_bounds(spec, arr, "value")
            new[name] = arr
        self._values.update(new)

    # ---- flat vector -----------------------------------------------------------------------
    def pack(self, values: Mapping[str, np.ndarray], free: Sequence[str] | str) -> np.ndarray:
        """Flat float64 ``x`` of the free blocks of ``values``, divided by scale."""
        free = self._free(free)
        self._check_names(values, "values")
        parts = []
        for n in free:
            spec = self._specs[n]
            if n not in values:
                raise ValueError(f"block {n!r} is free but missing from values")
            arr = self._as_block(spec, values[n], "value")
            parts.append((arr / spec.scale).ravel())
        return np.concatenate(parts) if parts else np.zeros(0)

    def unpack(self, x: np.ndarray, free: Sequence[str] | str,
               base: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """``base`` (default: the current values) with the free blocks replaced by ``x * scale``.

        The result is clipped to the bounds (``x`` inside the scaled bounds can land one rounding
        error outside them after the multiplication). Frozen blocks are the arrays of ``base``
        (not copied); free blocks are new arrays.
        """
        free = self._free(free)
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 1 or x.size != self.size(free):
            raise ValueError(f"x has shape {x.shape}, expected ({self.size(free)},) for free "
                             f"blocks {list(free)}")
        if base is None:
            out = dict(self._values)
        else:
            self._check_names(base, "base")
            out = dict(base)
        at = 0
        for n in free:
            s = self._specs[n]
            v = x[at:at + s.size].reshape(s.shape) * s.scale
            out[n] = np.clip(v, s.lower, s.upper)
            at += s.size
        return out

    def pack_grad(self, grads: Mapping[str, np.ndarray], free: Sequence[str] | str) -> np.ndarray:
        """Flat gradient wrt ``x``: each free block's gradient wrt its value times its scale.
        A free block missing from ``grads`` contributes zeros; frozen blocks are ignored."""
        free = self._free(free)
        self._check_names(grads, "grads")
        out = np.zeros(self.size(free))
        at = 0
        for n in free:
            s = self._specs[n]
            if n in grads and grads[n] is not None:
                g = self._as_block(s, grads[n], "gradient")
                out[at:at + s.size] = (g * s.scale).ravel()
            at += s.size
        return out

    def bounds(self, free: Sequence[str] | str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) flat arrays in ``x`` units (-inf / inf where unbounded)."""
        free = self._free(free)
        if not free:
            return np.zeros(0), np.zeros(0)
        lo = np.concatenate([(self._specs[n].lower / self._specs[n].scale).ravel() for n in free])
        hi = np.concatenate([(self._specs[n].upper / self._specs[n].scale).ravel() for n in free])
        return lo, hi

    # ---- helpers ---------------------------------------------------------------------------
    def _spec(self, name) -> _Spec:
        try:
            return self._specs[name]
        except (KeyError, TypeError):
            raise ValueError(f"unknown block {name!r} (blocks: {list(self._specs)})") from None

    def _check_names(self, mapping, what):
        unknown = [k for k in mapping if k not in self._specs]
        if unknown:
            raise ValueError(f"unknown block(s) {unknown} in {what} (blocks: {list(self._specs)})")

    def _free(self, free) -> tuple[str, ...]:
        """Validated free names, in ParamSet order."""
        if free is None:
            return self.names
        if isinstance(free, str):
            free = (free,)
        free = list(free)
        for n in free:
            self._spec(n)
        dup = sorted({n for n in free if free.count(n) > 1})
        if dup:
            raise ValueError(f"block(s) {dup} listed more than once in free")
        chosen = set(free)
        return tuple(n for n in self._specs if n in chosen)

    @staticmethod
    def _as_block(spec: _Spec, v, what) -> np.ndarray:
        try:
            arr = np.array(v, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"block {spec.name!r}: {what} is not numeric ({exc})") from None
        if arr.shape != spec.shape:
            raise ValueError(f"block {spec.name!r}: {what} has shape {arr.shape}, expected "
                             f"{spec.shape}")
        return arr

    @staticmethod
    def _check_in_bounds(spec: _Spec, arr, what):
        bad = (arr < spec.lower) | (arr > spec.upper)
        if np.any(bad):
            i = tuple(int(j) for j in np.argwhere(bad)[0])
            raise ValueError(f"block {spec.name!r}: {what} outside its bounds at index {i} "
                             f"({arr[i]} not in [{spec.lower[i]}, {spec.upper[i]}])")
