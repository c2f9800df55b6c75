"""Data layout shared by the host and kernels/soft_raster.cl, defined here only.

`program.build_program` passes every entry of `LAYOUT` as -DNAME=value to every build, and the
kernels refuse to compile without them (they never #define these themselves), so the host code
that fills the buffers and the kernels that read them cannot drift apart.

Tiles: the padded image is cut into tiles of (vector width) x TILE_H pixels; the vector width
is the kernel's SR_VEC, one of LANES[dtype] (4 doubles; 8 or 16 floats, by device:
softras_cl.cl.device.vector_lanes).

GPU layout (RasterSettings.layout): tiles of GPU_TILE_W x TILE_H pixels, one work-item per pixel
in the forward (a work-group per tile, its face records staged in local memory GPU_CHUNK faces at
a time) and GPU_BWD_GROUP work-items per tile in the backward (one per (tile, face) entry).
GPU_TILE_W is the widest CPU vector, so both layouts pad images alike.

Per-face record: geometry buffer row of FACE_STRIDE reals per face (kernel dtype), written by
softras_cl.raster.binning.face_setup and read by load_face / outside_footprint in the kernel:

    offset              size  contents
    FACE_XY        0    6     screen positions, NDC, interleaved x0, y0, x1, y1, x2, y2
    FACE_M         6    6     m[k][0], m[k][1] for k = 0..2: b_k = m[k][0] dx + m[k][1] dy + (k == 0)
    FACE_Z        12    3     view depths z0, z1, z2
    FACE_INV_Z    15    3     1 / z_k
    FACE_INV_LEN2 18    3     1 / |edge|^2 of edges (v0 v1), (v1 v2), (v2 v0)
                  21    3     unused (zero)
    FACE_BOX      24    4     footprint box xmin, xmax, ymin, ymax (NDC)

Per-face colour attributes (texture "vertex"): CORNER_COLORS reals, the rgb of the three corners
(corner-major); with per-pixel lighting followed by as many reals of corner normals, i.e.
LIT_CORNER_ATTRS per face. Texture "uv": UV_ATTRS reals per face, (u, v) of the three corners.
Lighting parameters: LIGHT_PARAMS reals (docs/conventions.md).
"""
from __future__ import annotations

TILE_H = 8
GPU_TILE_W = 16
GPU_CHUNK = 128
GPU_BWD_GROUP = 32
LANES = {"float64": (4,), "float32": (8, 16)}     # pixels per kernel vector, narrowest first
FACE_STRIDE = 28
FACE_XY = 0
FACE_M = 6
FACE_Z = 12
FACE_INV_Z = 15
FACE_INV_LEN2 = 18
FACE_BOX = 24
CORNER_COLORS = 9
LIT_CORNER_ATTRS = 2 * CORNER_COLORS
UV_ATTRS = 6
LIGHT_PARAMS = 27

# name -> value of every constant the kernels receive as -DNAME=value
LAYOUT = dict(TILE_H=TILE_H, GPU_TILE_W=GPU_TILE_W, GPU_CHUNK=GPU_CHUNK, GPU_BWD_GROUP=GPU_BWD_GROUP,
              FACE_STRIDE=FACE_STRIDE, FACE_XY=FACE_XY, FACE_M=FACE_M,
              FACE_Z=FACE_Z, FACE_INV_Z=FACE_INV_Z, FACE_INV_LEN2=FACE_INV_LEN2,
              FACE_BOX=FACE_BOX, CORNER_COLORS=CORNER_COLORS, LIT_CORNER_ATTRS=LIT_CORNER_ATTRS,
              UV_ATTRS=UV_ATTRS, LIGHT_PARAMS=LIGHT_PARAMS)


def vertex_attr_width(lit: bool) -> int:
    """Reals per face of the "vertex" texture's attributes: colours, plus normals when lit."""
    return LIT_CORNER_ATTRS if lit else CORNER_COLORS
