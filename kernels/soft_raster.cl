/* Soft rasteriser: forward and backward (Liu et al., eq. 2-14). Maths: docs/conventions.md.
 *
 * Build-time flags (softras_cl/raster/rasterizer.py sets every one, softras_cl/cl/program.py adds
 * the layout constants below):
 *   SR_OUT_RGB, SR_OUT_ALPHA, SR_OUT_DEPTH      which images to produce (0/1)
 *   SR_METRIC_BARY        0: Euclidean distance to the edges, 1: barycentric distance
 *   SR_COLOR_HARD         0: softmax aggregation of rgb/depth, 1: hard z-buffer
 *   SR_ALPHA_AGG          0: occupancy, 1: sum, 2: hard
 *   SR_TEXTURE            0: vertex colours, 1: per-face R x R textures, 2: uv map (bilinear)
 *   SR_PERSPECTIVE        1: perspective-correct interpolation, 0: linear
 *   SR_LIGHTING           0: colours as given, 1: per-pixel Lambert, 2: per-pixel SH (texture 0)
 *   SR_SAVE_STATE         forward also writes what the backward needs
 *   SR_GRAD_POS, SR_GRAD_COLOR   which gradients the backward computes
 *   SR_ROWS               image rows per forward work-item (divides TILE_H; CPU layout)
 *   SR_INT64_ATOMICS      1: the device has cl_khr_int64_base_atomics (uv texel gradients)
 *
 * Work layout: the image (padded to Wp x Hp) is cut into tiles of SR_VEC x TILE_H pixels; the
 * host bins each face into the tiles its cut-off footprint touches, in increasing face order.
 * Forward: one work-item = SR_VEC adjacent pixels (a realv) of SR_ROWS adjacent rows, looping over
 * its tile's faces.
 * Backward: one work-item = one tile, looping over its faces; each (tile, face) pair writes its
 * summed gradient to its own slot (its index in the tile lists, so the writes go in order), and
 * kernels/grad_sums.cl adds the slots of each face in a fixed order, so results are bit-identical
 * run to run (no float atomics).
 * That is the CPU layout (SR_VEC > 1). The GPU layout (SR_VEC 1, kernels soft_raster_fwd_tile
 * and soft_raster_bwd_tile) runs the same per-pixel code on tiles of GPU_TILE_W x TILE_H pixels:
 * one work-item per pixel in the forward, one per (tile, face) entry in the backward.
 * Per-pixel images are stored as planes (channel-major) of Wp x Hp pixels per batch item.
 */

/* Data layout shared with the host: tile height, the per-face geometry record (FACE_*), colour
 * attribute widths and the number of light parameters. softras_cl/cl/layout.py defines them and
 * softras_cl/cl/program.py passes them to every build; they are never #defined here. */
#ifndef TILE_H
#error "TILE_H must be passed with -D"
#endif
#ifndef FACE_STRIDE
#error "FACE_STRIDE must be passed with -D"
#endif
#ifndef FACE_XY
#error "FACE_XY must be passed with -D"
#endif
#ifndef FACE_M
#error "FACE_M must be passed with -D"
#endif
#ifndef FACE_Z
#error "FACE_Z must be passed with -D"
#endif
#ifndef FACE_INV_Z
#error "FACE_INV_Z must be passed with -D"
#endif
#ifndef FACE_INV_LEN2
#error "FACE_INV_LEN2 must be passed with -D"
#endif
#ifndef FACE_BOX
#error "FACE_BOX must be passed with -D"
#endif
#ifndef CORNER_COLORS
#error "CORNER_COLORS must be passed with -D"
#endif
#ifndef LIT_CORNER_ATTRS
#error "LIT_CORNER_ATTRS must be passed with -D"
#endif
#ifndef UV_ATTRS
#error "UV_ATTRS must be passed with -D"
#endif
#ifndef LIGHT_PARAMS
#error "LIGHT_PARAMS must be passed with -D"
#endif

#define SR_NEED_COLOR (SR_OUT_RGB || SR_OUT_DEPTH)
/* per-face colour data of texture 0: corner colours, and with lighting corner normals after them */
#define VERTEX_ATTR (SR_LIGHTING ? LIT_CORNER_ATTRS : CORNER_COLORS)

#if SR_TEXTURE == 2 && SR_GRAD_COLOR && SR_INT64_ATOMICS
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#endif

typedef maskv idv; /* per-lane face index, same width as the comparison masks */

/* Per-face constants prepared on the host (softras_cl/raster/binning.py, face_setup). */
typedef struct {
    real x[3], y[3];      /* screen positions, NDC */
    real m[3][2];         /* b_k = m[k][0] (px - x0) + m[k][1] (py - y0) + (k == 0) */
    real z[3], iz[3];     /* view depths and their inverses */
    real inv_len2[3];     /* 1 / |edge|^2 for edges (v0 v1), (v1 v2), (v2 v0) */
} Face;

/* Readers of the per-face records in address space `space` (OpenCL C 1.2 has no generic one):
 * outside_footprint<suffix> tests the face's footprint box (NDC, where D can reach dist_eps), which
 * lets a row of pixels skip a face with four compares instead of a full evaluation;
 * load_face<suffix> loads the record. The CPU layout reads __global records, the GPU layout also
 * the __local copies of its tile's records. */
#define FACE_READERS(space, suffix) \
inline bool outside_footprint##suffix(space const real *geom, int face, real x_lo, real x_hi, real y) \
{ \
    space const real *box = geom + face * FACE_STRIDE + FACE_BOX;   /* xmin, xmax, ymin, ymax */ \
    return x_hi < box[0] || x_lo > box[1] || y < box[2] || y > box[3]; \
} \
inline Face load_face##suffix(space const real *geom, int face) \
{ \
    space const real *g = geom + face * FACE_STRIDE; \
    Face f; \
    for (int k = 0; k < 3; ++k) { \
        f.x[k] = g[FACE_XY + 2 * k]; \
        f.y[k] = g[FACE_XY + 2 * k + 1]; \
        f.m[k][0] = g[FACE_M + 2 * k]; \
        f.m[k][1] = g[FACE_M + 2 * k + 1]; \
        f.z[k] = g[FACE_Z + k]; \
        f.iz[k] = g[FACE_INV_Z + k]; \
        f.inv_len2[k] = g[FACE_INV_LEN2 + k]; \
    } \
    return f; \
}
FACE_READERS(__global, )
#if SR_VEC == 1
FACE_READERS(__local, _local)
#endif

/* Scene constants shared by the forward and backward kernels. */
typedef struct {
    real inv_sigma, x_cut, inv_gamma, near, far, inv_range;
} Params;

/* Everything about one face at the SR_VEC pixels of a row. */
typedef struct {
    realv b[3];           /* unclipped barycentrics */
    maskv inside;
    realv x;              /* delta * d^2 / sigma: D = sigmoid(x) */
    realv bc[3];          /* clipped barycentrics */
    realv inv_clip_sum;   /* 1 / sum(clamp(b, 0, 1)) */
    realv Z;              /* interpolated view depth */
    realv a[3];           /* attribute weights */
    maskv valid;          /* the pair counts: D >= dist_eps and near <= Z <= far */
#if SR_METRIC_BARY
    maskv min1, min2;     /* smallest barycentric is b1 / b2 (else b0) */
#else
    realv cx, cy;         /* closest point on the nearest edge, minus the pixel */
    realv t;              /* its position along that edge */
    maskv on1, on2;       /* nearest edge is (v1 v2) / (v2 v0) (else (v0 v1)) */
#endif
} Frag;

#if !SR_METRIC_BARY
/* Squared distance from the pixels to segment a + t e, t in [0, 1]. */
inline realv edge_distance2(real xa, real ya, real ex, real ey, real inv_len2,
                            realv px, real py, realv *t, realv *cx, realv *cy)
{
    realv wx = px - xa;
    real wy = py - ya;
    *t = clamp((wx * ex + wy * ey) * inv_len2, R(0), R(1));
    *cx = *t * ex - wx;
    *cy = *t * ey - wy;
    return *cx * *cx + *cy * *cy;
}

inline realv euclidean_distance2(const Face *f, realv px, real py, Frag *r)
{
    realv t1, cx1, cy1, t2, cx2, cy2;
    realv d2 = edge_distance2(f->x[0], f->y[0], f->x[1] - f->x[0], f->y[1] - f->y[0],
                              f->inv_len2[0], px, py, &r->t, &r->cx, &r->cy);
    realv d2_1 = edge_distance2(f->x[1], f->y[1], f->x[2] - f->x[1], f->y[2] - f->y[1],
                                f->inv_len2[1], px, py, &t1, &cx1, &cy1);
    realv d2_2 = edge_distance2(f->x[2], f->y[2], f->x[0] - f->x[2], f->y[0] - f->y[2],
                                f->inv_len2[2], px, py, &t2, &cx2, &cy2);
    r->on1 = d2_1 < d2;
    d2 = select(d2, d2_1, r->on1);
    r->t = select(r->t, t1, r->on1);
    r->cx = select(r->cx, cx1, r->on1);
    r->cy = select(r->cy, cy1, r->on1);
    r->on2 = d2_2 < d2;
    r->on1 = r->on1 & MASK_NOT(r->on2);
    d2 = select(d2, d2_2, r->on2);
    r->t = select(r->t, t2, r->on2);
    r->cx = select(r->cx, cx2, r->on2);
    r->cy = select(r->cy, cy2, r->on2);
    return d2;
}
#else
inline realv barycentric_distance2(Frag *r)
{
    realv bmin = r->b[0];
    r->min1 = r->b[1] < bmin;
    bmin = select(bmin, r->b[1], r->min1);
    r->min2 = r->b[2] < bmin;
    r->min1 = r->min1 & MASK_NOT(r->min2);
    bmin = select(bmin, r->b[2], r->min2);
    return bmin * bmin;
}
#endif

inline Frag eval_frag(const Face *f, realv px, real py, const Params *p)
{
    Frag r;
    realv dx = px - f->x[0];
    real dy = py - f->y[0];
    r.b[1] = f->m[1][0] * dx + f->m[1][1] * dy;
    r.b[2] = f->m[2][0] * dx + f->m[2][1] * dy;
    r.b[0] = R(1) - r.b[1] - r.b[2];
    r.inside = (r.b[0] >= R(0)) & (r.b[1] >= R(0)) & (r.b[2] >= R(0));
#if SR_METRIC_BARY
    realv d2 = barycentric_distance2(&r);
#else
    realv d2 = euclidean_distance2(f, px, py, &r);
#endif
    r.x = select(-d2, d2, r.inside) * p->inv_sigma;

    realv c0 = clamp(r.b[0], R(0), R(1)), c1 = clamp(r.b[1], R(0), R(1)), c2 = clamp(r.b[2], R(0), R(1));
    r.inv_clip_sum = R(1) / (c0 + c1 + c2);
    r.bc[0] = c0 * r.inv_clip_sum;
    r.bc[1] = c1 * r.inv_clip_sum;
    r.bc[2] = c2 * r.inv_clip_sum;
#if SR_PERSPECTIVE
    realv q0 = r.bc[0] * f->iz[0], q1 = r.bc[1] * f->iz[1], q2 = r.bc[2] * f->iz[2];
    r.Z = R(1) / (q0 + q1 + q2);
    r.a[0] = q0 * r.Z;
    r.a[1] = q1 * r.Z;
    r.a[2] = q2 * r.Z;
#else
    r.Z = r.bc[0] * f->z[0] + r.bc[1] * f->z[1] + r.bc[2] * f->z[2];
    r.a[0] = r.bc[0];
    r.a[1] = r.bc[1];
    r.a[2] = r.bc[2];
#endif
    r.valid = (r.x >= p->x_cut) & (r.Z >= p->near) & (r.Z <= p->far);
    return r;
}

/* ---- colour of a face at SR_VEC pixels ------------------------------------------------------- */
#if SR_TEXTURE == 1
inline int face_texel(real a0, real a1, int res)
{
    return min((int)floor(a0 * res), res - 1) * res + min((int)floor(a1 * res), res - 1);
}
#endif

#if SR_TEXTURE == 2
/* Bilinear taps of the uv map for one pixel: 4 texel offsets (into an Ht x Wt x 3 image) and
 * their weights; d_du / d_dv are the weights' derivatives with respect to u and v. */
typedef struct {
    int offset[4];
    real weight[4], d_du[4], d_dv[4];
} Taps;

inline Taps bilinear_taps(real u, real v, int tex_h, int tex_w)
{
    real fx = u * tex_w - R(0.5), fy = (R(1) - v) * tex_h - R(0.5);
    real fx0 = floor(fx), fy0 = floor(fy);
    real tx = fx - fx0, ty = fy - fy0;
    int x0 = (int)fx0, y0 = (int)fy0;
    int xs[2] = {clamp(x0, 0, tex_w - 1), clamp(x0 + 1, 0, tex_w - 1)};
    int ys[2] = {clamp(y0, 0, tex_h - 1), clamp(y0 + 1, 0, tex_h - 1)};
    real wx[2] = {R(1) - tx, tx}, wy[2] = {R(1) - ty, ty};
    real dwx[2] = {-(real)tex_w, (real)tex_w}, dwy[2] = {(real)tex_h, -(real)tex_h};
    Taps taps;
    for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i) {
            int k = 2 * j + i;
            taps.offset[k] = (ys[j] * tex_w + xs[i]) * 3;
            taps.weight[k] = wy[j] * wx[i];
            taps.d_du[k] = wy[j] * dwx[i];
            taps.d_dv[k] = dwy[j] * wx[i];
        }
    return taps;
}
#endif


#if SR_LIGHTING
/* Per-pixel lighting: albedo and normal interpolated with the attribute weights, the normal
 * renormalised, then shaded. light[27]: Lambert = ambient rgb, directional rgb, unit direction
 * towards the light; SH = 3 x 9 coefficients already scaled by the host (A_l times the basis
 * constants), so here the basis is the plain polynomial P below. */
typedef struct {
    realv albedo[3], n[3], inv_len, shade[3];
#if SR_LIGHTING == 1
    realv n_dot_l;
#else
    realv P[9];
#endif
} Lit;

inline Lit eval_lit(__global const real *col, __global const real *light, const Frag *r)
{
    Lit L;
    realv m[3];
    for (int c = 0; c < 3; ++c) {
        L.albedo[c] = r->a[0] * col[c] + r->a[1] * col[3 + c] + r->a[2] * col[6 + c];
        m[c] = r->a[0] * col[CORNER_COLORS + c] + r->a[1] * col[CORNER_COLORS + 3 + c]
               + r->a[2] * col[CORNER_COLORS + 6 + c];
    }
    realv len = sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
    L.inv_len = keep(R(1) / fmax(len, R(1e-30)), len > R(1e-30));   /* a vanished normal stays 0 */
    for (int d = 0; d < 3; ++d)
        L.n[d] = m[d] * L.inv_len;
#if SR_LIGHTING == 1
    L.n_dot_l = L.n[0] * light[6] + L.n[1] * light[7] + L.n[2] * light[8];
    for (int c = 0; c < 3; ++c)
        L.shade[c] = light[c] + light[3 + c] * fmax(L.n_dot_l, R(0));
#else
    const realv x = L.n[0], y = L.n[1], z = L.n[2];
    L.P[0] = (realv)R(1); L.P[1] = y; L.P[2] = z; L.P[3] = x; L.P[4] = x * y; L.P[5] = y * z;
    L.P[6] = R(3) * z * z - R(1); L.P[7] = x * z; L.P[8] = x * x - y * y;
    for (int c = 0; c < 3; ++c) {
        L.shade[c] = (realv)R(0);
        for (int i = 0; i < 9; ++i)
            L.shade[c] += light[9 * c + i] * L.P[i];
    }
#endif
    return L;
}
#endif

/* Colour C (3 vectors) of face `face` at the pixels; dC_du/dC_dv only for the uv map (may be 0). */
inline void face_color(__global const real *attr, __global const real *tex_image,
                       __global const real *light, int face, int tex_res, int tex_h, int tex_w,
                       const Frag *r, realv C[3], realv *dC_du, realv *dC_dv)
{
#if SR_TEXTURE == 0 && SR_LIGHTING
    const Lit L = eval_lit(attr + face * VERTEX_ATTR, light, r);
    for (int c = 0; c < 3; ++c)
        C[c] = L.albedo[c] * L.shade[c];
#elif SR_TEXTURE == 0
    __global const real *col = attr + face * VERTEX_ATTR;
    for (int c = 0; c < 3; ++c)
        C[c] = r->a[0] * col[c] + r->a[1] * col[3 + c] + r->a[2] * col[6 + c];
#else
    real a0[SR_VEC], a1[SR_VEC], a2[SR_VEC], out[3][SR_VEC];
    VSTORE(r->a[0], 0, a0);
    VSTORE(r->a[1], 0, a1);
    VSTORE(r->a[2], 0, a2);
#if SR_TEXTURE == 1
    __global const real *tex = attr + (size_t)face * tex_res * tex_res * 3;
    if (tex_res == 1) {           /* flat colour per face (e.g. per-face shading): no lookups */
        for (int c = 0; c < 3; ++c)
            C[c] = (realv)tex[c];
        return;
    }
    for (int l = 0; l < SR_VEC; ++l) {
        int texel = face_texel(a0[l], a1[l], tex_res) * 3;
        for (int c = 0; c < 3; ++c)
            out[c][l] = tex[texel + c];
    }
#else
    __global const real *uv = attr + face * UV_ATTRS;
    real du[3][SR_VEC], dv[3][SR_VEC];
    for (int l = 0; l < SR_VEC; ++l) {
        real u = a0[l] * uv[0] + a1[l] * uv[2] + a2[l] * uv[4];
        real v = a0[l] * uv[1] + a1[l] * uv[3] + a2[l] * uv[5];
        Taps taps = bilinear_taps(u, v, tex_h, tex_w);
        for (int c = 0; c < 3; ++c) {
            out[c][l] = du[c][l] = dv[c][l] = R(0);
            for (int k = 0; k < 4; ++k) {
                real texel = tex_image[taps.offset[k] + c];
                out[c][l] += taps.weight[k] * texel;
                du[c][l] += taps.d_du[k] * texel;
                dv[c][l] += taps.d_dv[k] * texel;
            }
        }
    }
    if (dC_du)
        for (int c = 0; c < 3; ++c) {
            dC_du[c] = VLOAD(0, du[c]);
            dC_dv[c] = VLOAD(0, dv[c]);
        }
#endif
    for (int c = 0; c < 3; ++c)
        C[c] = VLOAD(0, out[c]);
#endif
}

inline Params make_params(real inv_sigma, real x_cut, real inv_gamma, real near, real far)
{
    Params p = {inv_sigma, x_cut, inv_gamma, near, far, R(1) / (far - near)};
    return p;
}

#define GEOMETRY_ARGS \
    const int W, const int H, const int Wp, const int Hp, const int ntx, const int nty, \
    const real pix_scale, const real inv_sigma, const real x_cut, const real inv_gamma, \
    const real eps, const int tex_res, const int tex_h, const int tex_w, \
    __global const real *geom, __global const real *attr, __global const real *tex_image, \
    __global const real *light, __global const int *tile_start, __global const int *tile_faces, \
    __global const real *depth_range   /* (B, 2): each view's near and far */

/* ---- forward ------------------------------------------------------------------------------ */
#ifndef SR_ROWS
#error "SR_ROWS (image rows per forward work-item, dividing TILE_H) must be passed with -D"
#endif
#if TILE_H % SR_ROWS
#error "SR_ROWS must divide TILE_H"
#endif

/* The forward's running sums at SR_VEC pixels of one row. */
typedef struct {
#if SR_NEED_COLOR && !SR_COLOR_HARD
    realv m, S, accZ, acc[3];      /* online softmax: running maximum, normaliser, sums */
#elif SR_NEED_COLOR
    realv bestZ, best[3];
    idv best_id;
#endif
#if SR_OUT_ALPHA && SR_ALPHA_AGG == 0
    realv l_rest, l_min;           /* sum of log(1 - D) without its most negative term, that term */
    idv min_id;
#elif SR_OUT_ALPHA && SR_ALPHA_AGG == 1
    realv sumD;
#elif SR_OUT_ALPHA
    maskv covered;
#endif
} FwdSums;

inline void fwd_init(FwdSums *a, real eps, real inv_gamma, real far, const realv bg[3])
{
#if SR_NEED_COLOR && !SR_COLOR_HARD
    a->m = (realv)(eps * inv_gamma);
    a->S = (realv)R(1);
    a->accZ = (realv)far;
    for (int c = 0; c < 3; ++c)
        a->acc[c] = bg[c];
#elif SR_NEED_COLOR
    a->bestZ = (realv)far;
    for (int c = 0; c < 3; ++c)
        a->best[c] = bg[c];
    a->best_id = (idv)(-1);
#endif
#if SR_OUT_ALPHA && SR_ALPHA_AGG == 0
    a->l_rest = a->l_min = (realv)R(0);
    a->min_id = (idv)(-1);
#elif SR_OUT_ALPHA && SR_ALPHA_AGG == 1
    a->sumD = (realv)R(0);
#elif SR_OUT_ALPHA
    a->covered = (maskv)0;
#endif
}

/* Add face `face` (fragment r) to the sums of its pixels. Always inlined: as a call (PoCL did not
 * inline it), the fragment went through memory (docs/notes/raster_passes.md, "Sixth pass: kernels"). */
__attribute__((always_inline))
inline void fwd_add(FwdSums *a, const Frag *r, int face, const Params *p, real far, real inv_gamma,
                    __global const real *attr, __global const real *image, __global const real *light,
                    int tex_res, int tex_h, int tex_w)
{
#if (SR_NEED_COLOR && !SR_COLOR_HARD) || (SR_OUT_ALPHA && SR_ALPHA_AGG != 2)
    realv log_D, log_1mD;     /* log D and log(1 - D), sharing one exp and one log1p */
    log_sigmoid_pair(r->x, &log_D, &log_1mD);
#endif
#if SR_NEED_COLOR
    realv C[3] = {(realv)R(0), (realv)R(0), (realv)R(0)};
#if SR_OUT_RGB
    face_color(attr, image, light, face, tex_res, tex_h, tex_w, r, C, 0, 0);
#endif
#if !SR_COLOR_HARD
    /* online softmax: one exp per pair, the running maximum m keeps every exp <= 1 */
    realv t = log_D + (far - r->Z) * p->inv_range * inv_gamma;
    realv diff = t - a->m, e = exp(-fabs(diff));
    maskv up = (diff > R(0)) & r->valid;
    realv old_scale = select((realv)R(1), e, up);
    realv new_weight = keep(select(e, (realv)R(1), up), r->valid);
    a->S = a->S * old_scale + new_weight;
    for (int c = 0; c < 3; ++c)
        a->acc[c] = a->acc[c] * old_scale + new_weight * C[c];
    a->accZ = a->accZ * old_scale + new_weight * r->Z;
    a->m = select(a->m, t, up);
#else
    maskv nearer = r->inside & r->valid & ((r->Z < a->bestZ) | (a->best_id < 0));
    a->bestZ = select(a->bestZ, r->Z, nearer);
    for (int c = 0; c < 3; ++c)
        a->best[c] = select(a->best[c], C[c], nearer);
    a->best_id = select(a->best_id, (idv)face, nearer);
#endif
#endif
#if SR_OUT_ALPHA && SR_ALPHA_AGG == 0
    /* log(1 - D) summed; the most negative term is kept apart for a stable backward */
    realv l1m = log_1mD;
    maskv lower = (l1m < a->l_min) & r->valid;
    a->l_rest += keep(select(l1m, a->l_min, lower), r->valid);
    a->l_min = select(a->l_min, l1m, lower);
    a->min_id = select(a->min_id, (idv)face, lower);
#elif SR_OUT_ALPHA && SR_ALPHA_AGG == 1
    a->sumD += keep(exp(log_D), r->valid);
#elif SR_OUT_ALPHA
    a->covered |= r->inside & r->valid;
#endif
}

/* The images (and with SR_SAVE_STATE the backward's state) at the SR_VEC pixels from pix. */
inline void fwd_store(const FwdSums *a, size_t pix, size_t npix,
                      __global real *out_rgb, __global real *out_alpha, __global real *out_depth,
                      __global real *color_state, __global real *alpha_state, __global int *id_state)
{
#if SR_NEED_COLOR && !SR_COLOR_HARD
    const realv inv_S = R(1) / a->S;
#if SR_OUT_RGB
    for (int c = 0; c < 3; ++c)
        VSTORE(a->acc[c] * inv_S, 0, out_rgb + c * npix + pix);
#endif
#if SR_OUT_DEPTH
    VSTORE(a->accZ * inv_S, 0, out_depth + pix);
#endif
#if SR_SAVE_STATE
    VSTORE(a->m + log(a->S), 0, color_state + pix);
#endif
#elif SR_NEED_COLOR
#if SR_OUT_RGB
    for (int c = 0; c < 3; ++c)
        VSTORE(a->best[c], 0, out_rgb + c * npix + pix);
#endif
#if SR_OUT_DEPTH
    VSTORE(a->bestZ, 0, out_depth + pix);
#endif
#if SR_SAVE_STATE
    VSTORE(TO_INT(a->best_id), 0, id_state + pix);
#endif
#endif

#if SR_OUT_ALPHA && SR_ALPHA_AGG == 0
    VSTORE(-expm1(a->l_rest + a->l_min), 0, out_alpha + pix);
#if SR_SAVE_STATE
    VSTORE(a->l_rest, 0, alpha_state + pix);
    VSTORE(a->l_min, 0, alpha_state + npix + pix);
    VSTORE(TO_INT(a->min_id), 0, id_state + npix + pix);
#endif
#elif SR_OUT_ALPHA && SR_ALPHA_AGG == 1
    VSTORE(fmin(a->sumD, R(1)), 0, out_alpha + pix);
#if SR_SAVE_STATE
    VSTORE(a->sumD, 0, alpha_state + pix);
#endif
#elif SR_OUT_ALPHA
    VSTORE(select((realv)R(0), (realv)R(1), a->covered), 0, out_alpha + pix);
#endif
}

/* One work-item = SR_VEC pixels of SR_ROWS adjacent rows of one tile. Each face of the tile's
 * list is loaded once and added to every row its footprint box reaches, so each pixel sees the
 * same faces in the same order with the same arithmetic whatever SR_ROWS is. */
__kernel void soft_raster_fwd(GEOMETRY_ARGS,
                              const real bg_r, const real bg_g, const real bg_b,
                              __global real *out_rgb, __global real *out_alpha, __global real *out_depth,
                              __global real *color_state, __global real *alpha_state,
                              __global int *id_state)
{
    const int cb = get_global_id(0), row0 = get_global_id(1) * SR_ROWS, batch = get_global_id(2);
    if (row0 >= H || cb >= ntx)    /* padding rows / work-items of the last group */
        return;
    const Params p = make_params(inv_sigma, x_cut, inv_gamma, depth_range[2 * batch], depth_range[2 * batch + 1]);
    const int tile = (batch * nty + row0 / TILE_H) * ntx + cb;
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    const realv px = ((real)(cb * SR_VEC) - R(0.5) * W + LANE_OFFSETS) * pix_scale;
    const real x_lo = FIRST_LANE(px), x_hi = LAST_LANE(px);
    const realv bg[3] = {(realv)bg_r, (realv)bg_g, (realv)bg_b};
    __global const real *image = tex_image + (size_t)batch * tex_h * tex_w * 3;
    real py[SR_ROWS];
    FwdSums sums[SR_ROWS];
    for (int i = 0; i < SR_ROWS; ++i) {
        py[i] = (R(0.5) * H - (row0 + i) - R(0.5)) * pix_scale;
        fwd_init(&sums[i], eps, inv_gamma, p.far, bg);
    }
    const int rows = min(SR_ROWS, H - row0);

    for (int k = tile_start[tile]; k < tile_start[tile + 1]; ++k) {
        const int face = tile_faces[k];
        __global const real *box = geom + face * FACE_STRIDE + FACE_BOX;   /* xmin, xmax, ymin, ymax */
        if (x_hi < box[0] || x_lo > box[1])
            continue;
        const real y_min = box[2], y_max = box[3];
        uint hit = 0;    /* bit i: row i is inside the box's rows */
        for (int i = 0; i < SR_ROWS; ++i)
            hit |= (uint)(i < rows && !(py[i] < y_min || py[i] > y_max)) << i;
        if (!hit)
            continue;
        const Face f = load_face(geom, face);
        for (int i = 0; i < SR_ROWS; ++i) {
            if (!(hit >> i & 1u))
                continue;
            const Frag r = eval_frag(&f, px, py[i], &p);
            if (ANY(r.valid))
                fwd_add(&sums[i], &r, face, &p, p.far, inv_gamma, attr, image, light, tex_res, tex_h, tex_w);
        }
    }
    for (int i = 0; i < rows; ++i)
        fwd_store(&sums[i], ((size_t)batch * Hp + row0 + i) * Wp + cb * SR_VEC, npix,
                  out_rgb, out_alpha, out_depth, color_state, alpha_state, id_state);
}

#if SR_VEC == 1
/* GPU layout: one work-item = one pixel, one work-group = one tile of GPU_TILE_W x TILE_H pixels.
 * The tile's face records go through local memory GPU_CHUNK faces at a time (loaded by the whole
 * group, then read by every work-item), so each record is read from global memory once per tile.
 * Each pixel sees the tile's faces in list order with the CPU layout's per-pixel arithmetic. */
#define GPU_GROUP_ITEMS (GPU_TILE_W * TILE_H)

/* Records (and face indices) of the tile-list entries faces[0 .. n-1] into local memory, each
 * work-item (lid: its index in the group) copying every GPU_GROUP_ITEMS-th value. */
inline void stage_records(__global const real *geom, __global const int *faces, const int n,
                          const int lid, __local real *records, __local int *ids)
{
    for (int i = lid; i < n * FACE_STRIDE; i += GPU_GROUP_ITEMS) {
        /* i - j * FACE_STRIDE, not i % FACE_STRIDE: LLVM turns that division pair into a `freeze`
         * instruction, which Oclgrind's uninitialised-memory checker cannot run */
        const int j = i / FACE_STRIDE;
        records[i] = geom[faces[j] * FACE_STRIDE + i - j * FACE_STRIDE];
    }
    for (int i = lid; i < n; i += GPU_GROUP_ITEMS)
        ids[i] = faces[i];
}

__kernel __attribute__((reqd_work_group_size(GPU_TILE_W, TILE_H, 1)))
void soft_raster_fwd_tile(GEOMETRY_ARGS,
                          const real bg_r, const real bg_g, const real bg_b,
                          __global real *out_rgb, __global real *out_alpha, __global real *out_depth,
                          __global real *color_state, __global real *alpha_state,
                          __global int *id_state)
{
    __local real records[GPU_CHUNK * FACE_STRIDE];
    __local int ids[GPU_CHUNK];
    const int col = get_global_id(0), row = get_global_id(1), batch = get_global_id(2);
    const int lid = get_local_id(1) * GPU_TILE_W + get_local_id(0);
    const int tile = (batch * nty + get_group_id(1)) * ntx + get_group_id(0);
    const bool in_image = row < H;   /* padding rows only help load the records */
    const Params p = make_params(inv_sigma, x_cut, inv_gamma, depth_range[2 * batch], depth_range[2 * batch + 1]);
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    const real px = ((real)col - R(0.5) * W + LANE_OFFSETS) * pix_scale;
    const real py = (R(0.5) * H - row - R(0.5)) * pix_scale;
    const realv bg[3] = {bg_r, bg_g, bg_b};
    __global const real *image = tex_image + (size_t)batch * tex_h * tex_w * 3;
    FwdSums sums;
    fwd_init(&sums, eps, inv_gamma, p.far, bg);

    const int first = tile_start[tile], end = tile_start[tile + 1];
    for (int base = first; base < end; base += GPU_CHUNK) {
        const int n = min(GPU_CHUNK, end - base);
        barrier(CLK_LOCAL_MEM_FENCE);          /* every work-item is done with the last chunk */
        stage_records(geom, tile_faces + base, n, lid, records, ids);
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int j = 0; j < n && in_image; ++j) {
            if (outside_footprint_local(records, j, px, px, py))
                continue;
            const Face f = load_face_local(records, j);
            const Frag r = eval_frag(&f, px, py, &p);
            if (ANY(r.valid))
                fwd_add(&sums, &r, ids[j], &p, p.far, inv_gamma, attr, image, light, tex_res, tex_h, tex_w);
        }
    }
    if (in_image)
        fwd_store(&sums, ((size_t)batch * Hp + row) * Wp + col, npix,
                  out_rgb, out_alpha, out_depth, color_state, alpha_state, id_state);
}
#endif

/* ---- backward ----------------------------------------------------------------------------- */
/* Gradient sums of one (tile, face) pair, kept per lane until the end of the tile. */
typedef struct {
    realv gx[3], gy[3], gz[3];   /* dL/d(x, y, z) of the face's three vertices */
    realv gcol[CORNER_COLORS];   /* dL/d(vertex colour or albedo) (texture == vertex) */
#if SR_LIGHTING
    realv gnrm[CORNER_COLORS];   /* dL/d(vertex normal) at the three corners */
    realv glight[LIGHT_PARAMS];  /* dL/d(light parameters), layout of `light` */
#endif
} Accum;

/* Cotangents and saved state at SR_VEC pixels. */
typedef struct {
    realv g[3], g_alpha, g_depth, g_dot_img;
    realv lse, l_rest, l_min, sumD;
    idv best_id, min_id;
} PixelIn;

inline PixelIn load_pixel(__global const real *grad_rgb, __global const real *grad_alpha,
                          __global const real *grad_depth, __global const real *g_dot_img,
                          __global const real *color_state, __global const real *alpha_state,
                          __global const int *id_state, size_t pix, size_t npix)
{
    PixelIn in;
    /* fields the variant does not use are zero, not undefined: the GPU layout copies the whole
     * struct into local memory */
    in.g_alpha = in.g_dot_img = in.lse = in.l_rest = in.l_min = in.sumD = (realv)R(0);
    in.best_id = in.min_id = (idv)0;
    for (int c = 0; c < 3; ++c)
        in.g[c] = SR_OUT_RGB ? VLOAD(0, grad_rgb + c * npix + pix) : (realv)R(0);
    in.g_depth = SR_OUT_DEPTH ? VLOAD(0, grad_depth + pix) : (realv)R(0);
#if SR_NEED_COLOR && !SR_COLOR_HARD
    in.g_dot_img = VLOAD(0, g_dot_img + pix);
    in.lse = VLOAD(0, color_state + pix);
#elif SR_NEED_COLOR
    in.best_id = TO_MASK(VLOAD(0, id_state + pix));
#endif
#if SR_OUT_ALPHA
    in.g_alpha = VLOAD(0, grad_alpha + pix);
#if SR_ALPHA_AGG == 0
    in.l_rest = VLOAD(0, alpha_state + pix);
    in.l_min = VLOAD(0, alpha_state + npix + pix);
    in.min_id = TO_MASK(VLOAD(0, id_state + npix + pix));
#elif SR_ALPHA_AGG == 1
    in.sumD = VLOAD(0, alpha_state + pix);
#endif
#endif
    return in;
}

/* Whether any cotangent (or the softmax's g.out image) at the SR_VEC pixels is non-zero. Where all
 * are zero, every term a pair adds is a product with zero, i.e. +-0, and adding +-0 leaves the
 * sums' bits unchanged (they start at +0 and x + -0 = x): the backward skips such rows. */
inline bool has_cotangent(__global const real *grad_rgb, __global const real *grad_alpha,
                          __global const real *grad_depth, __global const real *g_dot_img,
                          size_t pix, size_t npix)
{
    maskv nonzero = (maskv)0;
#if SR_OUT_RGB
    for (int c = 0; c < 3; ++c)
        nonzero |= VLOAD(0, grad_rgb + c * npix + pix) != R(0);
#endif
#if SR_OUT_DEPTH
    nonzero |= VLOAD(0, grad_depth + pix) != R(0);
#endif
#if SR_OUT_ALPHA
    nonzero |= VLOAD(0, grad_alpha + pix) != R(0);
#endif
#if SR_NEED_COLOR && !SR_COLOR_HARD
    nonzero |= VLOAD(0, g_dot_img + pix) != R(0);
#endif
    return ANY(nonzero);
}

/* Spread dL/d(b) (unclipped barycentrics) to the vertex positions: db = -U^-1 dU b. */
inline void barycentric_vjp(const Face *f, const Frag *r, const realv gb[3], maskv valid, Accum *acc)
{
    realv Gx = gb[0] * f->m[0][0] + gb[1] * f->m[1][0] + gb[2] * f->m[2][0];
    realv Gy = gb[0] * f->m[0][1] + gb[1] * f->m[1][1] + gb[2] * f->m[2][1];
    for (int k = 0; k < 3; ++k) {
        acc->gx[k] -= keep(r->b[k] * Gx, valid);
        acc->gy[k] -= keep(r->b[k] * Gy, valid);
    }
}

#if !SR_METRIC_BARY
/* dL/d(d^2) through the nearest edge's closest point c = a + t (b - a) to its two vertices. */
inline void edge_vjp(const Frag *r, realv g_d2, maskv valid, Accum *acc)
{
    realv ga = keep(R(2) * g_d2 * (R(1) - r->t), valid), gb = keep(R(2) * g_d2 * r->t, valid);
    maskv on0 = MASK_NOT(r->on1 | r->on2);
    /* vertex k is the start of edge k and the end of edge k-1 */
    const maskv start[3] = {on0, r->on1, r->on2}, end[3] = {r->on2, on0, r->on1};
    for (int k = 0; k < 3; ++k) {
        realv w = select((realv)R(0), ga, start[k]) + select((realv)R(0), gb, end[k]);
        acc->gx[k] += w * r->cx;
        acc->gy[k] += w * r->cy;
    }
}
#endif

#if SR_LIGHTING
/* Adjoint of per-pixel lighting: from dL/dC to the attribute weights (g_a), corner albedos,
 * corner normals and the light parameters. */
inline void lit_vjp(__global const real *col, __global const real *light, const Frag *r,
                    const realv gC[3], maskv valid, Accum *acc, realv g_a[3])
{
    const Lit L = eval_lit(col, light, r);
    realv gA[3], gs[3], g_n[3];
    for (int c = 0; c < 3; ++c) {
        gA[c] = keep(gC[c] * L.shade[c], valid);
        gs[c] = keep(gC[c] * L.albedo[c], valid);
    }
#if SR_LIGHTING == 1
    realv lit = fmax(L.n_dot_l, R(0));
    realv g_ndl = select((realv)R(0), gs[0] * light[3] + gs[1] * light[4] + gs[2] * light[5],
                         TO_MASK(L.n_dot_l > R(0)));
    for (int c = 0; c < 3; ++c) {
        acc->glight[c] += gs[c];
        acc->glight[3 + c] += gs[c] * lit;
        acc->glight[6 + c] += g_ndl * L.n[c];
        g_n[c] = g_ndl * light[6 + c];
    }
#else
    realv gP[9];
    for (int i = 0; i < 9; ++i) {
        gP[i] = gs[0] * light[i] + gs[1] * light[9 + i] + gs[2] * light[18 + i];
        for (int c = 0; c < 3; ++c)
            acc->glight[9 * c + i] += gs[c] * L.P[i];
    }
    const realv x = L.n[0], y = L.n[1], z = L.n[2];
    g_n[0] = gP[3] + y * gP[4] + z * gP[7] + R(2) * x * gP[8];
    g_n[1] = gP[1] + x * gP[4] + z * gP[5] - R(2) * y * gP[8];
    g_n[2] = gP[2] + y * gP[5] + R(6) * z * gP[6] + x * gP[7];
#endif
    /* n = m / |m| */
    realv n_dot_g = L.n[0] * g_n[0] + L.n[1] * g_n[1] + L.n[2] * g_n[2];
    realv g_m[3];
    for (int d = 0; d < 3; ++d)
        g_m[d] = (g_n[d] - L.n[d] * n_dot_g) * L.inv_len;
    for (int k = 0; k < 3; ++k) {
        g_a[k] += gA[0] * col[3 * k] + gA[1] * col[3 * k + 1] + gA[2] * col[3 * k + 2]
                  + g_m[0] * col[CORNER_COLORS + 3 * k] + g_m[1] * col[CORNER_COLORS + 3 * k + 1]
                  + g_m[2] * col[CORNER_COLORS + 3 * k + 2];
        for (int c = 0; c < 3; ++c) {
            acc->gcol[3 * k + c] += r->a[k] * gA[c];
            acc->gnrm[3 * k + c] += r->a[k] * g_m[c];
        }
    }
}
#endif

/* Adjoint of one (face, SR_VEC pixels) pair: the whole chain from the image cotangents to the face's
 * vertices and colours. */
inline void pair_vjp(const Face *f, const Frag *r, const PixelIn *in, const Params *p, int face,
                     __global const real *attr, __global const real *tex_image,
                     __global const real *light, int tex_res, int tex_h, int tex_w,
                     Accum *acc, realv gC[3])
{
    const maskv valid = r->valid;
    realv g_x = (realv)R(0);          /* dL/dx, x the sigmoid's argument */
    realv g_Z = (realv)R(0);          /* dL/dZ, Z the interpolated depth */
    realv g_a[3] = {(realv)R(0), (realv)R(0), (realv)R(0)};
    gC[0] = gC[1] = gC[2] = (realv)R(0);
#if (SR_NEED_COLOR && !SR_COLOR_HARD) || (SR_OUT_ALPHA && SR_ALPHA_AGG != 2)
    realv log_D, log_1mD;             /* log D and log(1 - D), sharing one exp and one log1p */
    log_sigmoid_pair(r->x, &log_D, &log_1mD);
#endif
#if SR_NEED_COLOR
    realv C[3] = {(realv)R(0), (realv)R(0), (realv)R(0)}, dC_du[3], dC_dv[3];
#if SR_OUT_RGB
    face_color(attr, tex_image, light, face, tex_res, tex_h, tex_w, r, C, dC_du, dC_dv);
#endif
#if !SR_COLOR_HARD
    realv t = log_D + (p->far - r->Z) * p->inv_range * p->inv_gamma;
    realv w = keep(exp(t - in->lse), valid);
    realv g_t = w * (in->g[0] * C[0] + in->g[1] * C[1] + in->g[2] * C[2]
                     + in->g_depth * r->Z - in->g_dot_img);                /* eq. 11-12 */
    g_x += g_t * exp(log_1mD);                                               /* dlogD/dx = 1-D */
    g_Z -= g_t * p->inv_gamma * p->inv_range;
#else
    realv w = select((realv)R(0), (realv)R(1), valid & (in->best_id == (idv)face));
#endif
    for (int c = 0; c < 3; ++c)
        gC[c] = w * in->g[c];
    g_Z += w * in->g_depth;
#if SR_OUT_RGB && SR_TEXTURE == 0 && SR_LIGHTING
    lit_vjp(attr + face * VERTEX_ATTR, light, r, gC, valid, acc, g_a);
#elif SR_OUT_RGB && SR_TEXTURE == 0
    __global const real *col = attr + face * VERTEX_ATTR;
    for (int k = 0; k < 3; ++k)
        g_a[k] = gC[0] * col[3 * k] + gC[1] * col[3 * k + 1] + gC[2] * col[3 * k + 2];
#elif SR_OUT_RGB && SR_TEXTURE == 2
    realv g_u = gC[0] * dC_du[0] + gC[1] * dC_du[1] + gC[2] * dC_du[2];
    realv g_v = gC[0] * dC_dv[0] + gC[1] * dC_dv[1] + gC[2] * dC_dv[2];
    __global const real *uv = attr + face * UV_ATTRS;
    for (int k = 0; k < 3; ++k)
        g_a[k] = g_u * uv[2 * k] + g_v * uv[2 * k + 1];
#endif
#endif
#if SR_OUT_ALPHA && SR_ALPHA_AGG == 0
    /* dA/dD_j = prod_{k != j} (1 - D_k), from the saved sums with the smallest term apart */
    realv l1m = log_1mD;
    realv l_excl = select(in->l_rest + in->l_min - l1m, in->l_rest, TO_MASK(in->min_id == (idv)face));
    g_x += keep(in->g_alpha * exp(l_excl + log_D + l1m), valid);
#elif SR_OUT_ALPHA && SR_ALPHA_AGG == 1
    g_x += keep(in->g_alpha * exp(log_D + log_1mD), valid & (in->sumD < R(1)));
#endif

#if SR_GRAD_POS
    g_x = keep(g_x, valid);
    g_Z = keep(g_Z, valid);
    /* attribute weights and depth -> clipped barycentrics and vertex depths */
    realv g_bc[3];
#if SR_PERSPECTIVE
    realv g_dot_a = g_a[0] * r->a[0] + g_a[1] * r->a[1] + g_a[2] * r->a[2];
    for (int k = 0; k < 3; ++k) {
        realv g_q = r->Z * (g_a[k] - g_dot_a) - r->Z * r->Z * g_Z;
        g_bc[k] = g_q * f->iz[k];
        acc->gz[k] -= keep(g_q * r->bc[k] * f->iz[k] * f->iz[k], valid);
    }
#else
    for (int k = 0; k < 3; ++k) {
        g_bc[k] = g_a[k] + g_Z * f->z[k];
        acc->gz[k] += keep(g_Z * r->bc[k], valid);
    }
#endif
    /* clipping: bc = clamp(b, 0, 1) / sum */
    realv g_dot_bc = g_bc[0] * r->bc[0] + g_bc[1] * r->bc[1] + g_bc[2] * r->bc[2];
    realv gb[3];
    for (int k = 0; k < 3; ++k)
        gb[k] = keep((g_bc[k] - g_dot_bc) * r->inv_clip_sum, (r->b[k] > R(0)) & (r->b[k] < R(1)));
    /* distance: x = +-d^2 / sigma */
    realv g_d2 = g_x * select((realv)(-p->inv_sigma), (realv)p->inv_sigma, r->inside);
#if SR_METRIC_BARY
    maskv min0 = MASK_NOT(r->min1 | r->min2);
    const maskv is_min[3] = {min0, r->min1, r->min2};
    for (int k = 0; k < 3; ++k)
        gb[k] += select((realv)R(0), R(2) * g_d2 * r->b[k], is_min[k]);
#else
    edge_vjp(r, g_d2, valid, acc);
#endif
    barycentric_vjp(f, r, gb, valid, acc);
#endif
}

#if SR_GRAD_COLOR && SR_TEXTURE == 0 && !SR_LIGHTING
inline void add_vertex_color_grads(const Frag *r, const realv gC[3], maskv valid, Accum *acc)
{
    for (int k = 0; k < 3; ++k)
        for (int c = 0; c < 3; ++c)
            acc->gcol[3 * k + c] += keep(r->a[k] * gC[c], valid);
}
#elif SR_GRAD_COLOR && SR_TEXTURE == 1
/* The face owns its texels, and this work-item owns the (tile, face) slot: plain adds. */
inline void add_face_texel_grads(const Frag *r, const realv gC[3], int tex_res,
                                 __global real *slot_tex)
{
    if (tex_res == 1) {           /* one texel: sum the lanes once */
        for (int c = 0; c < 3; ++c)
            slot_tex[c] += lane_sum(keep(gC[c], r->valid));
        return;
    }
    real a0[SR_VEC], a1[SR_VEC], g[3][SR_VEC];
    VSTORE(r->a[0], 0, a0);
    VSTORE(r->a[1], 0, a1);
    for (int c = 0; c < 3; ++c)
        VSTORE(keep(gC[c], r->valid), 0, g[c]);
    for (int l = 0; l < SR_VEC; ++l) {
        int texel = face_texel(a0[l], a1[l], tex_res) * 3;
        for (int c = 0; c < 3; ++c)
            slot_tex[texel + c] += g[c][l];
    }
}
#elif SR_GRAD_COLOR && SR_TEXTURE == 2
/* *sum += q atomically. Without cl_khr_int64_base_atomics (SR_INT64_ATOMICS 0): two 32-bit atomic
 * adds on the little-endian words, the low word's carry going into the high word. Every carry is
 * counted once, so when all adds are done the 64-bit sum is exact, the same in any order. */
inline void add_fixed_point(__global long *sum, const long q)
{
#if SR_INT64_ATOMICS
    atom_add(sum, q);
#else
    volatile __global uint *word = (volatile __global uint *)sum;
    const uint lo = (uint)q, hi = (uint)((ulong)q >> 32);
    const uint old = atomic_add(word, lo);
    atomic_add(word + 1, hi + (uint)(old + lo < old));
#endif
}

/* uv-map texels are shared between faces: integer (fixed-point) atomics, whose sums do not
 * depend on the order of the adds, keep the result deterministic. */
inline void add_uv_texel_grads(const Frag *r, const realv gC[3], __global const real *uv,
                               int tex_h, int tex_w, real scale, __global long *tex_grad)
{
    real a0[SR_VEC], a1[SR_VEC], a2[SR_VEC], g[3][SR_VEC];
    VSTORE(r->a[0], 0, a0);
    VSTORE(r->a[1], 0, a1);
    VSTORE(r->a[2], 0, a2);
    for (int c = 0; c < 3; ++c)
        VSTORE(keep(gC[c], r->valid), 0, g[c]);
    for (int l = 0; l < SR_VEC; ++l) {
        if (g[0][l] == R(0) && g[1][l] == R(0) && g[2][l] == R(0))
            continue;
        real u = a0[l] * uv[0] + a1[l] * uv[2] + a2[l] * uv[4];
        real v = a0[l] * uv[1] + a1[l] * uv[3] + a2[l] * uv[5];
        Taps taps = bilinear_taps(u, v, tex_h, tex_w);
        for (int k = 0; k < 4; ++k)
            for (int c = 0; c < 3; ++c) {
                long q = convert_long_rte(g[c][l] * taps.weight[k] * scale);
                if (q != 0)
                    add_fixed_point(tex_grad + taps.offset[k] + c, q);
            }
    }
}
#endif

/* The backward kernels' arguments after GEOMETRY_ARGS: cotangent planes, forward state, the uv
 * fixed-point scale and the outputs (slots per tile-list entry, uv texel sums). */
#define BACKWARD_ARGS \
    __global const real *grad_rgb, __global const real *grad_alpha, \
    __global const real *grad_depth, __global const real *g_dot_img, \
    __global const real *color_state, __global const real *alpha_state, \
    __global const int *id_state, const real tex_grad_scale, \
    __global real *slot_pos, __global real *slot_attr, __global real *slot_light, __global long *tex_grad

inline void accum_zero(Accum *acc)
{
    for (int i = 0; i < 3; ++i)
        acc->gx[i] = acc->gy[i] = acc->gz[i] = (realv)R(0);
    for (int i = 0; i < CORNER_COLORS; ++i)
        acc->gcol[i] = (realv)R(0);
#if SR_LIGHTING
    for (int i = 0; i < CORNER_COLORS; ++i)
        acc->gnrm[i] = (realv)R(0);
    for (int i = 0; i < LIGHT_PARAMS; ++i)
        acc->glight[i] = (realv)R(0);
#endif
}

/* The terms of one (face, pixels) pair: pair_vjp into acc, then the colour gradients (into acc,
 * the entry's face-texel slot slot_tex, or the batch item's uv texel sums tex_grad). */
inline void add_pair(const Face *f, const Frag *r, const PixelIn *in, const Params *p, int face,
                     __global const real *attr, __global const real *image, __global const real *light,
                     int tex_res, int tex_h, int tex_w, real tex_grad_scale, Accum *acc,
                     __global real *slot_tex, __global long *tex_grad)
{
    realv gC[3];
    pair_vjp(f, r, in, p, face, attr, image, light, tex_res, tex_h, tex_w, acc, gC);
#if SR_GRAD_COLOR && SR_TEXTURE == 0 && !SR_LIGHTING
    add_vertex_color_grads(r, gC, r->valid, acc);
#elif SR_GRAD_COLOR && SR_TEXTURE == 1
    add_face_texel_grads(r, gC, tex_res, slot_tex);
#elif SR_GRAD_COLOR && SR_TEXTURE == 2
    add_uv_texel_grads(r, gC, attr + face * UV_ATTRS, tex_h, tex_w, tex_grad_scale, tex_grad);
#endif
}

/* The summed terms of tile-list entry `slot` (lanes added in order) into its slot rows. */
inline void write_slots(const Accum *acc, int slot, __global real *slot_pos, __global real *slot_attr,
                        __global real *slot_light)
{
#if SR_GRAD_POS
    const realv pos[9] = {acc->gx[0], acc->gy[0], acc->gz[0], acc->gx[1], acc->gy[1], acc->gz[1],
                          acc->gx[2], acc->gy[2], acc->gz[2]};
    lane_sums(pos, 9, slot_pos + slot * 9);
#endif
#if SR_GRAD_COLOR && SR_TEXTURE == 0
    lane_sums(acc->gcol, CORNER_COLORS, slot_attr + slot * VERTEX_ATTR);
#endif
#if SR_GRAD_COLOR && SR_LIGHTING
    lane_sums(acc->gnrm, CORNER_COLORS, slot_attr + slot * VERTEX_ATTR + CORNER_COLORS);
    lane_sums(acc->glight, LIGHT_PARAMS, slot_light + slot * LIGHT_PARAMS);
#endif
}

__kernel void soft_raster_bwd(GEOMETRY_ARGS, BACKWARD_ARGS)
{
    const int cb = get_global_id(0), tile_row = get_global_id(1), batch = get_global_id(2);
    if (cb >= ntx)                /* work-items of the last group beyond the image */
        return;
    const Params p = make_params(inv_sigma, x_cut, inv_gamma, depth_range[2 * batch], depth_range[2 * batch + 1]);
    const int tile = (batch * nty + tile_row) * ntx + cb;
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    const realv px = ((real)(cb * SR_VEC) - R(0.5) * W + LANE_OFFSETS) * pix_scale;
    const int rows = min(TILE_H, H - tile_row * TILE_H);
    __global const real *image = tex_image + (size_t)batch * tex_h * tex_w * 3;
    __global long *item_tex_grad = tex_grad + (size_t)batch * tex_h * tex_w * 3;
    /* bit dr: row dr of the tile has a non-zero cotangent (a fit's masked loss leaves many without) */
    uint live_rows = 0;
    for (int dr = 0; dr < rows; ++dr) {
        const size_t pix = ((size_t)batch * Hp + tile_row * TILE_H + dr) * Wp + cb * SR_VEC;
        if (has_cotangent(grad_rgb, grad_alpha, grad_depth, g_dot_img, pix, npix))
            live_rows |= 1u << dr;
    }

    for (int k = tile_start[tile]; k < tile_start[tile + 1]; ++k) {
        const int face = tile_faces[k], slot = k;
        const Face f = load_face(geom, face);
        Accum acc;
        accum_zero(&acc);
        for (int dr = 0; dr < rows; ++dr) {
            const int row = tile_row * TILE_H + dr;
            const real py = (R(0.5) * H - row - R(0.5)) * pix_scale;
            if (!(live_rows >> dr & 1u) || outside_footprint(geom, face, FIRST_LANE(px), LAST_LANE(px), py))
                continue;
            const Frag r = eval_frag(&f, px, py, &p);
            if (!ANY(r.valid))
                continue;
            const size_t pix = ((size_t)batch * Hp + row) * Wp + cb * SR_VEC;
            const PixelIn in = load_pixel(grad_rgb, grad_alpha, grad_depth, g_dot_img,
                                          color_state, alpha_state, id_state, pix, npix);
            add_pair(&f, &r, &in, &p, face, attr, image, light, tex_res, tex_h, tex_w, tex_grad_scale,
                     &acc, slot_attr + (size_t)slot * tex_res * tex_res * 3, item_tex_grad);
        }
        write_slots(&acc, slot, slot_pos, slot_attr, slot_light);
    }
}

#if SR_VEC == 1
/* GPU layout backward: one work-group of GPU_BWD_GROUP work-items per tile. The tile's cotangents
 * and forward state go into local memory once; then each work-item owns the tile-list entries
 * first + lid, first + lid + GPU_BWD_GROUP, ...: for each, it adds its face's terms at every pixel
 * of the tile in row-major order and writes the entry's slot rows, which kernels/grad_sums.cl sums
 * per face in a fixed order. No two work-items write one slot (no float atomics), so reruns are
 * bit-identical; the sums group the terms by pixel, not by lane, so their last bits differ from
 * the CPU layout's. */
#define TILE_PIXELS (GPU_TILE_W * TILE_H)

__kernel __attribute__((reqd_work_group_size(GPU_BWD_GROUP, 1, 1)))
void soft_raster_bwd_tile(GEOMETRY_ARGS, BACKWARD_ARGS)
{
    __local PixelIn pixels[TILE_PIXELS];
    __local int live[TILE_PIXELS];   /* the pixel is in the image and has a non-zero cotangent */
    const int lid = get_local_id(0), tx = get_group_id(0), tile_row = get_group_id(1);
    const int batch = get_global_id(2);
    const int tile = (batch * nty + tile_row) * ntx + tx;
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    for (int i = lid; i < TILE_PIXELS; i += GPU_BWD_GROUP) {
        const int dr = i / GPU_TILE_W, row = tile_row * TILE_H + dr;   /* no %: see stage_records */
        const size_t pix = ((size_t)batch * Hp + row) * Wp + tx * GPU_TILE_W + i - dr * GPU_TILE_W;
        live[i] = row < H && has_cotangent(grad_rgb, grad_alpha, grad_depth, g_dot_img, pix, npix);
        if (live[i])
            pixels[i] = load_pixel(grad_rgb, grad_alpha, grad_depth, g_dot_img,
                                   color_state, alpha_state, id_state, pix, npix);
    }
    barrier(CLK_LOCAL_MEM_FENCE);

    const Params p = make_params(inv_sigma, x_cut, inv_gamma, depth_range[2 * batch], depth_range[2 * batch + 1]);
    __global const real *image = tex_image + (size_t)batch * tex_h * tex_w * 3;
    __global long *item_tex_grad = tex_grad + (size_t)batch * tex_h * tex_w * 3;
    for (int k = tile_start[tile] + lid; k < tile_start[tile + 1]; k += GPU_BWD_GROUP) {
        const int face = tile_faces[k], slot = k;
        const Face f = load_face(geom, face);
        Accum acc;
        accum_zero(&acc);
        for (int i = 0; i < TILE_PIXELS; ++i) {
            const int dr = i / GPU_TILE_W, row = tile_row * TILE_H + dr;
            const int col = tx * GPU_TILE_W + i - dr * GPU_TILE_W;
            const real px = ((real)col - R(0.5) * W + LANE_OFFSETS) * pix_scale;
            const real py = (R(0.5) * H - row - R(0.5)) * pix_scale;
            if (!live[i] || outside_footprint(geom, face, px, px, py))
                continue;
            const Frag r = eval_frag(&f, px, py, &p);
            if (!ANY(r.valid))
                continue;
            const PixelIn in = pixels[i];
            add_pair(&f, &r, &in, &p, face, attr, image, light, tex_res, tex_h, tex_w, tex_grad_scale,
                     &acc, slot_attr + (size_t)slot * tex_res * tex_res * 3, item_tex_grad);
        }
        write_slots(&acc, slot, slot_pos, slot_attr, slot_light);
    }
}
#endif

/* ---- layout: the padded planes (n, B, Hp, Wp) <-> interleaved (B, H, W, n) arrays ------------- */
/* The host hands images and cotangents over as numpy's interleaved arrays; transposing them on
 * the host (numpy's strided copies) cost more than these kernels. One work-item per SR_VEC pixels
 * of a row, as in the kernels above; plain copies, so the values keep their bits. */

/* Pixels x0 <= x < x1 of one row of an output's n planes (from: the row's start in a plane) into
 * its (B, H, W, n) array (to: the row's first pixel). */
inline void pack_row(__global const real *src, __global real *dst, const int n, const size_t npix,
                     const size_t from, const size_t to, const int x0, const int x1)
{
    for (int x = x0; x < x1; ++x)
        for (int c = 0; c < n; ++c)
            dst[(to + x) * n + c] = src[c * npix + from + x];
}

/* The forward's images, planes (n, B, Hp, Wp), as the (B, H, W[, 3]) arrays the host returns. */
__kernel void planes_to_pixels(const int W, const int H, const int Wp, const int Hp, const int ntx,
                               __global const real *rgb, __global const real *alpha,
                               __global const real *depth, __global real *out_rgb,
                               __global real *out_alpha, __global real *out_depth)
{
    const int cb = get_global_id(0), row = get_global_id(1), batch = get_global_id(2);
    if (cb >= ntx || row >= H)
        return;
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    const size_t from = ((size_t)batch * Hp + row) * Wp, to = ((size_t)batch * H + row) * W;
    const int x0 = cb * SR_VEC, x1 = min(W, x0 + SR_VEC);
#if SR_OUT_RGB
    pack_row(rgb, out_rgb, 3, npix, from, to, x0, x1);
#endif
#if SR_OUT_ALPHA
    pack_row(alpha, out_alpha, 1, npix, from, to, x0, x1);
#endif
#if SR_OUT_DEPTH
    pack_row(depth, out_depth, 1, npix, from, to, x0, x1);
#endif
}

/* The SR_VEC pixels from x0 of one padded row (in_image: the row is one of the H image rows) of
 * n planes, from a (B, H, W, n) array (from: the row's first pixel); zero in the padding, and
 * everywhere without a source. */
inline void unpack_row(__global const real *src, __global real *dst, const int n, const int has_src,
                       const bool in_image, const size_t npix, const size_t from, const size_t to,
                       const int x0, const int W)
{
    for (int x = x0; x < x0 + SR_VEC; ++x)
        for (int c = 0; c < n; ++c) {
            real value = R(0);
            if (has_src && in_image && x < W)
                value = src[(from + x) * n + c];
            dst[c * npix + to + x] = value;
        }
}

/* Backward prep: the cotangents (B, H, W[, 3]; has_*: given, else zero) as zero-padded planes,
 * and for softmax colours the per-pixel sum over rgb and depth of cotangent * forward output. */
__kernel void soft_raster_cotangents(const int W, const int H, const int Wp, const int Hp, const int ntx,
                                     const int has_rgb, const int has_alpha, const int has_depth,
                                     __global const real *grad_rgb, __global const real *grad_alpha,
                                     __global const real *grad_depth,
                                     __global const real *out_rgb, __global const real *out_depth,
                                     __global real *plane_rgb, __global real *plane_alpha,
                                     __global real *plane_depth, __global real *g_dot_img)
{
    /* no fused multiply-adds: the same roundings as the sums this replaced (numpy's, on the host) */
#pragma OPENCL FP_CONTRACT OFF
    const int cb = get_global_id(0), row = get_global_id(1), batch = get_global_id(2);
    if (cb >= ntx)
        return;
    const size_t npix = (size_t)get_global_size(2) * Hp * Wp;
    const size_t to = ((size_t)batch * Hp + row) * Wp, from = ((size_t)batch * H + row) * W;
    const int x0 = cb * SR_VEC;
#if SR_OUT_RGB
    unpack_row(grad_rgb, plane_rgb, 3, has_rgb, row < H, npix, from, to, x0, W);
#endif
#if SR_OUT_ALPHA
    unpack_row(grad_alpha, plane_alpha, 1, has_alpha, row < H, npix, from, to, x0, W);
#endif
#if SR_OUT_DEPTH
    unpack_row(grad_depth, plane_depth, 1, has_depth, row < H, npix, from, to, x0, W);
#endif
#if SR_NEED_COLOR && !SR_COLOR_HARD
    const size_t pix = to + x0;
    realv total = (realv)R(0);
    if (row < H) {                /* the forward leaves the padding rows unwritten */
#if SR_OUT_RGB
        realv rgb = VLOAD(0, plane_rgb + pix) * VLOAD(0, out_rgb + pix);
        for (int c = 1; c < 3; ++c)
            rgb = rgb + VLOAD(0, plane_rgb + c * npix + pix) * VLOAD(0, out_rgb + c * npix + pix);
        total = total + rgb;
#endif
#if SR_OUT_DEPTH
        total = total + VLOAD(0, plane_depth + pix) * VLOAD(0, out_depth + pix);
#endif
    }
    VSTORE(total, 0, g_dot_img + pix);
#endif
}
