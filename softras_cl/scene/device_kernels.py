"""Element-wise device kernels of the device-resident render path (pyopencl ElementwiseKernel, all
float64: they need cl_khr_fp64): camera projection and its vjp, face cross products, vertex
normals gathered over each vertex's faces (a CSR incidence list, softras_cl.scene.device_incidence),
Lambert and SH shading and their vjps, and fixed-order sums of per-element products (the camera's
and the light's parameter gradients).

Each kernel evaluates the numpy path's expressions (softras_cl.scene.camera, .shading) operation
for operation, with contraction into fused multiply-adds off: the element-wise arithmetic gives the
numpy path's bits. Where numpy multiplies matrices (BLAS: `verts @ R.T`, `normals @ light`, the SH
irradiance `basis @ M.T`) or sums with einsum, the device adds the same terms left to right, which
may differ from BLAS's order by a rounding (float64 parity to 1e-12 relative, docs/api.md). Sums
onto vertices add each vertex's terms in the numpy path's order (scipy's CSR products and
np.bincount: faces ascending, then corners), starting from 0.0 as they do: those are bit-identical.

Index maths uses divisions and multiply-subtracts, never a division and a remainder of the same
operands (softras_cl.raster.device_arrays says why).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from softras_cl.cl.generated import shared_kernel
from softras_cl.scene.shading import SH_Y0, SH_Y1, SH_Y2, SH_Y2_XXYY, SH_Y2_ZZ

PREAMBLE = "#pragma OPENCL FP_CONTRACT OFF\n"
# doubles per view in the camera parameter buffer (camera_params)
CAMERA_PARAMS = 20
# columns of the per-vertex camera products: g_cam (3), g_cam_i * vertex_j (9), g0 * a, g1 * b
CAMERA_PRODUCTS = 14
# per-element rows summed per chunk by the first pass of sum_products
SUM_CHUNK = 256


def _c(value: float) -> str:
    """A float64 literal that reads back as `value` exactly."""
    return repr(float(value))


def camera_params(cameras: list) -> np.ndarray:
    """(B, CAMERA_PARAMS) float64 of B cameras: R (9, row-major), t (3), fx, fy, cx, cy, the NDC
    scale k = 2 / min(H, W), W / min(H, W), H / min(H, W), 1.0 for perspective (0.0 orthographic)."""
    rows = []
    for cam in cameras:
        h, w = cam.image_size
        rows.append(np.concatenate([cam._rodrigues[0].ravel(), cam.translation,
                                    [cam.fx, cam.fy, cam.cx, cam.cy, cam._ndc_scale(), w / min(h, w),
                                     h / min(h, w), float(cam.projection == "perspective")]]))
    return np.array(rows, np.float64)


_SH_BASIS = f"""
    const double nx = n[3 * i], ny = n[3 * i + 1], nz = n[3 * i + 2];
    double basis[9];
    basis[0] = {_c(SH_Y0)};
    basis[1] = {_c(SH_Y1)} * ny;
    basis[2] = {_c(SH_Y1)} * nz;
    basis[3] = {_c(SH_Y1)} * nx;
    basis[4] = {_c(SH_Y2)} * nx * ny;
    basis[5] = {_c(SH_Y2)} * ny * nz;
    basis[6] = {_c(SH_Y2_ZZ)} * (3.0 * nz * nz - 1.0);
    basis[7] = {_c(SH_Y2)} * nx * nz;
    basis[8] = {_c(SH_Y2_XXYY)} * (nx * nx - ny * ny);
"""

# The albedo row of element i: shared albedo (one (N, 3) array for the whole batch) repeats
_ALBEDO_ROW = "const long arow = shared_albedo ? i - (i / n_items) * n_items : i;"

KERNELS = {
    # screen (B*V, 3) [x_ndc, y_ndc, Z] and camera-frame points cam (B*V, 3) of world vertices
    # (V, 3) shared by the views or (B, V, 3); params (B, CAMERA_PARAMS)
    "project": ("double *screen, double *cam, const double *verts, const double *params, "
                "const long n_vertices, const int shared",
                """
                const long b = i / n_vertices;
                const long v = shared ? i - b * n_vertices : i;
                __global const double *p = params + b * CAMERA_PARAMS;
                const double x = verts[3 * v], y = verts[3 * v + 1], z = verts[3 * v + 2];
                double c[3];
                for (int j = 0; j < 3; ++j)
                    c[j] = x * p[3 * j] + y * p[3 * j + 1] + z * p[3 * j + 2] + p[9 + j];
                const double a = p[19] != 0.0 ? c[0] / c[2] : c[0];
                const double bb = p[19] != 0.0 ? c[1] / c[2] : c[1];
                screen[3 * i] = p[16] * (p[12] * a + p[14] + 0.5) - p[17];
                screen[3 * i + 1] = p[18] - p[16] * (p[13] * bb + p[15] + 0.5);
                screen[3 * i + 2] = c[2];
                for (int j = 0; j < 3; ++j)
                    cam[3 * i + j] = c[j];
                """),
    # Camera.project_vjp per element: g_verts (B*V, 3) = dL/d(world vertex) of this view plus
    # `extra` (the shading's vertex gradient, or nothing), and the CAMERA_PRODUCTS columns of the
    # camera's parameter gradients (products (B*V, 14)) when with_products
    "project_vjp": ("double *g_verts, double *products, const double *g, const double *cam, "
                    "const double *verts, const double *params, const double *extra, "
                    "const long n_vertices, const int shared, const int with_extra, const int with_products",
                    """
                    const long b = i / n_vertices;
                    const long v = shared ? i - b * n_vertices : i;
                    __global const double *p = params + b * CAMERA_PARAMS;
                    const double k = p[16];
                    const double X = cam[3 * i], Y = cam[3 * i + 1], Z = cam[3 * i + 2];
                    const double a = p[19] != 0.0 ? X / Z : X;
                    const double bb = p[19] != 0.0 ? Y / Z : Y;
                    const double ga = (k * p[12]) * g[3 * i];
                    const double gb = (-k * p[13]) * g[3 * i + 1];
                    double gc[3];
                    if (p[19] != 0.0) {
                        const double inv_z = 1.0 / Z;
                        gc[0] = ga * inv_z;
                        gc[1] = gb * inv_z;
                        gc[2] = g[3 * i + 2] - (ga * a + gb * bb) * inv_z;
                    } else {
                        gc[0] = ga; gc[1] = gb; gc[2] = g[3 * i + 2];
                    }
                    for (int j = 0; j < 3; ++j) {
                        const double gv = gc[0] * p[j] + gc[1] * p[3 + j] + gc[2] * p[6 + j];
                        g_verts[3 * i + j] = gv + (with_extra ? extra[3 * i + j] : 0.0);
                    }
                    if (with_products) {
                        __global double *q = products + i * CAMERA_PRODUCTS;
                        const double w[3] = {verts[3 * v], verts[3 * v + 1], verts[3 * v + 2]};
                        for (int j = 0; j < 3; ++j) {
                            q[j] = gc[j];
                            for (int m = 0; m < 3; ++m)
                                q[3 + 3 * j + m] = gc[j] * w[m];
                        }
                        q[12] = g[3 * i] * a;
                        q[13] = g[3 * i + 1] * bb;
                    }
                    """),
    # edges e1 = v1 - v0, e2 = v2 - v0 and cross(e1, e2) of face f of item b (i = b * F + f), from
    # world vertices (V, 3) shared or (B, V, 3) and int32 faces (F, 3)
    "face_cross": ("double *cross, double *e1, double *e2, const double *verts, const int *faces, "
                   "const long n_faces, const long n_vertices, const int shared",
                   """
                   const long b = i / n_faces;
                   const long f = i - b * n_faces;
                   const long base = shared ? 0 : b * n_vertices;
                   __global const double *v0 = verts + 3 * (base + faces[3 * f]);
                   __global const double *v1 = verts + 3 * (base + faces[3 * f + 1]);
                   __global const double *v2 = verts + 3 * (base + faces[3 * f + 2]);
                   double a[3], c[3];
                   for (int j = 0; j < 3; ++j) {
                       a[j] = v1[j] - v0[j];
                       c[j] = v2[j] - v0[j];
                       e1[3 * i + j] = a[j];
                       e2[3 * i + j] = c[j];
                   }
                   cross[3 * i] = a[1] * c[2] - a[2] * c[1];
                   cross[3 * i + 1] = a[2] * c[0] - a[0] * c[2];
                   cross[3 * i + 2] = a[0] * c[1] - a[1] * c[0];
                   """),
    # unit (N, 3) and length (N,) of (N, 3) vectors; zero-length vectors stay zero
    "normalize": ("double *unit, double *length, const double *x",
                  """
                  const double x0 = x[3 * i], x1 = x[3 * i + 1], x2 = x[3 * i + 2];
                  const double len = sqrt(x0 * x0 + x1 * x1 + x2 * x2);
                  length[i] = len;
                  unit[3 * i] = len > 0.0 ? x0 / len : 0.0;
                  unit[3 * i + 1] = len > 0.0 ? x1 / len : 0.0;
                  unit[3 * i + 2] = len > 0.0 ? x2 / len : 0.0;
                  """),
    # out (B*V, 3): vertex v of item b sums src over its incidence entries e (3 f + corner, faces
    # ascending): src[(b * per_item + e / per) * 3 + j] / divisor, per = 3 (per-face values,
    # per_item = F) or 1 (per-corner values, per_item = 3 F)
    "vertex_sums": ("double *out, const double *src, const int *vstart, const int *entries, "
                    "const long n_vertices, const long per_item, const int per, const double divisor",
                    """
                    const long b = i / n_vertices;
                    const long v = i - b * n_vertices;
                    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
                    for (int e = vstart[v]; e < vstart[v + 1]; ++e) {
                        __global const double *x = src + 3 * (b * per_item + entries[e] / per);
                        s0 += x[0] / divisor;
                        s1 += x[1] / divisor;
                        s2 += x[2] / divisor;
                    }
                    out[3 * i] = s0;
                    out[3 * i + 1] = s1;
                    out[3 * i + 2] = s2;
                    """),
    # gradient of normalize at x = unit * length: (grad - unit (unit . grad)) / length, zero where
    # length is zero
    "normalize_vjp": ("double *out, const double *unit, const double *length, const double *g",
                      """
                      const double u0 = unit[3 * i], u1 = unit[3 * i + 1], u2 = unit[3 * i + 2];
                      const double dot = u0 * g[3 * i] + u1 * g[3 * i + 1] + u2 * g[3 * i + 2];
                      const double len = length[i];
                      out[3 * i] = len > 0.0 ? (g[3 * i] - u0 * dot) / len : 0.0;
                      out[3 * i + 1] = len > 0.0 ? (g[3 * i + 1] - u1 * dot) / len : 0.0;
                      out[3 * i + 2] = len > 0.0 ? (g[3 * i + 2] - u2 * dot) / len : 0.0;
                      """),
    # (B*F, 3 corners, 3) corner gradients of the face cross products; gather: the cross
    # gradient is the sum of gv (B*V, 3) over the face's corners (vertex normals' vjp), else
    # gf (B*F, 3) itself (face normals' vjp)
    "cross_vjp": ("double *corners, const double *gv, const double *gf, const double *e1, "
                  "const double *e2, const int *faces, const long n_faces, const long n_vertices, "
                  "const int gather",
                  """
                  const long b = i / n_faces;
                  const long f = i - b * n_faces;
                  double g[3];
                  for (int j = 0; j < 3; ++j) {
                      if (gather) {
                          double s = 0.0;
                          for (int k = 0; k < 3; ++k)
                              s += gv[3 * (b * n_vertices + faces[3 * f + k]) + j];
                          g[j] = s;
                      } else {
                          g[j] = gf[3 * i + j];
                      }
                  }
                  const double a0 = e1[3 * i], a1 = e1[3 * i + 1], a2 = e1[3 * i + 2];
                  const double c0 = e2[3 * i], c1 = e2[3 * i + 1], c2 = e2[3 * i + 2];
                  const double g1[3] = {c1 * g[2] - c2 * g[1], c2 * g[0] - c0 * g[2], c0 * g[1] - c1 * g[0]};
                  const double g2[3] = {g[1] * a2 - g[2] * a1, g[2] * a0 - g[0] * a2, g[0] * a1 - g[1] * a0};
                  __global double *q = corners + 9 * i;
                  for (int j = 0; j < 3; ++j) {
                      q[j] = -(g1[j] + g2[j]);
                      q[3 + j] = g1[j];
                      q[6 + j] = g2[j];
                  }
                  """),
    # face albedo (B*F, 3): the mean of the corners' albedo, (a0 + a1 + a2) / 3
    "face_albedo": ("double *out, const double *albedo, const int *faces, const long n_faces, "
                    "const long n_vertices, const int shared",
                    """
                    const long b = i / n_faces;
                    const long f = i - b * n_faces;
                    const long base = shared ? 0 : b * n_vertices;
                    for (int j = 0; j < 3; ++j)
                        out[3 * i + j] = (albedo[3 * (base + faces[3 * f]) + j]
                                          + albedo[3 * (base + faces[3 * f + 1]) + j]
                                          + albedo[3 * (base + faces[3 * f + 2]) + j]) / 3.0;
                    """),
    # Lambert: colours and irradiance (N, 3), cos (N,) of normals n and albedo (n_items rows,
    # shared by the batch or not); lights: unit direction (3), ambient (3), directional (3), one
    # light for all (per_view 0) or one per view of per_view items
    "lambert": ("double *colors, double *irr, double *cosines, const double *n, const double *albedo, "
                "const double *lights, const long n_items, const int shared_albedo, const long per_view",
                _ALBEDO_ROW + """
                __global const double *light = lights + (per_view ? 9 * (i / per_view) : 0);
                const double cs = n[3 * i] * light[0] + n[3 * i + 1] * light[1] + n[3 * i + 2] * light[2];
                cosines[i] = cs;
                for (int j = 0; j < 3; ++j) {
                    const double e = light[3 + j] + light[6 + j] * (cs > 0.0 ? cs : 0.0);
                    irr[3 * i + j] = e;
                    colors[3 * i + j] = albedo[3 * arow + j] * e;
                }
                """),
    # Lambert's vjp: normals and albedo gradients (N, 3), and the 9 product columns summed for
    # ambient (grad_irr), directional (grad_irr * max(0, cos)) and the light vector (grad_cos * n)
    "lambert_vjp": ("double *g_n, double *g_albedo, double *products, const double *g, const double *n, "
                    "const double *albedo, const double *irr, const double *cosines, const double *lights, "
                    "const long n_items, const int shared_albedo, const long per_view",
                    _ALBEDO_ROW + """
                    __global const double *light = lights + (per_view ? 9 * (i / per_view) : 0);
                    const double cs = cosines[i];
                    double gi[3];
                    for (int j = 0; j < 3; ++j) {
                        gi[j] = g[3 * i + j] * albedo[3 * arow + j];
                        g_albedo[3 * i + j] = g[3 * i + j] * irr[3 * i + j];
                    }
                    const double gcos = cs > 0.0 ? gi[0] * light[6] + gi[1] * light[7] + gi[2] * light[8] : 0.0;
                    __global double *q = products + 9 * i;
                    for (int j = 0; j < 3; ++j) {
                        g_n[3 * i + j] = gcos * light[j];
                        q[j] = gi[j];
                        q[3 + j] = gi[j] * (cs > 0.0 ? cs : 0.0);
                        q[6 + j] = gcos * n[3 * i + j];
                    }
                    """),
    # SH: colours and irradiance (N, 3); lights (27 per light) = coefficients * A_l,
    # channel-major, one light for all (per_view 0) or one per view of per_view items
    "sh": ("double *colors, double *irr, const double *n, const double *albedo, const double *lights, "
           "const long n_items, const int shared_albedo, const long per_view",
           _ALBEDO_ROW + _SH_BASIS + """
           __global const double *m = lights + (per_view ? 27 * (i / per_view) : 0);
           for (int c = 0; c < 3; ++c) {
               double e = basis[0] * m[9 * c];
               for (int k = 1; k < 9; ++k)
                   e += basis[k] * m[9 * c + k];
               irr[3 * i + c] = e;
               colors[3 * i + c] = albedo[3 * arow + c] * e;
           }
           """),
    # SH's vjp: normals and albedo gradients (N, 3), and the 27 product columns grad_irr_c * Y_k
    "sh_vjp": ("double *g_n, double *g_albedo, double *products, const double *g, const double *n, "
               "const double *albedo, const double *irr, const double *lights, const long n_items, "
               "const int shared_albedo, const long per_view",
               _ALBEDO_ROW + _SH_BASIS + f"""
               __global const double *m = lights + (per_view ? 27 * (i / per_view) : 0);
               double gi[3], gb[9];
               for (int c = 0; c < 3; ++c) {{
                   gi[c] = g[3 * i + c] * albedo[3 * arow + c];
                   g_albedo[3 * i + c] = g[3 * i + c] * irr[3 * i + c];
               }}
               for (int k = 0; k < 9; ++k)
                   gb[k] = gi[0] * m[k] + gi[1] * m[9 + k] + gi[2] * m[18 + k];
               g_n[3 * i] = {_c(SH_Y1)} * gb[3] + {_c(SH_Y2)} * (ny * gb[4] + nz * gb[7])
                            + {_c(2 * SH_Y2_XXYY)} * nx * gb[8];
               g_n[3 * i + 1] = {_c(SH_Y1)} * gb[1] + {_c(SH_Y2)} * (nx * gb[4] + nz * gb[5])
                                - {_c(2 * SH_Y2_XXYY)} * ny * gb[8];
               g_n[3 * i + 2] = {_c(SH_Y1)} * gb[2] + {_c(SH_Y2)} * (ny * gb[5] + nx * gb[7])
                                + {_c(6 * SH_Y2_ZZ)} * nz * gb[6];
               __global double *q = products + 27 * i;
               for (int c = 0; c < 3; ++c)
                   for (int k = 0; k < 9; ++k)
                       q[9 * c + k] = gi[c] * basis[k];
               """),
    # first pass of sum_products: partial (G, K, n_chunks) sums of chunks of SUM_CHUNK rows of
    # products (G, N, K), each chunk's rows added in order
    "chunk_sums": ("double *partial, const double *products, const long n_rows, const long width, "
                   "const long n_chunks",
                   """
                   const long gk = i / n_chunks;
                   const long chunk = i - gk * n_chunks;
                   const long grp = gk / width;
                   const long col = gk - grp * width;
                   const long first = chunk * SUM_CHUNK;
                   const long last = min(first + SUM_CHUNK, n_rows);
                   double s = 0.0;
                   for (long r = first; r < last; ++r)
                       s += products[(grp * n_rows + r) * width + col];
                   partial[i] = s;
                   """),
    # second pass: (G*K,) sums of the n_chunks partial sums, in order
    "chunk_totals": ("double *out, const double *partial, const long n_chunks",
                     """
                     double s = 0.0;
                     for (long c = 0; c < n_chunks; ++c)
                         s += partial[i * n_chunks + c];
                     out[i] = s;
                     """),
    # dst (N,) += src (N,)
    "add": ("double *dst, const double *src", "dst[i] = dst[i] + src[i]"),
}


class SceneKernels:
    """The kernels above, and a caller's own (extra: name -> (arguments, body), the same form,
    with OpenCL C helpers they call in preamble), for one OpenCL context, each built on first use."""

    def __init__(self, ctx: cl.Context, queue: cl.CommandQueue, extra: dict | None = None, preamble: str = ""):
        self.ctx, self.queue = ctx, queue
        self.table = KERNELS | (extra or {})
        self.preamble = preamble
        self.record: list | None = None     # a list: every launch's (name, event) is appended (bench)

    def __call__(self, name: str, n: int, *args) -> None:
        """Run kernel `name` over n elements on the queue (nothing for n = 0)."""
        if n == 0:
            return
        from pyopencl.elementwise import ElementwiseKernel

        arguments, body = self.table[name]
        defines = (f"#define CAMERA_PARAMS {CAMERA_PARAMS}\n#define CAMERA_PRODUCTS {CAMERA_PRODUCTS}\n"
                   f"#define SUM_CHUNK {SUM_CHUNK}\n")
        preamble = PREAMBLE + defines + self.preamble
        kernel = shared_kernel(self.ctx, ("scene", name, arguments, body, preamble), lambda: ElementwiseKernel(
            self.ctx, arguments, body, f"scene_{name}", preamble=preamble))
        event = kernel(*args, range=slice(n), queue=self.queue)
        if self.record is not None:
            self.record.append((f"scene_{name}", event))

    def empty(self, shape, dtype=np.float64) -> cla.Array:
        return cla.empty(self.queue, shape, dtype)

    def zeros(self, shape, dtype=np.float64) -> cla.Array:
        """Zeros written by a fill kernel (pyopencl's cla.zeros enqueues a buffer fill, which
        Oclgrind does not count as initialising the memory)."""
        return self.empty(shape, dtype).fill(0)

    def sum_products(self, products: cla.Array) -> cla.Array:
        """(G, N, K) float64 -> (G, K) float64 device sums over N in a fixed order (chunks of
        SUM_CHUNK rows added in order, then the chunk sums in order): the same bits run to run."""
        groups, rows, width = products.shape
        n_chunks = max(1, -(-rows // SUM_CHUNK))
        partial = self.empty(groups * width * n_chunks)
        self("chunk_sums", partial.size, partial, products, np.int64(rows), np.int64(width), np.int64(n_chunks))
        out = self.empty((groups, width))
        self("chunk_totals", out.size, out, partial, np.int64(n_chunks))
        return out

    def count(self, kind: str, *args) -> cla.Array:
        """Device int64 counts: "behind" (perspective camera points with Z <= 0, or non-finite
        coordinates, 2^32 each) of cam (B*V, 3) with params; "differ" (entries of two integer
        arrays that differ)."""
        if kind == "behind":
            cam, params, n_vertices = args
            key = kind
            arguments = "__global const double *cam, __global const double *params, const long n_vertices"
            expr = ("(!isfinite(cam[3 * i]) || !isfinite(cam[3 * i + 1]) || !isfinite(cam[3 * i + 2])) "
                    "? 4294967296L : ((params[(i / n_vertices) * CAMERA_PARAMS + 19] != 0.0 "
                    "&& cam[3 * i + 2] <= 0.0) ? 1L : 0L)")
            size = cam.size // 3
        else:
            a, b = args
            key = (kind, a.dtype, b.dtype)
            from softras_cl.raster.device_arrays import ctype

            arguments = f"__global const {ctype(a.dtype)} *a, __global const {ctype(b.dtype)} *b"
            expr = "((long)a[i] != (long)b[i]) ? 1L : 0L"
            size = a.size
        from pyopencl.reduction import ReductionKernel

        kernel = shared_kernel(self.ctx, ("scene count", key), lambda: ReductionKernel(
            self.ctx, np.int64, neutral="0", reduce_expr="a + b", map_expr=expr, arguments=arguments,
            preamble=f"#define CAMERA_PARAMS {CAMERA_PARAMS}\n"))
        return kernel(*args, range=slice(size), queue=self.queue)
