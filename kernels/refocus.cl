/* Computational refocusing by shift-and-add over the sub-aperture views (docs/design.md §4,
 * paper §II.B). NumPy twin: plenocl/reference/refocus.py (refocus_views).
 *
 * The light field arrives as views with a one-lens border: views[n, ky + 1, kx + 1] =
 * (value * valid, valid) for plaid sample n = (u, v) of microlens (kx, ky); valid is 0
 * where the sample does not exist (outside the aperture, a lens calibration missed,
 * off the sensor) and on the border. Interpolating value and validity together makes
 * every tap branch-free.
 *
 * Output pixel (i, j) of plane p sits at lens-index coordinates
 *   (kx, ky) = ((j + 0.5) / S - 0.5, (i + 0.5) / S - 0.5)    (S: supersampling)
 * and E = sum_n bilinear(value * valid) / sum_n bilinear(valid) over the four nearest
 * lenses at k + shift[p, n]: samples that do not exist carry no weight; 0 where none
 * does. The host prepares shift[p, n] = (1 - 1/alpha_p) L^-1 (u_n, v_n) in lens-index
 * units. One work-item per output pixel and plane; sizes are arguments.
 */

__kernel void refocus(__global const float2 *views,   /* (nuv, ny + 2, nx + 2) */
                      __global const float2 *shifts,  /* (planes, nuv), lens-index units */
                      const int nuv, const int nx, const int ny,
                      const int out_w, const int out_h, const float inv_supersample,
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
        const float fx = floor(x), fy = floor(y);
        const int x0 = (int)fx, y0 = (int)fy;
        if (x0 < 0 || y0 < 0 || x0 > nx || y0 > ny) continue;  /* all four taps outside */
        const float tx = x - fx, ty = y - fy;
        const __global float2 *v = views + (size_t)n * view_size + (size_t)y0 * pitch + x0;
        const float2 top = mix(v[0], v[1], tx), bottom = mix(v[pitch], v[pitch + 1], tx);
        sum += mix(top, bottom, ty);
    }
    out[((size_t)p * (size_t)out_h + (size_t)i) * (size_t)out_w + (size_t)j] =
        sum.y > 0.0f ? sum.x / sum.y : 0.0f;
}
