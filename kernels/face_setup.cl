/* Face set-up on the device (softras_cl/raster/device_setup.py): the per-face records of the
 * layout (softras_cl.cl.layout) and each face's tile range, from the vertices and the faces.
 *
 * The same float64 operations in the same order as the host's softras_cl.raster.binning.face_setup
 * and bin_faces (the reference, and the path for devices without cl_khr_fp64), so the records and
 * the bins carry the same bits. Contraction into fused multiply-adds would change them: it is
 * switched off below, and the program is never built with -cl-fast-relaxed-math.
 *
 * Build-time flags (besides common.h's): SR_DOUBLE says whether the records are written as
 * double or float (computed in double either way, then rounded once, like numpy's astype);
 * SR_TILE_W is the tile width in pixels (binning.Grid.tile_w).
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define MIN_AREA 1e-12      /* softras_cl.raster.binning.MIN_AREA */

/* ceil and floor of v in [-1, INT_MAX] as ints (here cheaper than the double ceil and floor,
 * which clamping before or after rounding does not change: the bounds are integers) */
inline int ceil_int(const double v)
{
    const int t = (int)v;      /* rounded towards zero */
    return t + ((double)t < v);
}

inline int floor_int(const double v)
{
    const int t = (int)v;
    return t - ((double)t > v);
}

/* Per face g of the B*F faces (one work-item each, global size >= n_faces):
 *   geom[g]: FACE_STRIDE reals, every one written (all zero when the face cannot be drawn)
 *   tiles[g]: (tx0, ty0, nx, ny), the first tile column and row and how many of each its
 *       footprint box covers (all four 0 when it covers no pixel or cannot be drawn)
 * vertices: (B*V, 3) double; faces: (B*F, 3) int, indices within the face's batch item;
 * depth_range: (B, 2) double, each view's near and far (face g is view g / faces_per_view's).
 * box_margin: NDC margin added to the boxes (inf: unbounded); grow_box: 1 to grow each triangle
 * by `grow` about its centroid first (the barycentric metric). half_w = W / 2, top = H / 2 - 0.5
 * and inv_ps = min(W, H) / 2 come from the host, computed there as binning does. */
__kernel void face_setup(const int n_faces, const int faces_per_view, const int width, const int height,
                         const int double_sided, __global const double *depth_range,
                         const int grow_box, const double grow, const double box_margin,
                         const double half_w, const double top, const double inv_ps,
                         __global const double *vertices, __global const int *faces,
                         __global real *geom, __global int4 *tiles)
{
    const int g = get_global_id(0);
    if (g >= n_faces)
        return;
    const double3 p0 = vload3(faces[3 * (size_t)g], vertices);
    const double3 p1 = vload3(faces[3 * (size_t)g + 1], vertices);
    const double3 p2 = vload3(faces[3 * (size_t)g + 2], vertices);
    const double area = (p1.x - p0.x) * (p2.y - p0.y) - (p2.x - p0.x) * (p1.y - p0.y);
    const double zmin = fmin(fmin(p0.z, p1.z), p2.z), zmax = fmax(fmax(p0.z, p1.z), p2.z);
    const double near = depth_range[2 * (g / faces_per_view)], far = depth_range[2 * (g / faces_per_view) + 1];
    const bool drawable = (fabs(area) >= MIN_AREA) & (zmin > 0.0) & (zmax >= near) & (zmin <= far)
                          & (double_sided | (area > 0.0));
    const double inv_area = 1.0 / area;
    const double m1x = (p2.y - p0.y) * inv_area, m1y = -(p2.x - p0.x) * inv_area;
    const double m2x = -(p1.y - p0.y) * inv_area, m2y = (p1.x - p0.x) * inv_area;
    const double l0 = (p1.x - p0.x) * (p1.x - p0.x) + (p1.y - p0.y) * (p1.y - p0.y);
    const double l1 = (p2.x - p1.x) * (p2.x - p1.x) + (p2.y - p1.y) * (p2.y - p1.y);
    const double l2 = (p0.x - p2.x) * (p0.x - p2.x) + (p0.y - p2.y) * (p0.y - p2.y);
    double x0 = p0.x, x1 = p1.x, x2 = p2.x, y0 = p0.y, y1 = p1.y, y2 = p2.y;
    if (grow_box) {     /* the barycentric metric: the triangle grown about its centroid */
        const double cx = (x0 + x1 + x2) / 3.0, cy = (y0 + y1 + y2) / 3.0;
        x0 = cx + grow * (x0 - cx);
        x1 = cx + grow * (x1 - cx);
        x2 = cx + grow * (x2 - cx);
        y0 = cy + grow * (y0 - cy);
        y1 = cy + grow * (y1 - cy);
        y2 = cy + grow * (y2 - cy);
    }
    const double xmin = clamp(fmin(fmin(x0, x1), x2) - box_margin, -1e6, 1e6);
    const double xmax = clamp(fmax(fmax(x0, x1), x2) + box_margin, -1e6, 1e6);
    const double ymin = clamp(fmin(fmin(y0, y1), y2) - box_margin, -1e6, 1e6);
    const double ymax = clamp(fmax(fmax(y0, y1), y2) + box_margin, -1e6, 1e6);
    /* every value of a face that cannot be drawn is 0 */
#define PUT(i, v) row[i] = drawable ? (real)(v) : (real)0
    __global real *row = geom + (size_t)g * FACE_STRIDE;
    PUT(FACE_XY + 0, p0.x);
    PUT(FACE_XY + 1, p0.y);
    PUT(FACE_XY + 2, p1.x);
    PUT(FACE_XY + 3, p1.y);
    PUT(FACE_XY + 4, p2.x);
    PUT(FACE_XY + 5, p2.y);
    PUT(FACE_M + 0, -(m1x + m2x));
    PUT(FACE_M + 1, -(m1y + m2y));
    PUT(FACE_M + 2, m1x);
    PUT(FACE_M + 3, m1y);
    PUT(FACE_M + 4, m2x);
    PUT(FACE_M + 5, m2y);
    PUT(FACE_Z + 0, p0.z);
    PUT(FACE_Z + 1, p1.z);
    PUT(FACE_Z + 2, p2.z);
    PUT(FACE_INV_Z + 0, 1.0 / p0.z);
    PUT(FACE_INV_Z + 1, 1.0 / p1.z);
    PUT(FACE_INV_Z + 2, 1.0 / p2.z);
    PUT(FACE_INV_LEN2 + 0, 1.0 / (l0 > 0.0 ? l0 : 1.0));
    PUT(FACE_INV_LEN2 + 1, 1.0 / (l1 > 0.0 ? l1 : 1.0));
    PUT(FACE_INV_LEN2 + 2, 1.0 / (l2 > 0.0 ? l2 : 1.0));
    PUT(FACE_INV_LEN2 + 3, 0.0);        /* unused in the layout */
    PUT(FACE_INV_LEN2 + 4, 0.0);
    PUT(FACE_INV_LEN2 + 5, 0.0);
    PUT(FACE_BOX + 0, xmin);
    PUT(FACE_BOX + 1, xmax);
    PUT(FACE_BOX + 2, ymin);
    PUT(FACE_BOX + 3, ymax);
#undef PUT
    /* pixel columns and rows whose centres fall in the box, clipped to the image */
    const int c0 = max(ceil_int(clamp(xmin * inv_ps + half_w - 0.5, -1.0, (double)width)), 0);
    const int c1 = min(floor_int(clamp(xmax * inv_ps + half_w - 0.5, -1.0, (double)width)), width - 1);
    const int r0 = max(ceil_int(clamp(top - ymax * inv_ps, -1.0, (double)height)), 0);
    const int r1 = min(floor_int(clamp(top - ymin * inv_ps, -1.0, (double)height)), height - 1);
    const int tx0 = c0 / SR_TILE_W, ty0 = r0 / TILE_H;
    tiles[g] = drawable && c1 >= c0 && r1 >= r0
               ? (int4)(tx0, ty0, c1 / SR_TILE_W - tx0 + 1, r1 / TILE_H - ty0 + 1) : (int4)(0, 0, 0, 0);
}
