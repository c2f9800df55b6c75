"""Which faces touch each vertex, on the device: a CSR incidence list built once per face array.

The device-resident render path sums per-face values (cross products, corner gradients) onto the
vertices by a gather over each vertex's faces, one work-item per vertex adding its terms in a
fixed order (no float atomics): the order of the numpy path's sums (scipy's CSR products in
softras_cl.scene.shading.Incidence and np.bincount in softras_cl.raster.corners), faces ascending,
then corners.

The list is built on the host from one download of the faces and kept with a device copy of
them; a later call with a face array of the same shape is matched to it by one device
comparison (a count of differing entries), so a face array changed in place is seen, unless the
caller vouches that its arrays do not change (`unchanged`: the same array object is then matched
by identity, without a comparison or a wait).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from softras_cl.checks import index_array

KEPT = 4        # incidence lists kept per renderer (a fit uses one)


@dataclass(eq=False)        # compared by identity (its fields are device arrays)
class DeviceIncidence:
    """The incidence of (F, 3) faces over V vertices, as device arrays.

    faces: (F, 3) int32 copy of the faces; start: (V + 1,) int32, vertex v's entries are
    entries[start[v]:start[v + 1]]; entries: (3 F,) int32, 3 f + corner of each corner touching
    v, increasing; n_vertices: V.
    """
    faces: cla.Array
    start: cla.Array
    entries: cla.Array
    n_vertices: int
    source: cla.Array | None = None     # the device array it was built from

    @property
    def n_faces(self) -> int:
        return self.faces.shape[0]


def build_incidence(queue, faces: np.ndarray, n_vertices: int) -> DeviceIncidence:
    """DeviceIncidence of host integer faces (F, 3), checked as the numpy path checks them
    (ValueError naming faces for an index outside [0, V))."""
    faces = index_array("faces", faces, n_vertices).astype(np.int32)
    flat = faces.ravel()
    order = np.argsort(flat, kind="stable").astype(np.int32)        # 3 f + corner, per vertex
    counts = np.bincount(flat, minlength=n_vertices)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    up = lambda a: cla.to_device(queue, np.ascontiguousarray(a))
    return DeviceIncidence(up(faces), up(start), up(order), n_vertices)


class IncidenceCache:
    """The last KEPT incidence lists of one queue, matched by content on the device."""

    def __init__(self, queue, kernels):
        self.queue, self.kernels = queue, kernels
        self._kept: list[DeviceIncidence] = []

    def get(self, faces: cla.Array, n_vertices: int, unchanged: bool = False) -> DeviceIncidence:
        """The DeviceIncidence of device faces (F, 3) (any integer dtype) over n_vertices;
        unchanged: the caller's face arrays are never changed in place (the array a list was
        built from is taken as it is)."""
        for inc in self._kept:
            if unchanged and inc.source is faces and inc.n_vertices == n_vertices:
                return inc
            if inc.n_vertices == n_vertices and inc.faces.shape == faces.shape:
                flat = faces if faces.flags.c_contiguous else faces.copy()
                if int(self.kernels.count("differ", flat.reshape(-1), inc.faces.reshape(-1)).get()) == 0:
                    self._kept.remove(inc)
                    self._kept.insert(0, inc)
                    return inc
        inc = build_incidence(self.queue, faces.get(), n_vertices)
        inc.source = faces
        self._kept.insert(0, inc)
        del self._kept[KEPT:]
        return inc
