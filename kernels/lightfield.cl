/* Computational refocusing by shift-and-add over the sub-aperture views (docs/design.md §4,
 * paper §II.B). NumPy twin: plenocl/reference/refocus.py (refocus_views).
 *
 * The light field arrives as views with a one-lens border: views[n, ky + 1, kx + 1] =
 * (value * valid, valid) for plaid sample n = (u, v) of microlens (kx, ky); valid is 0
 * where the sample does not exist (outside the aperture, a lens calibration missed,
 * off the sensor) and on the border. Interpolating value and validity together makes
 * every tap branch-free.
 *
 * Output pixel (i, j) of plane p sits at lens coordinates
 *   (a, b) = ((j + 0.5) / S - 0.5, (i + 0.5) / S - 0.5)    (S: supersampling)
 * in the array's frame: b the lens row, a along it in pitches. Lens (kx, ky) sits at
 * (kx + row_shift (ky mod 2), ky): row_shift is 0 for a rectangular array and the odd
 * rows' shift (+-0.5) for a hexagonal one, whose views are staggered images.
 * E = sum_n B(value * valid) / sum_n B(valid) over the 3 x 3 lenses nearest to
 * (a, b) + shift[p, n]: the three rows nearest b, in each row the three lenses nearest
 * a, B the quadratic B-spline weights across the rows times those along each row (a
 * hexagonal row's weights from its own lens positions): samples that do not exist carry
 * no weight; 0 where none does. The quadratic B-spline's second moment is 1/4 lens^2 at
 * every sub-lens phase (bilinear weights blur by t(1 - t), nothing at t = 0), so every
 * plane is smoothed alike and the plane the views reach unshifted (alpha = 1) is not
 * sharper than the others (a focal stack's sharpness is not biased towards z = 0).
 * -D PL_STAGGERED=1 (a hexagonal array; 0 otherwise) takes each row's x weights from its own lens
 * positions; without it (row_shift 0, a rectangular array) they are computed once.
 * The host prepares shift[p, n] = (1 - 1/alpha_p) L^-1 (u_n, v_n) in lens units (L: the
 * array-plane mm per unit of (a, b)).
 * One work-item per output pixel and plane; sizes are arguments.
 */

/* Quadratic B-spline weights of the nodes -1, 0, +1 around the nearest node, for an
 * offset d in [-0.5, 0.5] from it. */
inline float3 bspline2(const float d)
{
    const float a = 0.5f - d, b = 0.5f + d;
    return (float3)(0.5f * a * a, 0.75f - d * d, 0.5f * b * b);
}

__kernel void refocus(__global const float2 *views,   /* (nuv, ny + 2, nx + 2) */
                      __global const float2 *shifts,  /* (planes, nuv), lens units */
                      const int nuv, const int nx, const int ny,
                      const int out_w, const int out_h, const float inv_supersample,
                      const float row_shift,          /* odd lens rows' shift (lenses) */
                      __global float *out)            /* (planes, out_h, out_w) */
{
    const int j = get_global_id(0), i = get_global_id(1), p = get_global_id(2);
    if (j >= out_w || i >= out_h) return;
    const int pitch = nx + 2;
    const size_t view_size = (size_t)pitch * (size_t)(ny + 2);
    /* + 1: position in the bordered view */
    const float kx = ((float)j + 0.5f) * inv_supersample + 0.5f;
    const float ky = ((float)i + 0.5f) * inv_supersample + 0.5f;
    const __global float2 *shift = shifts + (size_t)p * (size_t)nuv;
    float2 sum = (float2)(0.0f, 0.0f);
    for (int n = 0; n < nuv; ++n) {
        const float2 s = shift[n];
        const float x = kx + s.x, y = ky + s.y;
        const float cy = floor(y + 0.5f);  /* nearest row */
        const int y0 = (int)cy;
#if PL_STAGGERED
        const int x_near = (int)floor(x + 0.5f);  /* a row's nearest lens is +-1 from it */
        if (x_near < -2 || y0 < -1 || x_near > nx + 3 || y0 > ny + 2) continue;  /* all out */
#else
        const float cx = floor(x + 0.5f);  /* nearest lens, the same in every row */
        const int x0 = (int)cx;
        if (x0 < -1 || y0 < -1 || x0 > nx + 2 || y0 > ny + 2) continue;  /* all taps out */
        const float3 wx = bspline2(x - cx);
        const float wxs[3] = {wx.x, wx.y, wx.z};
#endif
        const float3 wy = bspline2(y - cy);
        const float wys[3] = {wy.x, wy.y, wy.z};
        const __global float2 *v = views + (size_t)n * view_size;
        for (int b = 0; b < 3; ++b) {
            const int yy = y0 + b - 1;
            if (yy < 0 || yy > ny + 1) continue;
#if PL_STAGGERED
            /* bordered row yy is lens row yy - 1: odd when yy is even */
            const float xr = x - row_shift * (float)((yy + 1) & 1);
            const float cx = floor(xr + 0.5f);  /* nearest lens of the row */
            const int x0 = (int)cx;
            const float3 wx = bspline2(xr - cx);
            const float wxs[3] = {wx.x, wx.y, wx.z};
#endif
            for (int a = 0; a < 3; ++a) {
                const int xx = x0 + a - 1;
                if (xx < 0 || xx > nx + 1) continue;
                sum += (wxs[a] * wys[b]) * v[(size_t)yy * pitch + xx];
            }
        }
    }
    out[((size_t)p * (size_t)out_h + (size_t)i) * (size_t)out_w + (size_t)j] =
        sum.y > 0.0f ? sum.x / sum.y : 0.0f;
}
