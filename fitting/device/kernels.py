"""Element-wise float64 kernels of the device objectives (pyopencl ElementwiseKernel, run through
softras_cl.scene.device_kernels.SceneKernels with this table as its extra): a linear model's
evaluation and its transpose, a rigid transform and its vjp, and the robust photometric term.

Every sum runs in a fixed order (a work item adds its terms left to right; sums over many rows
go in chunks of SUM_CHUNK rows, then the chunks in order), so reruns give the same bits. Where
numpy calls BLAS (`coeffs @ basis`, `shape @ R.T`) the order differs from BLAS's by roundings:
float64 parity with the numpy objective is to about 1e-12 relative (tests/fitting/device).
"""
from __future__ import annotations

FIT_KERNELS = {
    # out (N,) = mean (N,) + sum_j w[j] basis[j, :] for basis (K, N) row-major: one row per item,
    # the K products added first to last, then the mean
    "basis_apply": ("double *out, const double *mean, const double *basis, const double *w, "
                    "const long n_rows, const long k",
                    """
                    double s = 0.0;
                    for (long j = 0; j < k; ++j)
                        s += w[j] * basis[j * n_rows + i];
                    out[i] = mean[i] + s;
                    """),
    # first pass of basis^T g: partial (K, n_chunks) sums over chunks of SUM_CHUNK rows of
    # basis[j, r] * g[r]; chunk_totals finishes it
    "basis_chunk_sums": ("double *partial, const double *basis, const double *g, const long n_rows, "
                         "const long n_chunks",
                         """
                         const long j = i / n_chunks;
                         const long chunk = i - j * n_chunks;
                         const long first = chunk * SUM_CHUNK;
                         const long last = min(first + SUM_CHUNK, n_rows);
                         double s = 0.0;
                         for (long r = first; r < last; ++r)
                             s += basis[j * n_rows + r] * g[r];
                         partial[i] = s;
                         """),
    # world (V, 3) = shape (V, 3) R^T + t; rt: R (9, row-major) then t (3)
    "rigid": ("double *world, const double *shape, const double *rt",
              """
              const double x = shape[3 * i], y = shape[3 * i + 1], z = shape[3 * i + 2];
              for (int r = 0; r < 3; ++r)
                  world[3 * i + r] = (x * rt[3 * r] + y * rt[3 * r + 1] + z * rt[3 * r + 2]) + rt[9 + r];
              """),
    # g_shape (V, 3) = g_world R; products (V, 12): g_world (3), then g_world[a] * shape[b] (9),
    # whose sums over the vertices are dL/dt and g_world^T shape (rodrigues_vjp's input)
    "rigid_vjp": ("double *g_shape, double *products, const double *g_world, const double *shape, "
                  "const double *rt",
                  """
                  const double g0 = g_world[3 * i], g1 = g_world[3 * i + 1], g2 = g_world[3 * i + 2];
                  const double g[3] = {g0, g1, g2};
                  for (int c = 0; c < 3; ++c)
                      g_shape[3 * i + c] = (g0 * rt[c] + g1 * rt[3 + c]) + g2 * rt[6 + c];
                  __global double *q = products + 12 * i;
                  for (int a = 0; a < 3; ++a) {
                      q[a] = g[a];
                      for (int b = 0; b < 3; ++b)
                          q[3 + 3 * a + b] = g[a] * shape[3 * i + b];
                  }
                  """),
    # out (K,) = std * (the n_chunks partial sums of basis_chunk_sums, added in order)
    "basis_totals": ("double *out, const double *partial, const double *std, const long n_chunks",
                     """
                     double s = 0.0;
                     for (long c = 0; c < n_chunks; ++c)
                         s += partial[i * n_chunks + c];
                     out[i] = std[i] * s;
                     """),
    # dst (N,) = dst + w * src
    "axpy": ("double *dst, const double *src, const double w", "dst[i] = dst[i] + w * src[i]"),
    # the Geman-McClure term (fitting.losses.GemanMcClure) over N kept pixels of an (H, W, 3)
    # image: rho_w (N,) weighted kernel values; grad (H*W*3,) gets the kept pixels' gradients
    # (the other entries are left as they are: zeros set once per stage). robust 0: plain
    # squared error (rho = r2, gradient 2 r) with the same weights.
    "photo_loss": ("double *rho_w, double *grad, const double *pred, const double *target, "
                   "const long *pixel, const double *weights, const double scale, const double total, "
                   "const double grad_scale, const int robust",
                   """
                   const long p = 3 * pixel[i];
                   const double r0 = pred[p] - target[3 * i], r1 = pred[p + 1] - target[3 * i + 1],
                                r2 = pred[p + 2] - target[3 * i + 2];
                   const double a = weights[i] / total;
                   if (!robust) {
                       rho_w[i] = weights[i] * ((r0 * r0 + r1 * r1) + r2 * r2);
                       grad[p] = (a * (2.0 * r0)) * grad_scale;
                       grad[p + 1] = (a * (2.0 * r1)) * grad_scale;
                       grad[p + 2] = (a * (2.0 * r2)) * grad_scale;
                   } else {
                       const double z0 = r0 / scale, z1 = r1 / scale, z2c = r2 / scale;
                       const double z2 = (z0 * z0 + z1 * z1) + z2c * z2c;
                       const double w = 1.0 / (1.0 + z2);
                       const double rho = z2 <= 1.0 ? ((r0 * r0 + r1 * r1) + r2 * r2) * w
                                                    : (scale * scale) * (1.0 - w);
                       rho_w[i] = weights[i] * rho;
                       const double ww = 2.0 * w * w;
                       grad[p] = (a * (ww * r0)) * grad_scale;
                       grad[p + 1] = (a * (ww * r1)) * grad_scale;
                       grad[p + 2] = (a * (ww * r2)) * grad_scale;
                   }
                   """),
    # front (F,) 1 where face i of verts (V, 3) faces the camera at the origin (its outward,
    # counter-clockwise normal towards it): fitting.recipes.contour.front_facing
    "front_faces": ("char *front, const double *verts, const int *faces",
                    """
                    __global const double *v0 = verts + 3 * faces[3 * i];
                    __global const double *v1 = verts + 3 * faces[3 * i + 1];
                    __global const double *v2 = verts + 3 * faces[3 * i + 2];
                    double e1[3], e2[3], d[3];
                    for (int c = 0; c < 3; ++c) {
                        e1[c] = v1[c] - v0[c];
                        e2[c] = v2[c] - v0[c];
                        d[c] = 0.0 - ((v0[c] + v1[c]) + v2[c]) / 3.0;
                    }
                    const double n0 = e1[1] * e2[2] - e1[2] * e2[1];
                    const double n1 = e1[2] * e2[0] - e1[0] * e2[2];
                    const double n2 = e1[0] * e2[1] - e1[1] * e2[0];
                    front[i] = ((n0 * d[0] + n1 * d[1]) + n2 * d[2]) > 0.0;
                    """),
    # candidate m of a sliding point (cand_point[m], edge cand_edge[m]): when the point's face is
    # turned away and the edge is on the occluding contour, the squared pixel distance from its
    # landmark to the edge's projection (dist) and where along it (frac); else dist = INFINITY.
    # ContourLandmarks.choose and _nearest_on_segments, one candidate per item.
    "contour_distances": ("double *dist, double *frac, const int *cand_edge, const int *cand_point, "
                          "const char *front, const int *point_face, const int *edge_verts, "
                          "const int *edge_faces, const double *verts, const double *params, "
                          "const double *targets, const double side, const double width, const double height",
                          """
                          const int p = cand_point[i], e = cand_edge[i];
                          const int f1 = edge_faces[2 * e + 1];
                          const char a = front[edge_faces[2 * e]];
                          const char b = f1 < 0 ? 0 : front[f1];
                          if (front[point_face[p]] || !((a != b) || (f1 < 0 && a))) {
                              dist[i] = INFINITY;
                              frac[i] = 0.0;
                              PYOPENCL_ELWISE_CONTINUE;
                          }
                          double uv[2][2];
                          for (int end = 0; end < 2; ++end)
                              pixel_of(uv[end], verts + 3 * edge_verts[2 * e + end], params, side, width, height);
                          const double t0 = targets[2 * p], t1 = targets[2 * p + 1];
                          const double ab0 = uv[1][0] - uv[0][0], ab1 = uv[1][1] - uv[0][1];
                          const double num = (t0 - uv[0][0]) * ab0 + (t1 - uv[0][1]) * ab1;
                          const double s = clamp(num / fmax(ab0 * ab0 + ab1 * ab1, 1e-300), 0.0, 1.0);
                          const double d0 = (uv[0][0] + s * ab0) - t0, d1 = (uv[0][1] + s * ab1) - t1;
                          dist[i] = d0 * d0 + d1 * d1;
                          frac[i] = s;
                          """),
    # the first smallest dist in each chunk (chunks: (C, 2) first and end candidate of chunk i)
    "contour_chunk_min": ("double *best, int *which, const double *dist, const int *chunks",
                          """
                          double low = INFINITY;
                          int at = -1;
                          for (int m = chunks[2 * i]; m < chunks[2 * i + 1]; ++m)
                              if (dist[m] < low) {
                                  low = dist[m];
                                  at = m;
                              }
                          best[i] = low;
                          which[i] = at;
                          """),
    # landmark l's 3D point (points (L, 3)): a sliding point (point_of[l] = p >= 0) whose face is
    # turned away and that found a contour edge (over its chunks point_chunks[p]..[p + 1]) sits on
    # it (edge[l], t[l]: the 3D fraction from the image fraction and the ends' depths); any other
    # is its barycentric point of corners (L, 3) with bary (L, 3). ContourLandmarks.points_3d.
    "landmark_points": ("double *points, int *edge, double *t, const int *point_of, const int *point_chunks, "
                        "const double *best, const int *which, const int *cand_edge, const double *frac, "
                        "const int *edge_verts, const int *corners, const double *bary, const double *verts",
                        """
                        const int p = point_of[i];
                        double low = INFINITY;
                        int at = -1;
                        if (p >= 0)
                            for (int c = point_chunks[p]; c < point_chunks[p + 1]; ++c)
                                if (best[c] < low) {
                                    low = best[c];
                                    at = which[c];
                                }
                        if (at >= 0) {
                            const int e = cand_edge[at];
                            __global const double *a = verts + 3 * edge_verts[2 * e];
                            __global const double *b = verts + 3 * edge_verts[2 * e + 1];
                            const double s = frac[at], wa = -a[2], wb = -b[2];
                            const double f = s * wa / (s * wa + (1.0 - s) * wb);
                            for (int c = 0; c < 3; ++c)
                                points[3 * i + c] = (1.0 - f) * a[c] + f * b[c];
                            edge[i] = e;
                            t[i] = f;
                        } else {
                            for (int c = 0; c < 3; ++c)
                                points[3 * i + c] = (bary[3 * i] * verts[3 * corners[3 * i] + c]
                                                     + bary[3 * i + 1] * verts[3 * corners[3 * i + 1] + c])
                                                    + bary[3 * i + 2] * verts[3 * corners[3 * i + 2] + c];
                            edge[i] = -1;
                            t[i] = 0.0;
                        }
                        """),
    # one item (a range of 1): the landmark term over the L points (FaceObjective.landmark_term: weighted squared
    # pixel distances, summed) -> out[0] its value, out[1] dL/d(focal) (fx and fy together), and
    # g_points (L, 3) dL/d(3D points): landmarks_2d, project_pixels_vjp and project_vjp's focal
    "landmark_loss": ("double *out, double *g_points, const double *points, const double *targets, "
                      "const double *weights, const double *params, const long n, const double side, "
                      "const double width, const double height, const double robust",
                      """
                      __global const double *p = params;
                      const double k = p[16];
                      double value = 0.0, gfx = 0.0, gfy = 0.0;
                      for (long l = 0; l < n; ++l) {
                          double uv[2], cam[3];
                          camera_point(cam, points + 3 * l, p);
                          pixel_of(uv, points + 3 * l, p, side, width, height);
                          const double d0 = uv[0] - targets[2 * l], d1 = uv[1] - targets[2 * l + 1];
                          const double r2 = d0 * d0 + d1 * d1;
                          double g;
                          if (robust > 0.0) {     /* losses.landmarks_2d_robust: Geman-McClure at c */
                              const double c2 = robust * robust, u2 = weights[l] * r2, den = u2 + c2;
                              value += c2 * u2 / den;
                              g = (2.0 / n) * (weights[l] * (c2 * c2) / (den * den));
                          } else {
                              value += weights[l] * r2;
                              g = (2.0 / n) * weights[l];
                          }
                          const double gs0 = (g * d0) * n * side / 2.0, gs1 = -((g * d1) * n) * side / 2.0;
                          const double a = cam[0] / cam[2], bb = cam[1] / cam[2];
                          const double ga = (k * p[12]) * gs0, gb = (-k * p[13]) * gs1;
                          const double inv_z = 1.0 / cam[2];
                          const double gc0 = ga * inv_z, gc1 = gb * inv_z, gc2 = 0.0 - (ga * a + gb * bb) * inv_z;
                          for (int j = 0; j < 3; ++j)
                              g_points[3 * l + j] = gc0 * p[j] + gc1 * p[3 + j] + gc2 * p[6 + j];
                          gfx += gs0 * a;
                          gfy += gs1 * bb;
                      }
                      out[0] = value / n * n;
                      out[1] = k * gfx + (-k * gfy);
                      """),
    # one item (a range of 1): g_world (V, 3) += w * the landmarks' point gradients g_points (L, 3), onto the two
    # ends of a sliding point's edge or the three corners of a fixed point, landmark by landmark
    "landmark_scatter": ("double *g_world, const double *g_points, const int *edge, const double *t, "
                         "const int *edge_verts, const int *corners, const double *bary, const long n, "
                         "const double w",
                         """
                         for (long l = 0; l < n; ++l)
                             for (int c = 0; c < 3; ++c) {
                                 const double g = g_points[3 * l + c];
                                 if (edge[l] >= 0) {
                                     const int e = edge[l];
                                     g_world[3 * edge_verts[2 * e] + c] += w * ((1.0 - t[l]) * g);
                                     g_world[3 * edge_verts[2 * e + 1] + c] += w * (t[l] * g);
                                 } else {
                                     for (int j = 0; j < 3; ++j)
                                         g_world[3 * corners[3 * l + j] + c] += w * (bary[3 * l + j] * g);
                                 }
                             }
                         """),
}

# helpers of the landmark kernels: a world point's camera-frame point and its pixel (u right, v
# down, (0, 0) the top-left pixel's centre), Camera.project then Camera.project_pixels, from the
# CAMERA_PARAMS row p of softras_cl.scene.device_kernels.camera_params (a perspective camera)
LANDMARK_PREAMBLE = """
void camera_point(double *c, __global const double *x, __global const double *p) {
    for (int j = 0; j < 3; ++j)
        c[j] = x[0] * p[3 * j] + x[1] * p[3 * j + 1] + x[2] * p[3 * j + 2] + p[9 + j];
}

void pixel_of(double *uv, __global const double *x, __global const double *p, const double side,
              const double width, const double height) {
    double c[3];
    camera_point(c, x, p);
    const double sx = p[16] * (p[12] * (c[0] / c[2]) + p[14] + 0.5) - p[17];
    const double sy = p[18] - p[16] * (p[13] * (c[1] / c[2]) + p[15] + 0.5);
    uv[0] = (sx * side + width) / 2.0 - 0.5;
    uv[1] = (height - sy * side) / 2.0 - 0.5;
}
"""
