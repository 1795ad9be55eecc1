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

/* The cubic B-spline prefilter along one axis, in place: each line of the volume turned
 * into its interpolating B-spline coefficients with the mirror boundary (SciPy twin:
 * scipy.ndimage.spline_filter1d(order=3, mode="mirror"), which plenocl.piv.interpolate
 * .prepare applies to the zero-padded volume axis by axis; the device deformer filters
 * the same padded volume here, z then y then x, instead of on the host).
 *
 * The filter is the gain 6 then a causal and an anticausal first-order recursion with
 * the pole z = sqrt(3) - 2, started as SciPy starts them for a mirrored line (the causal
 * start sums z^i over the line, truncated at PL_HORIZON terms, where z^i < 1e-18: exact
 * in float32).
 *
 * Parallel structure: one work-item per line over a 2-D range of the other two axes
 * (line start = gid0 * s0 + gid1 * s1, elements `stride` apart); each walks its line
 * three times, serially (the recursion), with no shared state. Along y and z the
 * neighbouring work-items read neighbouring x (coalesced on a GPU); along x each walks
 * a contiguous row (cache lines on a CPU, strided across work-items on a GPU). */
#define PL_POLE (-0.2679491924311227f)
#define PL_HORIZON 32

__kernel void spline_prefilter(__global float *coeffs, int n, int stride, int s0, int s1)
{
    __global float *c = coeffs + (long)get_global_id(0) * s0 + (long)get_global_id(1) * s1;
    const float z = PL_POLE, gain = (1.0f - PL_POLE) * (1.0f - 1.0f / PL_POLE);
    if (n < 2)
        return;
    for (int i = 0; i < n; ++i)
        c[(long)i * stride] *= gain;
    /* causal start, mirror boundary: c0 + sum z^i (c_i + z^(n-1) c_(n-1-i)), over
     * 1 - z^(2(n-1)) */
    float zn1 = 1.0f;
    for (int i = 0; i < n - 1 && i < PL_HORIZON; ++i)
        zn1 *= z;
    if (n - 1 > PL_HORIZON)
        zn1 = 0.0f;
    float c0 = c[0] + zn1 * c[(long)(n - 1) * stride], zi = z;
    for (int i = 1; i < n - 1 && i < PL_HORIZON; ++i) {
        c0 += zi * (c[(long)i * stride] + zn1 * c[(long)(n - 1 - i) * stride]);
        zi *= z;
    }
    c[0] = c0 / (1.0f - zn1 * zn1);
    for (int i = 1; i < n; ++i)
        c[(long)i * stride] += z * c[(long)(i - 1) * stride];
    const long last = (long)(n - 1) * stride;
    c[last] = (z * c[last - stride] + c[last]) * z / (z * z - 1.0f);
    for (int i = n - 2; i >= 0; --i)
        c[(long)i * stride] = z * (c[(long)(i + 1) * stride] - c[(long)i * stride]);
}

/* One axis of the predictor's tensor-product resampling (plenocl.piv.interpolate
 * .resample, which multiplies the field by a weight matrix along x, then y, then z):
 * out[o, t, i] = sum_s w[t, s] src[o, s, i] for a source of `outer` x nsrc x `inner`
 * elements and weights w of ntgt x nsrc (cubic-spline or linear interpolation weights with
 * linear extrapolation, plenocl.piv.interpolate.cubic_weights / linear_weights). The
 * device deformer resamples the window-centre field onto the voxels here, so the dense
 * predictor is made on the device instead of on the host and uploaded every pass.
 * NumPy twin: plenocl.piv.interpolate.resample.
 *
 * Parallel structure: one work-item per output element over a 3-D range (i, t, o); each
 * loops over the nsrc source nodes (tens) in order, reading one weight row and one source
 * column. No atomics, no shared state; neighbouring items (i) read neighbouring source
 * elements, coalesced on a GPU where inner > 1 (the y and z passes, most of the work). */
__kernel void resample_axis(__global const float *src, int nsrc,
                            __global const float *w, __global float *out)
{
    const int i = get_global_id(0), t = get_global_id(1), o = get_global_id(2);
    const int inner = get_global_size(0), ntgt = get_global_size(1);
    __global const float *s = src + (long)o * nsrc * inner + i;
    __global const float *row = w + (long)t * nsrc;
    float acc = 0.0f;
    for (int k = 0; k < nsrc; ++k)
        acc += row[k] * s[(long)k * inner];
    out[((long)o * ntgt + t) * inner + i] = acc;
}
