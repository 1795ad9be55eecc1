/* The correlated-sum factors of PIV's uncertainty (docs/design.md §7, plenocl.piv.direct
 * .correlated_factors, its NumPy twin, and plenocl.piv.devicesums.DeviceSums): how much
 * neighbouring voxels' contributions to a window's correlation asymmetry share, from the
 * whole volume once per pass.
 *
 * box_mean_axis: along one axis of a volume, the mean over the w values [i - w/2, i - w/2
 * + w) (zeros beyond the volume: scipy.ndimage.uniform_filter1d, mode constant, origin
 * 0); applied along z, y and x in turn it is uniform_filter's box mean. Lines as in
 * kernels/fftcorr.cl: line (u nv + v) of n elements `step` apart starts at u su + v sv.
 * contributions: for the unpadded voxels i of the padded volumes a, b (pads pz, py, px on
 * each face) and their box means ma, mb, with a' = a - ma and b' = b - mb, the field
 * a'(i) b'(i + e) - a'(i + e) b'(i) along the unit step e of axis `axis`.
 * lagged_rows: per row (z, y) of a field (nz, ny, nx), the products sum_x f(i) f(i + l d)
 * for lags l = 0 .. `lags` along axis `axis` (d its unit step; only pairs inside the
 * field), out[row (lags + 1) + l].
 * column_partials: per block of `block` rows of a (rows, cols) float array and per
 * column c, the block's values in that column added in row order in PL_ACC,
 * out[k cols + c] for block k; the host adds the blocks' partial sums in float64, so only
 * those come back (a few kB), not every row's lagged products.
 *
 * Parallel structure: box_mean_axis one work-item per line (a running sum in PL_ACC,
 * double where the device has it; lines along z and y are columns, neighbouring items
 * reading neighbouring voxels); contributions one work-item per row of voxels;
 * lagged_rows one work-item per row looping over its lags and voxels, eight at a time
 * (neighbouring items read neighbouring rows); column_partials one work-item per (column,
 * block of rows), neighbouring items reading neighbouring columns of the same rows. No
 * atomics, no shared writes; sums in a fixed order per item. Sizes are arguments. */

#ifdef PL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define PL_ACC double
#else
#define PL_ACC float
#endif

__kernel void box_mean_axis(__global const float *src, __global float *dst, int n,
                            int step, int nu, int su, int nv, int sv, int w)
{
    const int line = get_global_id(0);
    const int v = line % nv, u = line / nv;
    const long base = (long)u * su + (long)v * sv;
    const int lead = w / 2;
    PL_ACC acc = 0;
    for (int j = max(-lead, 0); j < min(w - lead, n); j++)
        acc += src[base + (long)j * step];
    for (int i = 0; i < n; i++) {
        dst[base + (long)i * step] = (float)(acc / w);
        if (i - lead >= 0)
            acc -= src[base + (long)(i - lead) * step];
        if (i - lead + w < n)
            acc += src[base + (long)(i - lead + w) * step];
    }
}

__kernel void contributions(__global const float *a, __global const float *b,
                            __global const float *ma, __global const float *mb,
                            int py_all, int px_all, int pz, int py, int px, int axis,
                            int ny, int nx, __global float *field)
{
    const int row = get_global_id(0);
    const int y = row % ny, z = row / ny;
    const long i0 = ((long)(z + pz) * py_all + (y + py)) * px_all + px;
    const long e = axis == 0 ? (long)py_all * px_all : axis == 1 ? px_all : 1;
    __global float *out = field + (long)row * nx;
    for (int x = 0; x < nx; x++) {
        const long i = i0 + x;
        const float ai = a[i] - ma[i], bi = b[i] - mb[i];
        const float aj = a[i + e] - ma[i + e], bj = b[i + e] - mb[i + e];
        out[x] = ai * bj - aj * bi;
    }
}

/* sum_x f[x] g[x] over len values, eight at a time in a fixed order (vector units), then
 * the rest. */
inline float pl_dot(__global const float *f, __global const float *g, int len)
{
    float8 acc = (float8)(0.0f);
    int x = 0;
    for (; x + 8 <= len; x += 8)
        acc += vload8(0, f + x) * vload8(0, g + x);
    const float4 h = acc.lo + acc.hi;
    float s = (h.x + h.z) + (h.y + h.w);
    for (; x < len; x++)
        s += f[x] * g[x];
    return s;
}

__kernel void lagged_rows(__global const float *field, int nz, int ny, int nx, int axis,
                          int lags, __global float *out)
{
    const int row = get_global_id(0);
    const int y = row % ny, z = row / ny;
    __global const float *f = field + (long)row * nx;
    for (int l = 0; l <= lags; l++) {
        float s = 0.0f;
        if (axis == 2)
            s = pl_dot(f, f + l, nx - l);
        else if ((axis == 1 ? y : z) + l < (axis == 1 ? ny : nz))
            s = pl_dot(f, f + (long)l * (axis == 1 ? nx : (long)ny * nx), nx);
        out[(long)row * (lags + 1) + l] = s;
    }
}

__kernel void column_partials(__global const float *x, int rows, int cols, int block,
                              __global PL_ACC *out)
{
    const int c = get_global_id(0), k = get_global_id(1);
    const int end = min(rows, (k + 1) * block);
    PL_ACC acc = 0;
    for (int r = k * block; r < end; r++)
        acc += x[(long)r * cols + c];
    out[(long)k * cols + c] = acc;
}
