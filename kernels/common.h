/* Shared definitions for softras-cl kernels (OpenCL C 1.2).
 *
 * Build-time flags (set by softras_cl/raster/rasterizer.py via softras_cl/cl/program.py):
 *   SR_DOUBLE      1: real = double (needs cl_khr_fp64), 0: real = float
 *   SR_LANES       pixels per work-item vector: 1 (the GPU layout: scalars), or 8 or 16 floats
 *                  (the CPU layout; doubles are then always 4)
 * The CPU layout's kernels work on SR_VEC adjacent pixels (8 or 16 floats, 4 doubles) of one image
 * row at a time, as realv vectors, so CPU drivers use their SIMD lanes. With SR_LANES 1 the same
 * code is compiled over scalars (SR_VEC 1: realv = real), one pixel per work-item as
 * GPUs want it: one copy of the maths for both layouts. Scalar comparisons give 1 (not -1) for
 * true, so masks are negated with MASK_NOT and tested with ANY, which suit both.
 */
#if SR_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#if SR_LANES == 1
#if SR_DOUBLE
typedef double real;
#else
typedef float real;
#endif
typedef real realv;
/* select(a, b, c) on scalars takes c of a's width: int for float, long for double */
#if SR_DOUBLE
typedef long maskv;
#define TO_INT (int)
#define TO_MASK (long)
#else
typedef int maskv;
#define TO_INT
#define TO_MASK
#endif
#define SR_VEC 1
#define VLOAD(offset, p) ((p)[offset])
#define VSTORE(v, offset, p) ((p)[offset] = (v))
#define FIRST_LANE(v) (v)
#define LAST_LANE(v) (v)
#define LANE_OFFSETS R(0.5)
#define MASK_NOT(m) (!(m))
#define ANY(m) ((m) != 0)
#elif SR_DOUBLE
/* 4 doubles (256 bits): wider double vectors break pip's PoCL 3.0 on CPUs without AVX-512 (its
 * kernel cache returns programs with no kernels), and 256 bits is the native width anyway. */
typedef double real;
typedef double4 realv;
typedef long4 maskv;    /* result type of comparisons between double4 */
#define SR_VEC 4
#define VLOAD vload4
#define VSTORE vstore4
#define TO_INT convert_int4
#define TO_MASK convert_long4
#define FIRST_LANE(v) ((v).s0)
#define LAST_LANE(v) ((v).s3)
#define LANE_OFFSETS ((realv)(R(0.5), R(1.5), R(2.5), R(3.5)))
#elif SR_LANES == 16
/* 16 floats (512 bits) where the device prefers them (softras_cl.cl.device.vector_lanes) */
typedef float real;
typedef float16 realv;
typedef int16 maskv;    /* result type of comparisons between float16 */
#define SR_VEC 16
#define VLOAD vload16
#define VSTORE vstore16
#define TO_INT
#define TO_MASK
#define FIRST_LANE(v) ((v).s0)
#define LAST_LANE(v) ((v).sf)
#define LANE_OFFSETS ((realv)(R(0.5), R(1.5), R(2.5), R(3.5), R(4.5), R(5.5), R(6.5), R(7.5), \
                              R(8.5), R(9.5), R(10.5), R(11.5), R(12.5), R(13.5), R(14.5), R(15.5)))
#else
typedef float real;
typedef float8 realv;
typedef int8 maskv;     /* result type of comparisons between float8 */
#define SR_VEC 8
#define VLOAD vload8
#define VSTORE vstore8
#define TO_INT
#define TO_MASK
#define FIRST_LANE(v) ((v).s0)
#define LAST_LANE(v) ((v).s7)
#define LANE_OFFSETS ((realv)(R(0.5), R(1.5), R(2.5), R(3.5), R(4.5), R(5.5), R(6.5), R(7.5)))
#endif

#if SR_LANES != 1
#define MASK_NOT(m) (~(m))
#define ANY(m) any(m)
#endif

#define R(x) ((real)(x))

/* log(sigmoid(x)) without overflow for any finite x: min(x, 0) - log1p(exp(-|x|)). */
inline realv log_sigmoid(realv x)
{
    return fmin(x, R(0)) - log1p(exp(-fabs(x)));
}

/* log(sigmoid(x)) and log(sigmoid(-x)) = log(1 - sigmoid(x)) together: both share
 * log1p(exp(-|x|)), so one exp and one log1p serve both (bit-identical to two log_sigmoid calls). */
inline void log_sigmoid_pair(realv x, realv *pos, realv *neg)
{
    const realv tail = log1p(exp(-fabs(x)));
    *pos = fmin(x, R(0)) - tail;
    *neg = fmin(-x, R(0)) - tail;
}

/* Sum of the SR_VEC lanes of a vector, in a fixed order (deterministic). */
inline real lane_sum(realv v)
{
    real s = R(0);
    real lanes[SR_VEC];
    VSTORE(v, 0, lanes);
    for (int l = 0; l < SR_VEC; ++l)
        s += lanes[l];
    return s;
}

/* out[i] = lane_sum(v[i]) for i < n <= LANE_SUMS_MAX: the same sums, each in the same lane order,
 * but advanced side by side. One sum after another is a chain of dependent adds (the latency of
 * each add, times lanes, times sums), which measured as a third of the backward kernel. */
#define LANE_SUMS_MAX 27
inline void lane_sums(const realv *v, const int n, __global real *out)
{
    real lanes[LANE_SUMS_MAX][SR_VEC], s[LANE_SUMS_MAX];
    for (int i = 0; i < n; ++i) {
        VSTORE(v[i], 0, lanes[i]);
        s[i] = R(0);
    }
    for (int l = 0; l < SR_VEC; ++l)
        for (int i = 0; i < n; ++i)
            s[i] += lanes[i][l];
    for (int i = 0; i < n; ++i)
        out[i] = s[i];
}

/* Lanes where mask is true keep value, others become 0 (never multiplies: 0 * inf would be NaN). */
inline realv keep(realv value, maskv mask)
{
    return select((realv)R(0), value, mask);
}
