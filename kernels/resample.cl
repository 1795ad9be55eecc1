/* Lateral resampling between a user's grid and the lens-row frame (docs/design.md §5.1):
 * the projector of a grid across a rotated array's lens rows applies A_frame S, where
 * S interpolates the user's volume bilinearly, depth slice by depth slice, at the centres
 * of a frame grid whose axes follow the lens rows (the separable path), and S^T is its
 * exact transpose. The two grids share their depth planes.
 *
 * A frame voxel (a, b) sits at the user's fractional index p = M (a, b) + t; its value
 * is the bilinear interpolation of the user's slice at p (taps outside the user's grid
 * read 0), each user voxel's value scaled by `norm`, the inverse of the sum of its taps
 * over the frame: every user voxel spreads its light onto frame voxels with weights
 * summing to 1 (light is conserved). NumPy twin:
 * plenocl.reference.resample.resample_matrix.
 *
 * Parallel structure: one work-item per output voxel over a 3-D range (x, y, z), both
 * ways. to_frame reads its four taps; from_frame (the transpose) gathers the frame
 * voxels whose taps hold its user voxel: it finds them through the inverse map and
 * recomputes each candidate's taps with the same arithmetic as to_frame, so the two are
 * transposes weight for weight. No atomics, no shared state; neighbouring items read
 * neighbouring voxels. */

typedef struct {
    float m00, m01, m10, m11, t0, t1;
} pl_affine;

/* The user's fractional index of frame voxel (a, b). */
inline float2 pl_user_index(pl_affine m, int a, int b)
{
    return (float2)(m.m00 * a + m.m01 * b + m.t0, m.m10 * a + m.m11 * b + m.t1);
}

/* Tap weight of user index i for a frame voxel at fractional index p along one axis:
 * 1 - (p - floor p) at floor p, p - floor p at floor p + 1, else 0 (the differences are
 * exact in float32, so to_frame and from_frame agree to the bit). Branch-free, so that
 * the work-items of a group run it in step (vectorised on CPUs). */
inline float pl_tap(float p, int i)
{
    return fmax(0.0f, 1.0f - fabs(p - (float)i));
}

/* frame[z - fz0][b][a] = S user, for depth planes z in [z_lo, z_lo + range(2)); the
 * slabs hold planes from uz0 (user) and fz0 (frame). */
__kernel void to_frame(__global const float *user, __global const float *norm,
                       int unx, int uny, int uz0,
                       __global float *frame, int fnx, int fny, int fz0, int z_lo,
                       float m00, float m01, float m10, float m11, float t0, float t1)
{
    int a = get_global_id(0), b = get_global_id(1), z = z_lo + (int)get_global_id(2);
    if (a >= fnx)
        return;
    pl_affine m = {m00, m01, m10, m11, t0, t1};
    float2 p = pl_user_index(m, a, b);
    int x0 = (int)floor(p.x), y0 = (int)floor(p.y);
    __global const float *slice = user + (size_t)(z - uz0) * uny * unx;
    float sum = 0.0f;
    for (int y = y0; y <= y0 + 1; y++) {
        if (y < 0 || y >= uny)
            continue;
        float wy = pl_tap(p.y, y);
        for (int x = x0; x <= x0 + 1; x++)
            if (x >= 0 && x < unx)
                sum += wy * pl_tap(p.x, x) * (slice[(size_t)y * unx + x]
                                              * norm[(size_t)y * unx + x]);
    }
    frame[((size_t)(z - fz0) * fny + b) * fnx + a] = sum;
}

/* user[z - uz0][y][x] = S^T frame: the frame voxels whose taps hold (x, y) lie within
 * (ra, rb) of its frame position q = Minv (x, y) + tinv (|a - q_a| < ra): na x nb
 * candidates from floor(q - r) + 1 (na = ceil(2 ra), the same for every work-item so
 * that the loops run in step), each weighed with to_frame's own taps. With
 * use_support, voxels where support (a slab like user's) is 0 are written 0 unread. */
__kernel void from_frame(__global const float *frame, int fnx, int fny, int fz0,
                         __global float *user, __global const float *norm,
                         __global const float *support, int use_support,
                         int unx, int uny, int uz0, int z_lo,
                         float m00, float m01, float m10, float m11, float t0, float t1,
                         float i00, float i01, float i10, float i11, float s0, float s1,
                         float ra, float rb, int na, int nb)
{
    int x = get_global_id(0), y = get_global_id(1), z = z_lo + (int)get_global_id(2);
    if (x >= unx)
        return;
    size_t out = ((size_t)(z - uz0) * uny + y) * unx + x;
    if (use_support && support[out] == 0.0f) {
        user[out] = 0.0f;
        return;
    }
    pl_affine m = {m00, m01, m10, m11, t0, t1};
    int a0 = (int)floor(i00 * x + i01 * y + s0 - ra) + 1;
    int b0 = (int)floor(i10 * x + i11 * y + s1 - rb) + 1;
    __global const float *slice = frame + (size_t)(z - fz0) * fny * fnx;
    float sum = 0.0f;
    for (int j = 0; j < nb; j++) {
        int b = b0 + j;
        for (int i = 0; i < na; i++) {
            int a = a0 + i;
            float2 p = pl_user_index(m, a, b);
            float w = pl_tap(p.x, x) * pl_tap(p.y, y);
            bool inside = a >= 0 && a < fnx && b >= 0 && b < fny;
            sum += inside ? w * slice[(size_t)(inside ? b : 0) * fnx + (inside ? a : 0)] : 0.0f;
        }
    }
    user[out] = sum * norm[(size_t)y * unx + x];
}

/* ---- A grid seen by a posed camera (docs/design.md §5.5, issue 49) ----------------------
 * The same resampling in three dimensions: the frame grid lies in the camera's own frame
 * (its axes along the lens rows, the separable path), the user's grid in the world; a
 * frame voxel (a, b, c) sits at the user's fractional index p = M (a, b, c) + t (M: 3 x 3,
 * the pose and both grids' steps), and takes the trilinear interpolation of the user's
 * volume there, each user voxel's value scaled by `norm` (its taps' inverse sum over the
 * frame: light conserved). Both volumes are one slab each. map: M row-major then t (12
 * floats); inv: M^-1 then -M^-1 t; reach: the candidates' half-widths (3 floats).
 *
 * Parallel structure: one work-item per output voxel over a 3-D range (x, y, planes),
 * both ways, as above: to_frame_3d reads its eight taps; from_frame_3d gathers the frame
 * voxels whose taps hold its user voxel (na x nb x nc candidates, the same count for
 * every item) with to_frame_3d's own arithmetic. No atomics, no shared state. */

/* Trilinear tap weight of user index i for a frame voxel at fractional index p along one
 * axis, from f = p - floor(p): 1 - f at floor(p), f at floor(p) + 1, else 0; to_frame_3d
 * computes the same two values once per axis, so the two kernels are transposes weight
 * for weight, to the bit. */
inline float pl_tap3(float p, int i)
{
    const int i0 = (int)floor(p);
    const float f = p - (float)i0;
    return i == i0 ? 1.0f - f : (i == i0 + 1 ? f : 0.0f);
}

inline float3 pl_user_index3(__global const float *m, int a, int b, int c)
{
    return (float3)(m[0] * a + m[1] * b + m[2] * c + m[9],
                    m[3] * a + m[4] * b + m[5] * c + m[10],
                    m[6] * a + m[7] * b + m[8] * c + m[11]);
}

/* frame[c][b][a] = S user for frame planes c in [c_lo, c_lo + range(2)). The eight taps
 * unrolled: a tap outside the user's grid reads voxel 0 with weight 0. */
__kernel void to_frame_3d(__global const float *user, __global const float *norm,
                          int unx, int uny, int unz, __global float *frame, int fnx, int fny,
                          int c_lo, __global const float *map)
{
    int a = get_global_id(0), b = get_global_id(1), c = c_lo + (int)get_global_id(2);
    if (a >= fnx)
        return;
    float3 p = pl_user_index3(map, a, b, c);
    int x0 = (int)floor(p.x), y0 = (int)floor(p.y), z0 = (int)floor(p.z);
    float fx = p.x - (float)x0, fy = p.y - (float)y0, fz = p.z - (float)z0;
    float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy}, wz[2] = {1.0f - fz, fz};
    float sum = 0.0f;
    if (x0 >= -1 && x0 < unx && y0 >= -1 && y0 < uny && z0 >= -1 && z0 < unz) {
        for (int k = 0; k < 8; k++) {
            int x = x0 + (k & 1), y = y0 + ((k >> 1) & 1), z = z0 + (k >> 2);
            bool in = x >= 0 && x < unx && y >= 0 && y < uny && z >= 0 && z < unz;
            size_t u = in ? ((size_t)z * uny + y) * unx + x : 0;
            float w = wx[k & 1] * wy[(k >> 1) & 1] * wz[k >> 2];
            sum += in ? w * (user[u] * norm[u]) : 0.0f;
        }
    }
    frame[((size_t)c * fny + b) * fnx + a] = sum;
}

/* user[z][y][x] = S^T frame for user planes z in [z_lo, z_lo + range(2)); with
 * use_support, voxels where support is 0 are written 0 unread. */
__kernel void from_frame_3d(__global const float *frame, int fnx, int fny, int fnz,
                            __global float *user, __global const float *norm,
                            __global const float *support, int use_support,
                            int unx, int uny, int z_lo, __global const float *map,
                            __global const float *inv, __global const float *reach,
                            int na, int nb, int nc)
{
    int x = get_global_id(0), y = get_global_id(1), z = z_lo + (int)get_global_id(2);
    if (x >= unx)
        return;
    size_t out = ((size_t)z * uny + y) * unx + x;
    if (use_support && support[out] == 0.0f) {
        user[out] = 0.0f;
        return;
    }
    int a0 = (int)floor(inv[0] * x + inv[1] * y + inv[2] * z + inv[9] - reach[0]) + 1;
    int b0 = (int)floor(inv[3] * x + inv[4] * y + inv[5] * z + inv[10] - reach[1]) + 1;
    int c0 = (int)floor(inv[6] * x + inv[7] * y + inv[8] * z + inv[11] - reach[2]) + 1;
    float sum = 0.0f;
    for (int k = 0; k < nc; k++) {
        int c = c0 + k;
        for (int j = 0; j < nb; j++) {
            int b = b0 + j;
            for (int i = 0; i < na; i++) {
                int a = a0 + i;
                float3 p = pl_user_index3(map, a, b, c);
                float w = pl_tap3(p.x, x) * pl_tap3(p.y, y) * pl_tap3(p.z, z);
                bool inside = a >= 0 && a < fnx && b >= 0 && b < fny && c >= 0 && c < fnz;
                size_t f = inside ? ((size_t)c * fny + b) * fnx + a : 0;
                sum += inside ? w * frame[f] : 0.0f;
            }
        }
    }
    user[out] = sum * norm[out];
}
