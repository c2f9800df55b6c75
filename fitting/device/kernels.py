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
}
