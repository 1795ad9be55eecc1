/* Lateral binning of a supersampled reconstruction (docs/design.md §6.4-6.5): each
 * output voxel is the sum of its factor x factor lateral sub-voxels, times a scale (the
 * image's scaling), so that only the binned volume crosses to the host; and its flat
 * inverse, the spreading of a coarse start over the sub-voxels, so that only the coarse
 * volume crosses to the device. NumPy twins: plenocl/reconstruction/supersample.py
 * (bin_lateral, spread_lateral). Sizes are arguments; one build serves every shape and
 * factor.
 *
 * Parallel structure: one work-item per output voxel of a depth slab, a gather of its
 * factor x factor sub-voxels; no atomics. The slab may be a cropped part of the fine grid
 * whose lateral start is not a multiple of the factor: (oy, ox) in [0, factor) is that
 * start's remainder, and the sub-voxels of a block that fall outside the slab (zero in
 * the full fine grid) are left out.
 *
 * Summation order: each sub-voxel row's sum over dx, then those row sums over dy, each
 * term scaled and rounded before it is added (FP_CONTRACT off: no fused multiply-add);
 * NumPy's bin_lateral of the scaled volume adds in that order today (numpy 2.x), but its
 * order is NumPy's choice, so the two agree to float32 rounding (tests/tolerances.py
 * BINNED), bit for bit where the orders coincide. */

#pragma OPENCL FP_CONTRACT OFF

__kernel void bin_lateral(__global const float *fine, int nyf, int nxf, int oy, int ox,
                          int factor, float scale, __global float *out, int ny, int nx,
                          int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    const int x = j % nx, y = (j / nx) % ny, z = j / (nx * ny);
    const int y0 = y * factor - oy, x0 = x * factor - ox;
    __global const float *slice = fine + (size_t)z * nyf * nxf;
    float sum = 0.0f;
    for (int dy = max(0, -y0); dy < factor && y0 + dy < nyf; ++dy) {
        __global const float *row = slice + (size_t)(y0 + dy) * nxf;
        float row_sum = 0.0f;
        for (int dx = max(0, -x0); dx < factor && x0 + dx < nxf; ++dx) {
            const float v = row[x0 + dx] * scale;
            row_sum += v;
        }
        sum += row_sum;
    }
    out[j] = sum;
}

/* fine[z][y][x] = coarse[z][y / factor][x / factor] * scale (scale: 1 / factor^2 over the
 * image's scaling). Parallel structure: one work-item per sub-voxel (x, y, z) of a depth
 * slab, a gather of its one coarse voxel; no atomics. */
__kernel void spread_lateral(__global const float *coarse, int ny, int nx, int factor,
                             float scale, __global float *fine, int nyf, int nxf)
{
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    fine[((size_t)z * nyf + y) * nxf + x] =
        coarse[((size_t)z * ny + y / factor) * nx + x / factor] * scale;
}

/* The coarse run's support found on the device (plenocl/reconstruction/schedule.py
 * support_of, its twin with box_dilated): keep[z][y][x] = 1 where any voxel of the 3 x 3
 * x 3 box around (x, y, z), inside the volume, is above floor (float32, as the host
 * compares), else 0. Parallel structure: one work-item per coarse voxel, a gather of its
 * 27 neighbours; no atomics. */
__kernel void grown_support(__global const float *coarse, int nz, int ny, int nx,
                            float floor_value, __global uchar *keep)
{
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    uchar found = 0;
    for (int dz = max(z - 1, 0); dz <= min(z + 1, nz - 1) && !found; ++dz)
        for (int dy = max(y - 1, 0); dy <= min(y + 1, ny - 1) && !found; ++dy) {
            __global const float *row = coarse + ((size_t)dz * ny + dy) * nx;
            for (int dx = max(x - 1, 0); dx <= min(x + 1, nx - 1); ++dx)
                found |= row[dx] > floor_value;
        }
    keep[((size_t)z * ny + y) * nx + x] = found;
}

/* The support spread over the sub-voxels of one depth slab (spread_lateral of the flat
 * start, without it crossing to the device): fine[z][y][x] = level * scale where
 * keep[z0 + z][y / factor][x / factor], else 0. Parallel structure: one work-item per
 * sub-voxel, a gather of its one coarse flag; no atomics. */
__kernel void spread_support(__global const uchar *keep, int z0, int ny, int nx, int factor,
                             float level, float scale, __global float *fine, int nyf,
                             int nxf)
{
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    const uchar on = keep[((size_t)(z0 + z) * ny + y / factor) * nx + x / factor];
    fine[((size_t)z * nyf + y) * nxf + x] = on ? level * scale : 0.0f;
}

/* The support's sums by (y, z) row: sums[r] = row r's values where keep (grown_support),
 * added in x order in float32; counts[r] = its voxels in the support (the NumPy form,
 * schedule.support_of, adds the same rows in the same order: the same bits). Parallel
 * structure: one work-item per row, a loop along it; no atomics. */
__kernel void support_rows(__global const float *coarse, __global const uchar *keep, int nx,
                           __global float *sums, __global int *counts)
{
    const size_t r = get_global_id(0);
    float sum = 0.0f;
    int count = 0;
    for (size_t i = r * nx; i < (r + 1) * nx; ++i) {
        const float v = keep[i] ? coarse[i] : 0.0f;
        sum += v;
        count += keep[i];
    }
    sums[r] = sum;
    counts[r] = count;
}

#ifdef PL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
/* support_parts: the rows' support sums and counts (support_rows, `rows` rows) combined
 * into parts, part p taking rows p, p + parts, p + 2 parts, ... in that order, the sums
 * added in double (supersample.row_parts, its NumPy twin, adds them alike: the same bits)
 * and the counts in long: what the host reads instead of one pair per row (a
 * paper-size coarse volume's 30,000 rows: 240 kB back, against 4 kB for 256 parts).
 * Devices without cl_khr_fp64 read the rows and combine them on the host. Parallel
 * structure: one work-item per part, a loop striding over the rows (consecutive items
 * read consecutive rows); no atomics, no local memory. */
__kernel void support_parts(__global const float *sums, __global const int *counts,
                            int rows, __global double *part_sums,
                            __global long *part_counts)
{
    const int p = get_global_id(0), parts = get_global_size(0);
    double sum = 0.0;
    long count = 0;
    for (int r = p; r < rows; r += parts) {
        sum += (double)sums[r];
        count += counts[r];
    }
    part_sums[p] = sum;
    part_counts[p] = count;
}
#endif
