/* Shared definitions for softras-cl kernels (OpenCL C 1.2).
 *
 * Build-time flags (set by softras_cl/program.py):
 *   SR_DOUBLE      1: real = double (needs cl_khr_fp64), 0: real = float
 * Every kernel works on SR_VEC = 8 adjacent pixels of one image row at a time, as realv vectors,
 * so CPU drivers use their SIMD lanes and GPU drivers simply see wider work-items.
 */
#if SR_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double8 realv;
typedef long8 maskv;   /* result type of comparisons between double8 */
#define REAL_MAX DBL_MAX
#else
typedef float real;
typedef float8 realv;
typedef int8 maskv;    /* result type of comparisons between float8 */
#define REAL_MAX FLT_MAX
#endif

#define SR_VEC 8
#define R(x) ((real)(x))

/* log(sigmoid(x)) without overflow for any finite x: min(x, 0) - log1p(exp(-|x|)). */
inline realv log_sigmoid(realv x)
{
    return fmin(x, R(0)) - log1p(exp(-fabs(x)));
}

/* Sum of the SR_VEC lanes of a vector, in a fixed order (deterministic). */
inline real lane_sum(realv v)
{
    real s = R(0);
    real lanes[SR_VEC];
    vstore8(v, 0, lanes);
    for (int l = 0; l < SR_VEC; ++l)
        s += lanes[l];
    return s;
}

/* Lanes where mask is true keep value, others become 0 (never multiplies: 0 * inf would be NaN). */
inline realv keep(realv value, maskv mask)
{
    return select((realv)R(0), value, mask);
}
