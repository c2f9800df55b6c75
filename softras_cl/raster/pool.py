"""Device buffers and host scratch arrays that one SoftRasterizer reuses from call to call.

A fitting loop renders the same mesh at the same size hundreds of times; allocating every
buffer afresh costs page faults on each first touch (on a CPU device the buffers live in RAM),
which measured as much as the kernels themselves. `BufferPool.take` hands out a free buffer of
the request's size class (sizes rounded up by at most 1/8) or allocates one; buffers go back
with `give`, or with `give_when_dead` once the object holding them (a forward's context) is
garbage collected, so a context never shares its buffers with a later call while it lives.
Free buffers are kept up to the peak amount ever in use at once, so the pool's memory stays a
small multiple of what one call needs (pixels + faces).

`ScratchArrays.get(name, shape, dtype)` returns the same numpy array for the same key: host
staging that a call fills and consumes before it returns (uv texel sums),
never an array handed to the caller.

Neither is thread-safe: like the kernels' argument slots, a SoftRasterizer serves one thread.
"""
from __future__ import annotations

import weakref
from collections import OrderedDict

import numpy as np
import pyopencl as cl

MIN_BYTES = 64
MIN_FREE_BYTES = 16 * 1024 ** 2      # free buffers always kept, whatever the peak in use


def size_class(nbytes: int) -> int:
    """nbytes rounded up to a multiple of 2^(bit length - 4): at most 1/8 (12.5 %) more."""
    n = max(int(nbytes), MIN_BYTES)
    step = 1 << max(n.bit_length() - 4, 0)
    return -(-n // step) * step


class BufferPool:
    """Free READ_WRITE cl.Buffers of one context, by size class."""

    def __init__(self, ctx: cl.Context):
        self.ctx = ctx
        self._free: OrderedDict[int, list] = OrderedDict()   # size class -> buffers, LRU first
        self._free_bytes = 0
        self._in_use = 0
        self._peak = 0

    def take(self, nbytes: int) -> cl.Buffer:
        """A buffer of at least nbytes (its contents are whatever the last user left)."""
        size = size_class(nbytes)
        free = self._free.get(size)
        if free:
            buf = free.pop()
            self._free_bytes -= size
            if not free:
                del self._free[size]
        else:
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, size)
        self._in_use += size
        self._peak = max(self._peak, self._in_use)
        return buf

    def give(self, buffers) -> None:
        """Return buffers from take(); the least recently used free ones beyond the limit are released."""
        for buf in buffers:
            self._in_use -= buf.size
            self._free.setdefault(buf.size, []).append(buf)
            self._free.move_to_end(buf.size)
            self._free_bytes += buf.size
        limit = max(self._peak, MIN_FREE_BYTES)
        while self._free_bytes > limit:
            size, free = next(iter(self._free.items()))
            free.pop(0).release()
            self._free_bytes -= size
            if not free:
                del self._free[size]

    def give_when_dead(self, owner, buffers) -> None:
        """give(buffers) once `owner` is garbage collected."""
        weakref.finalize(owner, self.give, list(buffers))

    @property
    def free_bytes(self) -> int:
        return self._free_bytes


class ScratchArrays:
    """Host arrays kept by name, returned as `shape` views of a buffer that grows by size classes
    (sizes that change from call to call, like uv texel sums, reuse one buffer)."""

    def __init__(self):
        self._arrays: dict = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        shape, dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        size = int(np.prod(shape))
        held = self._arrays.get(name)
        if held is None or held.dtype != dtype or held.size < size:
            self._arrays[name] = held = np.empty(size_class(size * dtype.itemsize) // dtype.itemsize, dtype)
        return held[:size].reshape(shape)
