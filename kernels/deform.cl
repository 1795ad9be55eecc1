/* Volume deformation for multi-pass PIV (docs/design.md §7): every voxel p of the output
 * samples a prepared volume (zero margin MARGIN around it, B-spline coefficients for
 * ORDER 3, the plain values for ORDER 1) at p + factor * d(p), d the dense predictor.
 * NumPy/SciPy twin: plenocl.piv.interpolate.deform (scipy.ndimage.map_coordinates,
 * mode="constant", prefilter=False).
 *
 * Parallel structure: one work-item per output voxel over a 3-D range (x, y, z); each
 * reads its three displacement components and 64 (ORDER 3) or 8 (ORDER 1) coefficients
 * and writes one value. No atomics, no shared state; neighbouring items read
 * neighbouring coefficients, so caches (CPU) and coalescing (GPU) serve them.
 * A sample outside the prepared volume is 0; taps beyond its faces read 0. */
#ifndef ORDER
#define ORDER 3
#endif

#if ORDER == 3
#define TAPS 4
#define FIRST 1   /* taps floor(x) - 1 .. floor(x) + 2 */
inline void pl_weights(float t, float *w)
{
    float t2 = t * t, t3 = t2 * t, s = 1.0f - t;
    w[0] = s * s * s / 6.0f;
    w[1] = (3.0f * t3 - 6.0f * t2 + 4.0f) / 6.0f;
    w[2] = (-3.0f * t3 + 3.0f * t2 + 3.0f * t + 1.0f) / 6.0f;
    w[3] = t3 / 6.0f;
}
#elif ORDER == 1
#define TAPS 2
#define FIRST 0   /* taps floor(x) .. floor(x) + 1 */
inline void pl_weights(float t, float *w)
{
    w[0] = 1.0f - t;
    w[1] = t;
}
#else
#error "ORDER must be 1 or 3"
#endif

__kernel void deform(__global const float *coeffs, int pz, int py, int px,
                     __global const float *disp, int margin, float factor,
                     __global float *out)
{
    int ix = get_global_id(0), iy = get_global_id(1), iz = get_global_id(2);
    int nx = get_global_size(0), ny = get_global_size(1), nz = get_global_size(2);
    long n = (long)nx * ny * nz, v = ((long)iz * ny + iy) * nx + ix;
    float cz = iz + margin + factor * disp[v];
    float cy = iy + margin + factor * disp[n + v];
    float cx = ix + margin + factor * disp[2 * n + v];
    if (!(cz >= 0.0f && cz <= pz - 1 && cy >= 0.0f && cy <= py - 1 &&
          cx >= 0.0f && cx <= px - 1)) {
        out[v] = 0.0f;
        return;
    }
    float fz = floor(cz), fy = floor(cy), fx = floor(cx);
    float wz[TAPS], wy[TAPS], wx[TAPS];
    pl_weights(cz - fz, wz);
    pl_weights(cy - fy, wy);
    pl_weights(cx - fx, wx);
    int z0 = (int)fz - FIRST, y0 = (int)fy - FIRST, x0 = (int)fx - FIRST;
    float sum = 0.0f;
    for (int a = 0; a < TAPS; ++a) {
        int z = z0 + a;
        if (z < 0 || z >= pz) continue;
        for (int b = 0; b < TAPS; ++b) {
            int y = y0 + b;
            if (y < 0 || y >= py) continue;
            __global const float *row = coeffs + ((long)z * py + y) * px;
            float line = 0.0f;
            for (int c = 0; c < TAPS; ++c) {
                int x = x0 + c;
                if (x >= 0 && x < px) line += wx[c] * row[x];
            }
            sum += wz[a] * wy[b] * line;
        }
    }
    out[v] = sum;
}
