/* The intensity centroid of a reconstructed particle along its line of sight (docs/design.md
 * §7.4; NumPy twin: plenocl.piv.tracking.SightLines.centres' host path, trilinear samples
 * by scipy.ndimage.map_coordinates(order=1, mode="constant")).
 *
 * tube_sums: particle p's tube samples lie at voxel index c_p + A_p l_s for the S local
 * offsets l_s = (u, v, t) (mm across and along the line; A_p: the particle's line frame
 * taken into voxel indices, row-major 3 x 3). Each sample is the volume's trilinear
 * value there (0 outside [0, n - 1] on any axis, as SciPy's constant mode), clipped at 0;
 * out[2p] = sum of the samples, out[2p + 1] = their sum weighted by t.
 *
 * Parallel structure: one work-group of PL_GROUP items per particle; item k takes the
 * samples k, k + PL_GROUP, ... and the group sums its two totals in local memory
 * (pl_group_sum). On a GPU PL_GROUP is wide and the group's items read neighbouring
 * samples of one small tube (cached); on a CPU it is 1 (one item per particle, looping).
 * No atomics, no shared state between particles. Sizes are arguments. */
#include "groupreduce.h" /* PL_GROUP, pl_group_sum */

inline float pl_trilinear(__global const float *vol, int nz, int ny, int nx, float x,
                          float y, float z)
{
    if (!(x >= 0.0f && x <= nx - 1 && y >= 0.0f && y <= ny - 1 && z >= 0.0f && z <= nz - 1))
        return 0.0f;
    const int x0 = min((int)x, nx - 1), y0 = min((int)y, ny - 1), z0 = min((int)z, nz - 1);
    const int x1 = min(x0 + 1, nx - 1), y1 = min(y0 + 1, ny - 1), z1 = min(z0 + 1, nz - 1);
    const float fx = x - x0, fy = y - y0, fz = z - z0;
    const long r00 = ((long)z0 * ny + y0) * nx, r01 = ((long)z0 * ny + y1) * nx;
    const long r10 = ((long)z1 * ny + y0) * nx, r11 = ((long)z1 * ny + y1) * nx;
    const float a = vol[r00 + x0] + fx * (vol[r00 + x1] - vol[r00 + x0]);
    const float b = vol[r01 + x0] + fx * (vol[r01 + x1] - vol[r01 + x0]);
    const float c = vol[r10 + x0] + fx * (vol[r10 + x1] - vol[r10 + x0]);
    const float d = vol[r11 + x0] + fx * (vol[r11 + x1] - vol[r11 + x0]);
    const float lo = a + fy * (b - a), hi = c + fy * (d - c);
    return lo + fz * (hi - lo);
}

__kernel void tube_sums(__global const float *vol, int nz, int ny, int nx,
                        __global const float *centre, __global const float *frame,
                        __global const float *offsets, int samples, __global float *out)
{
    __local float scratch[PL_GROUP];
    const int p = get_group_id(0), lid = get_local_id(0);
    __global const float *a = frame + 9 * p;
    const float cx = centre[3 * p], cy = centre[3 * p + 1], cz = centre[3 * p + 2];
    float total = 0.0f, along = 0.0f;
    for (int s = lid; s < samples; s += PL_GROUP) {
        const float u = offsets[3 * s], v = offsets[3 * s + 1], t = offsets[3 * s + 2];
        const float x = cx + a[0] * u + a[1] * v + a[2] * t;
        const float y = cy + a[3] * u + a[4] * v + a[5] * t;
        const float z = cz + a[6] * u + a[7] * v + a[8] * t;
        const float value = fmax(pl_trilinear(vol, nz, ny, nx, x, y, z), 0.0f);
        total += value;
        along += value * t;
    }
    total = pl_group_sum(scratch, total);
    along = pl_group_sum(scratch, along);
    if (lid == 0) {
        out[2 * p] = total;
        out[2 * p + 1] = along;
    }
}
