/* A volume kept on the device, summarised and read at a few voxels instead of copied to
 * the host (plenocl.opencl.volume.DeviceVolume; NumPy twins: plenocl.reference.volume).
 * A reconstruction's volume stays on the device from its solver to the particles it
 * holds; the checks and particle levels of the stages after it need only these numbers
 * (issue 46, docs/design.md §7.5). Sizes are arguments. */

/* row_summary: for each (z, y) row r of nx values, its smallest and largest finite
 * value (lo[r], hi[r]; +INFINITY and -INFINITY for a row without one), its values that
 * are not finite (nonfinite[r]) and its non-zero values (nonzero[r], NaN counted as
 * non-zero, as NumPy's count_nonzero). The host takes the extremes and sums of the rows:
 * exact, whatever the order. Parallel structure: one work-item per row, a loop along
 * it; no atomics, no local memory (nz ny items: tens of thousands for a volume). */
__kernel void row_summary(__global const float *v, int nx, __global float *lo,
                          __global float *hi, __global int *nonfinite,
                          __global int *nonzero)
{
    const size_t r = get_global_id(0);
    __global const float *row = v + r * (size_t)nx;
    float low = INFINITY, high = -INFINITY;
    int bad = 0, lit = 0;
    for (int x = 0; x < nx; ++x) {
        const float value = row[x];
        const int finite = isfinite(value);
        bad += !finite;
        lit += value != 0.0f;
        if (finite) {
            low = fmin(low, value);
            high = fmax(high, value);
        }
    }
    lo[r] = low;
    hi[r] = high;
    nonfinite[r] = bad;
    nonzero[r] = lit;
}

/* summary_parts: the rows' summaries (lo, hi, nonfinite, nonzero of `rows` rows, from
 * row_summary) combined into `parts` partial ones, part p taking rows p, p + parts,
 * p + 2 parts, ...: what the host reads instead of one per row (a paper-size volume's
 * 30,000 rows: 480 kB back, against 4 kB for 256 parts). Extremes and integer sums, so
 * exact in any order; the counts summed in long. Parallel structure: one work-item per
 * part, a loop striding over the rows (consecutive items read consecutive rows);
 * no atomics, no local memory. */
__kernel void summary_parts(__global const float *lo, __global const float *hi,
                            __global const int *nonfinite, __global const int *nonzero,
                            int rows, __global float *part_lo, __global float *part_hi,
                            __global long *part_nonfinite, __global long *part_nonzero)
{
    const int p = get_global_id(0), parts = get_global_size(0);
    float low = INFINITY, high = -INFINITY;
    long bad = 0, lit = 0;
    for (int r = p; r < rows; r += parts) {
        low = fmin(low, lo[r]);
        high = fmax(high, hi[r]);
        bad += nonfinite[r];
        lit += nonzero[r];
    }
    part_lo[p] = low;
    part_hi[p] = high;
    part_nonfinite[p] = bad;
    part_nonzero[p] = lit;
}

/* neighbourhoods: for each of n voxels (flat indices `index`, C order of nz x ny x nx),
 * its value and its six face neighbours' (out[7 k ...]: the voxel, then x - 1, x + 1,
 * y - 1, y + 1, z - 1, z + 1), 0 beyond the volume's faces: what a peak's three-point
 * fits read (plenocl.peaks.find_particles). Parallel structure: one work-item per voxel,
 * seven reads; no atomics. */
__kernel void neighbourhoods(__global const float *v, int nz, int ny, int nx,
                             __global const long *index, int n, __global float *out)
{
    const int k = get_global_id(0);
    if (k >= n)
        return;
    const long i = index[k];
    const int ix = (int)(i % nx), iy = (int)((i / nx) % ny), iz = (int)(i / ((long)nx * ny));
    const long sy = nx, sz = (long)nx * ny;
    __global float *o = out + 7 * (long)k;
    o[0] = v[i];
    o[1] = ix > 0 ? v[i - 1] : 0.0f;
    o[2] = ix < nx - 1 ? v[i + 1] : 0.0f;
    o[3] = iy > 0 ? v[i - sy] : 0.0f;
    o[4] = iy < ny - 1 ? v[i + sy] : 0.0f;
    o[5] = iz > 0 ? v[i - sz] : 0.0f;
    o[6] = iz < nz - 1 ? v[i + sz] : 0.0f;
}
