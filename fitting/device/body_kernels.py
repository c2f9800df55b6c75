"""Element-wise float64 kernels of the device body objective (pyopencl ElementwiseKernel, run
through softras_cl.scene.device_kernels.SceneKernels with this table in its extra and
BODY_PREAMBLE): linear blend skinning and its vjp over a sparse weight matrix, and the silhouette
and image terms of the body fit with their cotangents.

A sparse matrix is CSR: row r's entries are k = row_start[r] .. row_start[r + 1] - 1, with
column col[k] and value weight[k], columns ascending (scipy's CSR of the model's weights). Each
sum runs in a fixed order (a row's entries first to last; sums over pixels through
SceneKernels.sum_products), so reruns give the same bits.
"""
from __future__ import annotations

# b[c] = sum_k weight[k] transforms[12 col[k] + c] for c < n over row i's entries: the first n of
# the blended 12 (rotation row-major, then offset)
BODY_PREAMBLE = """
void blend_transforms(double *b, const int n, const long i, __global const int *row_start,
                      __global const int *col, __global const double *weight, __global const double *transforms) {
    for (int c = 0; c < n; ++c)
        b[c] = 0.0;
    for (int k = row_start[i]; k < row_start[i + 1]; ++k) {
        __global const double *m = transforms + 12 * col[k];
        for (int c = 0; c < n; ++c)
            b[c] += weight[k] * m[c];
    }
}
"""

BODY_KERNELS = {
    # vertices (S, 3) = sum_k weight[k] (R_j v + o_j) + t, j = col[k] over vertex i's row, v its
    # v_posed (S, 3) row; transforms: (J, 12) rows R_j row-major (9) and o_j (3), then t (3)
    "skin": ("double *vertices, const double *v_posed, const double *transforms, const int *row_start, "
             "const int *col, const double *weight, const long n_joints",
             """
             double b[12];
             blend_transforms(b, 12, i, row_start, col, weight, transforms);
             const double x = v_posed[3 * i], y = v_posed[3 * i + 1], z = v_posed[3 * i + 2];
             __global const double *t = transforms + 12 * n_joints;
             for (int r = 0; r < 3; ++r)
                 vertices[3 * i + r] = (((b[3 * r] * x + b[3 * r + 1] * y) + b[3 * r + 2] * z) + b[9 + r]) + t[r];
             """),
    # skin's vjp per vertex, g (S, 3) its vertices' cotangent: g_posed (S, 3) = (sum_k weight[k]
    # R_j)^T g; products (S, 12): g_a v_b (row-major, 9), then g (3)
    "skin_vjp": ("double *g_posed, double *products, const double *g, const double *v_posed, "
                 "const double *transforms, const int *row_start, const int *col, const double *weight",
                 """
                 double b[9];
                 blend_transforms(b, 9, i, row_start, col, weight, transforms);
                 const double g0 = g[3 * i], g1 = g[3 * i + 1], g2 = g[3 * i + 2];
                 const double gv[3] = {g0, g1, g2};
                 for (int c = 0; c < 3; ++c)
                     g_posed[3 * i + c] = (b[c] * g0 + b[3 + c] * g1) + b[6 + c] * g2;
                 __global double *q = products + 12 * i;
                 for (int a = 0; a < 3; ++a) {
                     for (int c = 0; c < 3; ++c)
                         q[3 * a + c] = gv[a] * v_posed[3 * i + c];
                     q[9 + a] = gv[a];
                 }
                 """),
    # out (R, width) = the sparse (R, N) matrix times x (N, width): one entry per item
    "sparse_times": ("double *out, const double *x, const int *row_start, const int *col, "
                     "const double *weight, const long width",
                     """
                     const long r = i / width, c = i - r * width;
                     double s = 0.0;
                     for (int k = row_start[r]; k < row_start[r + 1]; ++k)
                         s += weight[k] * x[width * col[k] + c];
                     out[i] = s;
                     """),
    # per pixel (N,): terms (N, 3) = care p t, care (p + t - p t), and the squared error of the
    # composite p rgb + (1 - p) background against target_rgb (0 without colours), p the
    # render's alpha, t the target's (fitting.recipes.body.BodyObjective.image_terms)
    "body_image_terms": ("double *terms, const double *alpha, const double *rgb, const double *target_alpha, "
                         "const double *care, const double *target_rgb, const double *background, "
                         "const int has_rgb",
                         """
                         const double p = alpha[i], t = target_alpha[i], w = care[i];
                         terms[3 * i] = (w * p) * t;
                         terms[3 * i + 1] = w * ((p + t) - p * t);
                         double sq = 0.0;
                         if (has_rgb) {
                             for (int c = 0; c < 3; ++c) {
                                 const double r = (rgb[3 * i + c] * p + (1.0 - p) * background[c])
                                                  - target_rgb[3 * i + c];
                                 sq += r * r;
                             }
                         }
                         terms[3 * i + 2] = sq;
                         """),
    # the weighted terms' cotangents, sums (3) body_image_terms' totals (I, U, squares):
    # g_alpha (N,) = w_sil n_pixels d(soft IoU loss)/dp + w_img d(squares)/dp; g_rgb (N, 3) =
    # w_img d(squares)/d rgb (losses.silhouette_iou's guarded formula, eps its eps)
    "body_image_grads": ("double *g_alpha, double *g_rgb, const double *sums, const double *alpha, "
                         "const double *rgb, const double *target_alpha, const double *care, "
                         "const double *target_rgb, const double *background, const double eps, "
                         "const double n_pixels, const double w_sil, const double w_img, const int has_rgb",
                         """
                         const double inter = sums[0], den = sums[1] + eps;
                         const double p = alpha[i], t = target_alpha[i];
                         const double g_iou = care[i] * ((1.0 - 2.0 * t) * den - (sums[1] - inter) * (1.0 - t))
                                              / (den * den);
                         double g = w_sil * (g_iou * n_pixels);
                         if (has_rgb) {
                             double ga = 0.0;
                             for (int c = 0; c < 3; ++c) {
                                 const double r = (rgb[3 * i + c] * p + (1.0 - p) * background[c])
                                                  - target_rgb[3 * i + c];
                                 const double gc = w_img * (2.0 * r);
                                 g_rgb[3 * i + c] = gc * p;
                                 ga += gc * (rgb[3 * i + c] - background[c]);
                             }
                             g += ga;
                         }
                         g_alpha[i] = g;
                         """),
}
