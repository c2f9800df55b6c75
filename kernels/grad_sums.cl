/* Gradient reductions after the backward kernel (softras_cl/raster/reduce.py): the (tile, face)
 * slots summed per face, then the per-face corner sums summed onto vertices.
 *
 * Build-time flags (besides common.h's):
 *   SR_SUM_DOUBLE   1: accumulate and write double (needs cl_khr_fp64), 0: real
 *
 * Each output value is one work-item's sum of its terms one after another in a fixed order, so
 * results are bit-identical run to run (no atomics), and with double sums they carry the same
 * bits as a sequential float64 loop over the same terms in the same order (for the vertex sums,
 * np.bincount's; np.add.reduceat adds pairwise, so the per-face sums differ from it in the last
 * bit). Float32 slots are exact in double; without fp64 the sums are float.
 */
#if SR_SUM_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double sum_t;
#else
typedef real sum_t;
#endif

/* sums[g][c] = slot rows of face g added in face-major order: the rows are
 * slots[face_slots[j]] for j in face_start[g] .. face_start[g + 1] - 1, and an entry with
 * face_slots[j] < 0 (outside a region of interest) adds 0. One work-item per face (global size
 * >= n_faces): one per (face, column) made the work-groups so many that launching them cost
 * more than the sums on a CPU device. Up to SUM_COLUMNS columns at a time advance together, so
 * each slot row is read once per chunk instead of once per column. */
#define SUM_COLUMNS 9
__kernel void face_sums(const int n_faces, const int width,
                        __global const int *face_start, __global const int *face_slots,
                        __global const real *slots, __global sum_t *sums)
{
    const int g = get_global_id(0);
    if (g >= n_faces)
        return;
    const int first = face_start[g], end = face_start[g + 1];
    for (int c0 = 0; c0 < width; c0 += SUM_COLUMNS) {
        const int n = min(SUM_COLUMNS, width - c0);
        sum_t s[SUM_COLUMNS];
        for (int c = 0; c < n; ++c)
            s[c] = (sum_t)0;
        for (int j = first; j < end; ++j) {
            const int k = face_slots[j];
            for (int c = 0; c < n; ++c) {
                const sum_t term = k < 0 ? (sum_t)0 : (sum_t)slots[(size_t)k * width + c0 + c];
                s[c] = j == first ? term : s[c] + term;    /* the first term as is, like numpy's reductions */
            }
        }
        for (int c = 0; c < n; ++c)
            sums[(size_t)g * width + c0 + c] = s[c];
    }
}

/* out[v][c] = 0 + the corner values of vertex v added in increasing corner order: corner
 * corners[j] for j in vertex_start[v] .. vertex_start[v + 1] - 1, where corner i = 4 g + k is
 * corner k of face g and its value is face_vals[g * face_width + offset + 3 k + c] (4 g + k, not
 * 3 g + k: a shift and a mask, where i / 3 and i % 3 compile to an instruction Oclgrind lacks).
 * One work-item per vertex (global size >= n_vertices). */
__kernel void vertex_sums(const int n_vertices, const int face_width, const int offset,
                          __global const int *vertex_start, __global const int *corners,
                          __global const sum_t *face_vals, __global sum_t *out)
{
    const int v = get_global_id(0);
    if (v >= n_vertices)
        return;
    sum_t s[3] = {(sum_t)0, (sum_t)0, (sum_t)0};
    for (int j = vertex_start[v]; j < vertex_start[v + 1]; ++j) {
        const int i = corners[j];
        __global const sum_t *val = face_vals + (size_t)(i >> 2) * face_width + offset + 3 * (i & 3);
        for (int c = 0; c < 3; ++c)
            s[c] += val[c];
    }
    for (int c = 0; c < 3; ++c)
        out[(size_t)v * 3 + c] = s[c];
}
