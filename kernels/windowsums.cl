/* Weighted window sums of the direct correlation (docs/design.md §7, plenocl.piv.direct):
 * separable Gaussian-weighted sums of fields of two volumes, evaluated only at the window
 * corners of a grid, as three passes (x, then y, then z). NumPy twin:
 * plenocl.piv.direct.HostSums (three matrix products per sum, BLAS on the host).
 *
 * Lags: -PL_ZREACH ... PL_ZREACH in z (-D define: plenocl.piv.direct.REACH[0], 3), -1, 0,
 * 1 in y and x: NZLAG x 3 x 3 (63) lags.
 *
 * Taps: per axis a table of 2 n rows of T floats, the weight W(q + s/2) of its n lags
 * (rows 0 to n - 1; n = 3 in x and y, NZLAG in z) and its square (rows n to 2 n - 1);
 * tap t of a window with low corner L (unpadded voxels) weighs voxel L - margin + t.
 * Every voxel outside the volume is zero.
 *
 * Parallel structure: one work-item per output sum, no atomics, no shared state.
 *  - pair_rows, spread_rows (x pass): one work-item per (x corner, y, z) row segment of the
 *    volume; it loops over the T taps, reads the segment of a and the segments of b in the
 *    neighbouring rows once, and forms the fields (products a(q) b(q + s), differences)
 *    on the fly, writing NPAIR (75) or NSPREAD (27) sums. Neighbouring items read
 *    overlapping segments of the same rows (caches serve them).
 *  - axis_sums (y and z passes): one work-item per (inner index, corner, outer index x
 *    output field); it loops over T taps along the middle axis of its source field.
 *    Neighbouring items along the inner (fastest) index read neighbouring floats, so the
 *    reads coalesce on a GPU and stream on a CPU.
 * Each sum is one work-item's loop in tap order: the results do not depend on the device's
 * work-group size or core count. */

#ifndef PL_ZREACH
#define PL_ZREACH 3
#endif
#define NZLAG (2 * PL_ZREACH + 1)
#define NPAIR (12 + 9 * NZLAG) /* a, a^2, b, b^2 at 3 x lags each; a(q) b(q + s) at 63 lags */
#define NSPREAD 27  /* 9 fields of the uncertainty's asymmetry per axis e */

inline float pl_hsum(float8 v)
{
    float4 h = v.lo + v.hi;
    return (h.x + h.z) + (h.y + h.w);
}

/* The row kernels read padded volumes (PL_ZREACH zero planes on each side in z, one row
 * on each side in y,
 * enough zeros in x that every 8-float chunk of taps stays inside: see
 * plenocl.piv.devicesums.DeviceSums) and taps rows of `chunks` 8-float chunks (zeros
 * beyond the T taps), so their inner loops have no bounds checks and run as 8-wide vector
 * operations on a CPU. `row` is the padded offset of the unpadded row (z, y), `x0` the
 * padded x of tap 0 of corner c (`start` that of corner 0), `py`, `px` the padded row
 * count and length. */

/* x pass of the correlation sums. Output field f at out[((f nz + z) ny + y) cx + c]:
 * f = sx (a), 3 + sx (a^2), 6 + sx (b at x + sx - 1), 9 + sx (b^2 at x + sx - 1),
 * 12 + (sz 3 + sy) 3 + sx (a(z, y, x) b(z + sz - PL_ZREACH, y + sy - 1, x + sx - 1)). */
__kernel void pair_rows(__global const float *a, __global const float *b,
                        int nz, int ny, int py, int px, int start, int step, int cx,
                        int chunks, __global const float *taps,
                        __global float *out)
{
    int c = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    int len = 8 * chunks;
    long x0 = start + c * step;
    long row = ((long)(z + PL_ZREACH) * py + (y + 1)) * px + x0;
    __global const float *arow = a + row, *brow = b + row;
    long plane = (long)nz * ny * cx, at = ((long)z * ny + y) * cx + c;
    for (int s = 0; s < 3; ++s) {
        __global const float *w = taps + s * len;
        float8 sa = 0.0f, saa = 0.0f, sb = 0.0f, sbb = 0.0f;
        for (int k = 0; k < chunks; ++k) {
            float8 tap = vload8(k, w), av = vload8(k, arow);
            float8 bv = vload8(0, brow + 8 * k + s - 1);
            float8 wa = tap * av, wb = tap * bv;
            sa += wa;
            saa += wa * av;
            sb += wb;
            sbb += wb * bv;
        }
        out[s * plane + at] = pl_hsum(sa);
        out[(3 + s) * plane + at] = pl_hsum(saa);
        out[(6 + s) * plane + at] = pl_hsum(sb);
        out[(9 + s) * plane + at] = pl_hsum(sbb);
    }
    for (int dz = 0; dz < NZLAG; ++dz) { /* 9 independent sums (y lag, x lag) per plane */
        __global const float *lag = brow + (long)(dz - PL_ZREACH) * py * px - px - 1;
        float8 acc[9];
        for (int f = 0; f < 9; ++f) acc[f] = 0.0f;
        for (int k = 0; k < chunks; ++k) {
            float8 av = vload8(k, arow);
            float8 wa[3] = {vload8(k, taps) * av, vload8(k, taps + len) * av,
                            vload8(k, taps + 2 * len) * av};
            for (int dy = 0; dy < 3; ++dy)
                for (int sx = 0; sx < 3; ++sx)
                    acc[3 * dy + sx] += wa[sx] * vload8(0, lag + dy * px + 8 * k + sx);
        }
        for (int f = 0; f < 9; ++f) out[(12 + 9 * dz + f) * plane + at] = pl_hsum(acc[f]);
    }
}

/* x pass of the uncertainty's sums, one work-item per (c, y, z) and all three axes e of
 * the pair (i, i + e): with a0 = a(i), a1 = a(i + e), b0, b1 likewise, the fields
 * X = a0 b1 - a1 b0, Da = a0 - a1, Db = b1 - b0 weighted by W (lag e) and X^2, Da^2,
 * Db^2, X Da, X Db, Da Db by W^2. Output field 9 e + k as in pair_rows. The x weight of
 * lag e is that of lag +1 (taps rows 2, 5) along x, of lag 0 (rows 1, 4) otherwise;
 * `left` is the padded x of the volume's first voxel. */
__kernel void spread_rows(__global const float *a, __global const float *b,
                          int nz, int ny, int py, int px, int start, int step, int cx,
                          int chunks, __global const float *taps, int left,
                          __global float *out)
{
    int c = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    int len = 8 * chunks;
    long x0 = start + c * step;
    long row = ((long)(z + PL_ZREACH) * py + (y + 1)) * px + x0;
    long plane = (long)nz * ny * cx, at = ((long)z * ny + y) * cx + c;
    for (int e = 0; e < 3; ++e) {
        long next = e == 0 ? (long)py * px : (e == 1 ? px : 1);
        __global const float *w = taps + (e == 2 ? 2 : 1) * len;
        __global const float *w2 = taps + (e == 2 ? 5 : 4) * len;
        float8 acc[9];
        for (int f = 0; f < 9; ++f) acc[f] = 0.0f;
        for (int k = 0; k < chunks; ++k) {
            /* the fields are zero at i outside the volume, though a(i + e) may not be
             * (i = -1 along x): keep only the lanes at x >= 0 (x >= nx reads zeros) */
            int8 xs = (int8)(0, 1, 2, 3, 4, 5, 6, 7) + (int)(x0 - left) + 8 * k;
            float8 keep = select((float8)(0.0f), (float8)(1.0f), xs >= (int8)(0));
            float8 a0 = vload8(k, a + row), a1 = keep * vload8(k, a + row + next);
            float8 b0 = vload8(k, b + row), b1 = keep * vload8(k, b + row + next);
            float8 cross = a0 * b1 - a1 * b0, da = a0 - a1, db = b1 - b0;
            float8 t = vload8(k, w), t2 = vload8(k, w2);
            acc[0] += t * cross;
            acc[1] += t * da;
            acc[2] += t * db;
            acc[3] += t2 * (cross * cross);
            acc[4] += t2 * (da * da);
            acc[5] += t2 * (db * db);
            acc[6] += t2 * (cross * da);
            acc[7] += t2 * (cross * db);
            acc[8] += t2 * (da * db);
        }
        for (int f = 0; f < 9; ++f) out[(9 * e + f) * plane + at] = pl_hsum(acc[f]);
    }
}

/* y or z pass: input fields (nf_in, outer, n, inner), output (nf_out, outer, count, inner).
 * Output field j sums its source field fields[3 j] with tap row fields[3 j + 1] from
 * voxel L - margin + fields[3 j + 2] on (a lag's offset for the second window). */
__kernel void axis_sums(__global const float *in, int outer, int n, int inner,
                        int origin, int step, int count, int margin, int taps_len,
                        __global const float *taps, __global const int *fields,
                        __global float *out)
{
    int i = get_global_id(0), c = get_global_id(1), k = get_global_id(2);
    int j = k / outer, o = k % outer;
    int src = fields[3 * j], row = fields[3 * j + 1];
    int first = origin + c * step - margin + fields[3 * j + 2];
    __global const float *line = in + ((long)src * outer + o) * n * inner + i;
    __global const float *w = taps + row * taps_len;
    int lo = max(0, -first), hi = min(taps_len, n - first);
    float sum = 0.0f;
    for (int t = lo; t < hi; ++t)
        sum += w[t] * line[(long)(first + t) * inner];
    out[((long)j * outer + o) * count * inner + (long)c * inner + i] = sum;
}
