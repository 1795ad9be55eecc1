/* The direct correlation's 63 lags per window, fitted on the device (docs/design.md §7.5,
 * plenocl.piv.devicesums.DeviceSums.window_fit, for plenocl.piv.direct.correlate_deformed),
 * so that eight numbers per window come back instead of its 315 window sums. NumPy twin:
 * plenocl.piv.direct.direct_correlation, fit_direct, off_centre and uncertainty_from_sums on
 * the same sums (the host's arithmetic, operation for operation: float32 products of the
 * float32 sums, the rest in PL_REAL; FP_CONTRACT off so that no product is fused).
 *
 * window_fit: for window w of W, from its sums sums[(q 63 + k) W + w] (q: 0 s_a, 1 raw_a,
 * 2 s_b, 3 raw_b, 4 products; k the lag in plenocl.piv.direct.LAGS order, z -3..3 then y
 * and x -1..1, x fastest) and the lags' weight sums n[k]: the weighted Pearson coefficient
 * at every lag, the highest (the first among equals, as np.argmax), fitted per axis by the
 * three-point Gaussian (kernels/subpixel.h) where it lies at zero laterally and within two
 * voxels of zero in depth (else at lag zero). With `uncertain`, each axis's standard
 * uncertainty (Wieneke 2015) from the spread sums spread[(e 9 + j) W + w] and consts[0..3]
 * (the three correlated-sum factors, then the voxels a window weighs); NaN without signal
 * or without `uncertain`. out[f W + w]: dz, dy, dx, peak, sigma_z, sigma_y, sigma_x;
 * flags[w]: fitted | signal << 1 | (peak off lag zero) << 2.
 *
 * Parallel structure: one work-item per window, reading its own sums (neighbouring items
 * read neighbouring windows: coalesced) and writing its own outputs. No atomics, no shared
 * writes, no loop longer than the 63 lags. PL_REAL is double where the device has it
 * (PL_DOUBLE), else float. Sizes are arguments. */

#pragma OPENCL FP_CONTRACT OFF

#ifdef PL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define PL_REAL double
#else
#define PL_REAL float
#endif
#define PL_SUBPIXEL_REAL PL_REAL
#include "subpixel.h" /* pl_subpixel */

#define PL_NLAG 63
#define PL_CENTRE 31 /* lag (0, 0, 0) */

/* Lag index of the offsets (z, y, x) from the lowest lag: z 0..6, y and x 0..2. */
inline int pl_lag(int z, int y, int x) { return (z * 3 + y) * 3 + x; }

/* A window's weighted variance (as a sum), raw - s s / n: the product in float as the
 * host's float32 sums, the rest in PL_REAL; NaN stays NaN (np.maximum). */
inline PL_REAL pl_variance(float s, float raw, PL_REAL n)
{
    const float ss = s * s;
    return (PL_REAL)raw - (PL_REAL)ss / n;
}

inline PL_REAL pl_positive(PL_REAL v) { return v < 0 ? (PL_REAL)0 : v; }

/* The coefficient's normaliser at lag k: sqrt(max(var_a, 0) max(var_b, 0)). */
inline PL_REAL pl_norm(__global const float *sums, __global const PL_REAL *n, int k,
                       int w, int W)
{
    const long lag = (long)k * W + w, q = (long)PL_NLAG * W;
    return sqrt(pl_positive(pl_variance(sums[lag], sums[q + lag], n[k]))
                * pl_positive(pl_variance(sums[2 * q + lag], sums[3 * q + lag], n[k])));
}

/* The coefficient at lag k: cov / sqrt(scale), 0 where a variance is not positive. */
inline PL_REAL pl_coefficient(__global const float *sums, __global const PL_REAL *n, int k,
                              int w, int W)
{
    const long lag = (long)k * W + w, q = (long)PL_NLAG * W;
    const float sa = sums[lag], sb = sums[2 * q + lag];
    const PL_REAL scale = pl_positive(pl_variance(sa, sums[q + lag], n[k]))
                          * pl_positive(pl_variance(sb, sums[3 * q + lag], n[k]));
    const float sab = sa * sb;
    const PL_REAL cov = (PL_REAL)sums[4 * q + lag] - (PL_REAL)sab / n[k];
    return scale > 0 ? cov / sqrt(scale) : (PL_REAL)0;
}

/* One axis's uncertainty (plenocl.piv.direct.uncertainty_from_sums): the asymmetry's
 * spread from the nine spread sums raw[j W], the means ma, mb, the factor and count,
 * carried through the Gaussian fit at lag zero and its neighbours along the axis. */
inline PL_REAL pl_sigma(__global const float *raw, int W, PL_REAL ma, PL_REAL mb,
                        PL_REAL factor, PL_REAL count, PL_REAL rlo, PL_REAL r0, PL_REAL rhi,
                        PL_REAL nlo, PL_REAL nhi)
{
    const PL_REAL total = (PL_REAL)raw[0] - mb * raw[W] - ma * raw[2 * W];
    PL_REAL spread = (PL_REAL)raw[3 * W] + mb * mb * raw[4 * W];
    spread = spread + ma * ma * raw[5 * W];
    spread = spread + -2 * mb * raw[6 * W];
    spread = spread + -2 * ma * raw[7 * W];
    spread = spread + 2 * ma * mb * raw[8 * W];
    const PL_REAL excess = spread - total * total / count;
    const PL_REAL semi = (PL_REAL)0.5 * sqrt(factor * (excess < 0 ? (PL_REAL)0 : excess));
    const PL_REAL dlo = semi / (nlo > (PL_REAL)1e-30 ? nlo : (PL_REAL)1e-30);
    const PL_REAL dhi = semi / (nhi > (PL_REAL)1e-30 ? nhi : (PL_REAL)1e-30);
    const PL_REAL up = pl_subpixel(rlo - dlo, r0, rhi + dhi);
    const PL_REAL down = pl_subpixel(rlo + dlo, r0, rhi - dhi);
    return (PL_REAL)0.5 * fabs(up - down);
}

__kernel void window_fit(__global const float *sums, __global const PL_REAL *n, int W,
                         __global const float *spread, __global const PL_REAL *consts,
                         int uncertain, __global PL_REAL *out, __global int *flags)
{
    const int w = get_global_id(0);
    if (w >= W)
        return;
    PL_REAL r[PL_NLAG];
    int best = 0;
    for (int k = 0; k < PL_NLAG; k++) {
        r[k] = pl_coefficient(sums, n, k, w, W);
        if (r[k] > r[best])
            best = k;
    }
    const long q = (long)PL_NLAG * W, centre = (long)PL_CENTRE * W + w;
    const float sa = sums[centre], ra = sums[q + centre];
    const float sb = sums[2 * q + centre], rb = sums[3 * q + centre];
    const int signal = pl_variance(sa, ra, n[PL_CENTRE]) > (PL_REAL)(1e-9f * ra)
                       && pl_variance(sb, rb, n[PL_CENTRE]) > (PL_REAL)(1e-9f * fmax(ra, 1e-30f));
    const int lz = best / 9 - 3, ly = (best / 3) % 3 - 1, lx = best % 3 - 1;
    const int fitted = ly == 0 && lx == 0 && abs(lz) < 3;
    const int k = fitted ? lz + 3 : 3;
    const PL_REAL peak = r[pl_lag(k, 1, 1)];
    out[w] = (PL_REAL)(k - 3) + pl_subpixel(r[pl_lag(k - 1, 1, 1)], peak, r[pl_lag(k + 1, 1, 1)]);
    out[W + w] = pl_subpixel(r[pl_lag(k, 0, 1)], peak, r[pl_lag(k, 2, 1)]);
    out[2 * W + w] = pl_subpixel(r[pl_lag(k, 1, 0)], peak, r[pl_lag(k, 1, 2)]);
    out[3 * W + w] = peak;
    flags[w] = fitted | signal << 1 | (best != PL_CENTRE) << 2;
    const PL_REAL ma = (PL_REAL)sa / n[PL_CENTRE], mb = (PL_REAL)sb / n[PL_CENTRE];
    for (int e = 0; e < 3; e++) {
        const int step = e == 0 ? 9 : e == 1 ? 3 : 1;
        const int lo = PL_CENTRE - step, hi = PL_CENTRE + step;
        out[(4 + e) * W + w] = uncertain && signal
            ? pl_sigma(spread + (long)e * 9 * W + w, W, ma, mb, consts[e], consts[3], r[lo],
                       r[PL_CENTRE], r[hi], pl_norm(sums, n, lo, w, W), pl_norm(sums, n, hi, w, W))
            : (PL_REAL)NAN;
    }
}
