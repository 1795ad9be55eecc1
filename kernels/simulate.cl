/* Plenoptic image simulator (docs/design.md §2, §8): rays traced exactly through the main
 * lens (thin, or thick as its exit pupil at d_p before the array) and the microlens each
 * one enters. NumPy twin: plenocl/reference/simulate.py.
 *
 * Work layout: global id 0 = block of rays, global id 1 = source (particle or lens)
 * within the current chunk. A source's rays are numbered 0..rays-1 and each ray's
 * random words depend only on (seed, source, ray, k), so the image does not depend
 * on the device or on how the work is split. A lens may sit off its lattice node by
 * lens_shift (mm on the array plane; manufacturing errors): its optical centre and its
 * lit cell move with it, while the cell boundaries a particle's ray is sorted by stay on
 * the lattice (the shifts are a small fraction of a pitch). Sensor millimetres count from
 * the optical axis, which lies (edge_col, edge_row) pixels from the sensor's first pixel's
 * outer edge (Camera.sensor_edge_px: W/2, H/2 unless the sensor is a region of a larger
 * one). */
#include "common.h"

inline float2 pl_blur(uint key, float sigma_mm)
{
    float r = sqrt(-2.0f * log(1.0f - pl_uniform(pl_word(key, 3))));
    float t = PLENOCL_TWO_PI * pl_uniform(pl_word(key, 4));
    return (float2)(r * cos(t), r * sin(t)) * sigma_mm;
}

inline int pl_transmitted(__global const float *gain, int k, uint key)
{
    float g = gain[k];
    return g >= 1.0f || pl_uniform(pl_word(key, 2)) < g;
}

/* Rays of point particles. img_pts[p] = (X', Y', d', unused) in image space. */
__kernel void trace_particles(
    __global const float4 *img_pts, __global const pl_acc_t *quantum,
    __global const float *lens_gain, __global const float2 *lens_shift,
    volatile __global pl_acc_t *image,
    uint seed, uint src_offset, uint rays, uint rays_per_item,
    float aperture_radius, float d_p, float f_ml, float blur_mm,
    float ml_pitch, float ml_cos, float ml_sin, float ml_ox, float ml_oy, int nx, int ny,
    float ml_row, float ml_odd, float px_pitch, float edge_col, float edge_row, int width,
    int height)
{
    const pl_mla m = {ml_pitch, ml_cos, ml_sin, ml_ox, ml_oy, nx, ny, ml_row, ml_odd};
    const uint p = get_global_id(1);
    const uint src = src_offset + p;
    const float4 ip = img_pts[p];
    const pl_acc_t q = quantum[p];
    const float inv = d_p / ip.z;
    const uint r0 = get_global_id(0) * rays_per_item;
    const uint r1 = min(r0 + rays_per_item, rays);
    const uint skey = pl_source_key(seed, src);
    for (uint r = r0; r < r1; ++r) {
        const uint key = pl_ray_key(skey, r);
        float rad = aperture_radius * sqrt(pl_uniform(pl_word(key, 0)));
        float th = PLENOCL_TWO_PI * pl_uniform(pl_word(key, 1));
        float u = rad * cos(th), v = rad * sin(th);
        float x = u + (ip.x - u) * inv, y = v + (ip.y - v) * inv;
        int kx, ky;
        int k = pl_lens_index(m, x, y, &kx, &ky);
        if (k < 0 || !pl_transmitted(lens_gain, k, key)) continue;
        float2 c = pl_lens_center(m, kx, ky) + lens_shift[k];
        float2 s = c + f_ml * (float2)(ip.x - u, ip.y - v) / ip.z;
        if (blur_mm > 0.0f) s += pl_blur(key, blur_mm);
        int idx = pl_pixel_index(s.x, s.y, px_pitch, edge_col, edge_row, width, height);
        if (idx >= 0) pl_accumulate(image, idx, q);
    }
}

/* A uniform point of a lens's cell (array frame, from its centre) from two uniform
 * numbers: the pitch x row rectangle, for a hexagonal array with the four corners that lie
 * outside the (pointy-top) hexagon folded into its tips (the same area, point-reflected
 * about the middle of each rectangle half-edge). */
inline float2 pl_cell_point(const pl_mla m, float u1, float u2)
{
    float a = (u1 - 0.5f) * m.pitch, b = (u2 - 0.5f) * m.row;
    if (m.odd != 0.0f && fabs(b) > m.pitch * 0.57735027f - fabs(a) * 0.57735027f) {
        a = copysign(0.5f * m.pitch, a) - a;
        b = copysign(m.row, b) - b;
    }
    return (float2)(a, b);
}

/* Rays of a white calibration image: uniform light over each microlens, from a
 * stopped-down aperture of radius stop_radius. Source = lens index ky * nx + kx. */
__kernel void trace_white(
    __global const float *lens_gain, __global const float2 *lens_shift,
    volatile __global pl_acc_t *image, pl_acc_t quantum,
    uint seed, uint src_offset, uint rays, uint rays_per_item,
    float stop_radius, float d_p, float f_ml, float blur_mm,
    float ml_pitch, float ml_cos, float ml_sin, float ml_ox, float ml_oy, int nx, int ny,
    float ml_row, float ml_odd, float px_pitch, float edge_col, float edge_row, int width,
    int height)
{
    const pl_mla m = {ml_pitch, ml_cos, ml_sin, ml_ox, ml_oy, nx, ny, ml_row, ml_odd};
    const uint src = src_offset + get_global_id(1);
    if (src >= (uint)(nx * ny)) return;
    const int kx = (int)(src % (uint)nx), ky = (int)(src / (uint)nx);
    const float2 c = pl_lens_center(m, kx, ky) + lens_shift[src];
    const uint r0 = get_global_id(0) * rays_per_item;
    const uint r1 = min(r0 + rays_per_item, rays);
    const uint skey = pl_source_key(seed, src);
    for (uint r = r0; r < r1; ++r) {
        const uint key = pl_ray_key(skey, r);
        if (!pl_transmitted(lens_gain, (int)src, key)) continue;
        float2 ab = pl_cell_point(m, pl_uniform(pl_word(key, 5)), pl_uniform(pl_word(key, 6)));
        float a = ab.x, b = ab.y;
        float2 x = c + (float2)(ml_cos * a - ml_sin * b, ml_sin * a + ml_cos * b);
        float rad = stop_radius * sqrt(pl_uniform(pl_word(key, 0)));
        float th = PLENOCL_TWO_PI * pl_uniform(pl_word(key, 1));
        float2 s = c + f_ml * (x - (float2)(rad * cos(th), rad * sin(th))) / d_p;
        if (blur_mm > 0.0f) s += pl_blur(key, blur_mm);
        int idx = pl_pixel_index(s.x, s.y, px_pitch, edge_col, edge_row, width, height);
        if (idx >= 0) pl_accumulate(image, idx, quantum);
    }
}
