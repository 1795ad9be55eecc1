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
 * frame: light conserved). Both volumes are one slab each.
 *
 * Fixed point: p is computed in 64-bit integers with 32 fractional bits (PL_FX_ONE):
 * map holds M's columns (the steps of p along a, b and c) and t, each rounded to that
 * grid (12 longs). Integer sums are exact in any order, so to_frame_3d (p from its
 * index) and from_frame_3d (p stepped from a candidate box's corner) find the same
 * floor and fraction for a frame voxel, and so the same taps: the two kernels are
 * transposes weight for weight (float32's roundings aside in the sums), and p carries
 * no float32 rounding at large indices. start: where a user voxel's candidate box
 * starts, as rows of M^-1 then -M^-1 t - reach (reach: the box's half-widths), in the
 * same fixed point: the box's corner is floor(start X) + 1 along each axis.
 *
 * Parallel structure: one work-item per output voxel over a 3-D range (x, y, planes),
 * both ways, as above: to_frame_3d reads its eight taps; from_frame_3d gathers the frame
 * voxels whose taps hold its user voxel (na x nb x nc candidates, the same count for
 * every item). No atomics, no shared state. With b_outer / y_outer the range is (x,
 * planes, y) instead: for a pose that keeps the world's y (a turn about y) the items of
 * one y row, run together, read one row of the other volume's (x, z) plane, which stays
 * in cache where a frame plane's tilted footprint through hundreds of world planes does
 * not (the whole sensor's grids). CPUs run the transpose as from_frame_3d_row, one
 * work-item per user row (y, z) along it: a sparse support's zero voxels then cost a
 * read each. to_frame_3d skips the frame voxels beyond each plane's columns (those that
 * reach the user's grid). */

#define PL_FX_ONE 4294967296.0f

typedef struct {
    long x, y, z;
} pl_fx3;

/* p's fraction, p - floor(p), from its low 32 bits. */
inline float pl_fx_frac(long p)
{
    return (float)(uint)(p & 0xffffffffL) * (1.0f / PL_FX_ONE);
}

/* p = t + a A + b B + c C (map: A, B, C, t). */
inline pl_fx3 pl_fx_index(__global const long *map, int a, int b, int c)
{
    pl_fx3 p = {map[9] + a * map[0] + b * map[3] + c * map[6],
                map[10] + a * map[1] + b * map[4] + c * map[7],
                map[11] + a * map[2] + b * map[5] + c * map[8]};
    return p;
}

/* Tap weight of user index i for a frame voxel at fixed-point index p along one axis:
 * 1 - f at floor(p), f at floor(p) + 1, else 0 (to_frame_3d's two values). */
inline float pl_fx_tap(long p, int i)
{
    const int d = i - (int)(p >> 32);
    const float f = pl_fx_frac(p);
    return d == 0 ? 1.0f - f : (d == 1 ? f : 0.0f);
}

/* The user's voxel u scaled by its norm. */
inline float pl_scaled(__global const float *user, __global const float *norm, size_t u)
{
    return user[u] * norm[u];
}

/* frame[c][b][a] = S user for frame planes c in [c_lo, c_lo + range(2)); 0 without
 * computing it beyond the plane's columns cols[c] (PoseResampler.frame_columns: no voxel
 * there has a tap in the grid). Inside the user's grid the eight taps are read straight
 * and interpolated axis by axis (four where y's fraction is 0: a pose that keeps the
 * world's y on whole voxels, the same branch for every item); at its faces a tap outside
 * reads voxel 0 with weight 0. */
__kernel void to_frame_3d(__global const float *user, __global const float *norm,
                          int unx, int uny, int unz, __global float *frame, int fnx, int fny,
                          int c_lo, __global const long *map, int b_outer,
                          __global const int2 *cols)
{
    int a = get_global_id(0);
    int b = get_global_id(b_outer ? 2 : 1), c = c_lo + (int)get_global_id(b_outer ? 1 : 2);
    if (a >= fnx)
        return;
    const int2 reach = cols[c];
    if (a < reach.x || a >= reach.y) {
        frame[((size_t)c * fny + b) * fnx + a] = 0.0f;
        return;
    }
    pl_fx3 p = pl_fx_index(map, a, b, c);
    int x0 = (int)(p.x >> 32), y0 = (int)(p.y >> 32), z0 = (int)(p.z >> 32);
    float fx = pl_fx_frac(p.x), fy = pl_fx_frac(p.y), fz = pl_fx_frac(p.z);
    float gx = 1.0f - fx, gy = 1.0f - fy, gz = 1.0f - fz;
    float sum = 0.0f;
    bool inside = x0 >= 0 && x0 + 1 < unx && y0 >= 0 && y0 + 1 < uny && z0 >= 0
                  && z0 + 1 < unz;
    if (inside && fy == 0.0f) {
        /* y on whole voxels (a pose that keeps the world's y: the same for every item):
         * the y0 + 1 taps weigh 0, and the four left are the eight's sum exactly */
        size_t u = ((size_t)z0 * uny + y0) * unx + x0, sz = (size_t)uny * unx;
        float lo = gx * pl_scaled(user, norm, u) + fx * pl_scaled(user, norm, u + 1);
        u += sz;
        float hi = gx * pl_scaled(user, norm, u) + fx * pl_scaled(user, norm, u + 1);
        sum = gz * lo + fz * hi;
    } else if (inside) {
        size_t u = ((size_t)z0 * uny + y0) * unx + x0, sy = unx, sz = (size_t)uny * unx;
        float lo = gy * (gx * pl_scaled(user, norm, u) + fx * pl_scaled(user, norm, u + 1))
                 + fy * (gx * pl_scaled(user, norm, u + sy)
                         + fx * pl_scaled(user, norm, u + sy + 1));
        u += sz;
        float hi = gy * (gx * pl_scaled(user, norm, u) + fx * pl_scaled(user, norm, u + 1))
                 + fy * (gx * pl_scaled(user, norm, u + sy)
                         + fx * pl_scaled(user, norm, u + sy + 1));
        sum = gz * lo + fz * hi;
    } else if (x0 >= -1 && x0 < unx && y0 >= -1 && y0 < uny && z0 >= -1 && z0 < unz) {
        float wx[2] = {gx, fx}, wy[2] = {gy, fy}, wz[2] = {gz, fz};
        for (int k = 0; k < 8; k++) {
            int x = x0 + (k & 1), y = y0 + ((k >> 1) & 1), z = z0 + (k >> 2);
            bool in = x >= 0 && x < unx && y >= 0 && y < uny && z >= 0 && z < unz;
            size_t u = in ? ((size_t)z * uny + y) * unx + x : 0;
            sum += in ? wz[k >> 2] * (wy[(k >> 1) & 1] * (wx[k & 1] * pl_scaled(user, norm, u)))
                      : 0.0f;
        }
    }
    frame[((size_t)c * fny + b) * fnx + a] = sum;
}

/* S^T frame at user voxel (x, y, z), before its norm: the sum over the candidate box's
 * frame voxels (its corner floor(start X) + 1, na x nb x nc of them, p stepped from the
 * corner by map's columns) of each one's tap weight for the voxel times its value. */
inline float pl_gathered(__global const float *frame, int fnx, int fny, int fnz,
                         __global const long *map, __global const long *start,
                         int na, int nb, int nc, int x, int y, int z)
{
    int a0 = (int)((start[9] + x * start[0] + y * start[1] + z * start[2]) >> 32) + 1;
    int b0 = (int)((start[10] + x * start[3] + y * start[4] + z * start[5]) >> 32) + 1;
    int c0 = (int)((start[11] + x * start[6] + y * start[7] + z * start[8]) >> 32) + 1;
    const pl_fx3 A = {map[0], map[1], map[2]}, B = {map[3], map[4], map[5]};
    const pl_fx3 C = {map[6], map[7], map[8]};
    pl_fx3 r = pl_fx_index(map, a0, b0, c0);
    float sum = 0.0f;
    for (int k = 0; k < nc; k++) {
        int c = c0 + k;
        pl_fx3 q = r;
        for (int j = 0; j < nb; j++) {
            int b = b0 + j;
            pl_fx3 p = q;
            for (int i = 0; i < na; i++) {
                int a = a0 + i;
                float w = pl_fx_tap(p.z, z) * (pl_fx_tap(p.y, y) * pl_fx_tap(p.x, x));
                bool inside = a >= 0 && a < fnx && b >= 0 && b < fny && c >= 0 && c < fnz;
                size_t f = inside ? ((size_t)c * fny + b) * fnx + a : 0;
                sum += inside ? w * frame[f] : 0.0f;
                p.x += A.x; p.y += A.y; p.z += A.z;
            }
            q.x += B.x; q.y += B.y; q.z += B.z;
        }
        r.x += C.x; r.y += C.y; r.z += C.z;
    }
    return sum;
}

/* user[z][y][x] = S^T frame for user planes z in [z_lo, z_lo + planes) (pl_gathered,
 * times the voxel's norm); with use_support, voxels where support is 0 are written 0
 * unread. from_frame_3d (GPUs): one work-item per user voxel over (x, y, planes), or
 * (x, planes, y) with y_outer. from_frame_3d_row (CPUs): one per user row (y, z), along
 * it, so that a sparse support's zero voxels cost a read each (a CPU driver runs an
 * element kernel's items as vectors, whose every lane pays for one lit voxel). The
 * same numbers either way. */
__kernel void from_frame_3d(__global const float *frame, int fnx, int fny, int fnz,
                            __global float *user, __global const float *norm,
                            __global const float *support, int use_support,
                            int unx, int uny, int z_lo, __global const long *map,
                            __global const long *start, int na, int nb, int nc, int y_outer)
{
    int x = get_global_id(0);
    int y = get_global_id(y_outer ? 2 : 1), z = z_lo + (int)get_global_id(y_outer ? 1 : 2);
    if (x >= unx)
        return;
    size_t out = ((size_t)z * uny + y) * unx + x;
    if (use_support && support[out] == 0.0f) {
        user[out] = 0.0f;
        return;
    }
    user[out] = pl_gathered(frame, fnx, fny, fnz, map, start, na, nb, nc, x, y, z)
                * norm[out];
}

__kernel void from_frame_3d_row(__global const float *frame, int fnx, int fny, int fnz,
                                __global float *user, __global const float *norm,
                                __global const float *support, int use_support,
                                int unx, int uny, int z_lo, __global const long *map,
                                __global const long *start, int na, int nb, int nc,
                                int y_outer)
{
    const int y = get_global_id(0), z = z_lo + (int)get_global_id(1);
    const size_t row = ((size_t)z * uny + y) * unx;
    for (int x = 0; x < unx; x++) {
        const size_t out = row + x;
        user[out] = use_support && support[out] == 0.0f
                    ? 0.0f
                    : pl_gathered(frame, fnx, fny, fnz, map, start, na, nb, nc, x, y, z)
                      * norm[out];
    }
}
