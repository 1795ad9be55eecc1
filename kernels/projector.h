/* Helpers of the matrix-free projector (kernels/projector.cl); NumPy twin of the model:
 * plenocl/reference/weights.py.
 *
 * Per-depth coefficients (16 floats per depth, built on the host in float64):
 *   [0..3]   G: d(kx, ky)/d(ix, iy), fractional lens index per voxel step
 *   [4..5]   o: lens index of voxel (0, 0) seen through the aperture centre
 *   [6..9]   H: d(kx, ky)/d(i, j), lens index per aperture-sample step
 *   [10..13] inverse of G
 *   [14..15] half-widths (voxels) of the inverse image of a lens's [-1, 1]^2 box
 * A voxel (ix, iy) seen through aperture sample (i, j) meets the array plane at lens
 * index G (ix, iy) + o + H (i - c, j - c). The separable path needs G[1][0] = H[0][1] =
 * H[1][0] = 0 (ky of the voxel row and the aperture row only; kx of the voxel row's shift
 * G[0][1] iy, a hexagonal array's, and of the column), and then the general evaluation
 * equals the separable one bit for bit.
 *
 * Performance note: PoCL's CPU driver (3.0, distro build) calls its builtins (floor,
 * fma, fabs, fmax, vload8, ...) as out-of-line functions, spilling vector registers at
 * each call. Hot code here therefore uses plain arithmetic, vector pointers and the
 * small inline helpers below. FP contraction is off so that every kernel rounds the
 * shared expressions identically (forward and back stay exact transposes). */
#ifndef PLENOCL_PROJECTOR_H
#define PLENOCL_PROJECTOR_H

#pragma OPENCL FP_CONTRACT OFF

#ifndef PL_VW
#define PL_VW 8      /* explicit vector width of row updates (1, 4, 8 or 16) */
#endif
#if PL_VW == 16
typedef float16 pl_vec;
#elif PL_VW == 8
typedef float8 pl_vec;
#elif PL_VW == 4
typedef float4 pl_vec;
#else
typedef float pl_vec;
#endif

#ifndef PL_BACK_ALLCOLS
#define PL_BACK_ALLCOLS 0  /* 1: a back_y work-item covers every column of a chunk (CPUs) */
#endif
#define PL_PAIRS 128  /* (aperture row, depth) weights back_y lists at a time */
#define PL_XLIST 128  /* non-zero voxels of a row fwd_x_row and back_x_row list at a time */
#ifndef PL_LENS_EXTENT
#define PL_LENS_EXTENT 0  /* 1: lens weights integrate the voxel's extent (issue 47) */
#endif
#ifndef PL_EXTENT
#define PL_EXTENT 0  /* 1: the separable kernels keep to a plane extent (pl_seg_span) */
#endif
#ifndef PL_SCALAR_ROWS
#define PL_SCALAR_ROWS 0  /* 1: one row element per work-item (a GPU's layout): fwd_y and
                             back_y sum in a register (kernels/projector.cl) */
#endif

#define PL_NO_LENS (-1073741824)   /* lens_rnd.x of a lens calibration missed (NaN centre) */

#include "arith.h" /* pl_abs, pl_mini, pl_maxi, pl_floori, pl_ceili, pl_atomic_addf */

/* Linear-interpolation (hat) weight of a point at signed distance d. */
inline float pl_tent(float d)
{
    const float w = 1.0f - pl_abs(d);
    return w > 0.0f ? w : 0.0f;
}

/* The lens weights' inverse widths (x, y) at depth coefficients c: 1, the paper's bilinear
 * weights; with PL_LENS_EXTENT the inverse of the voxel's width in lens indices (the row
 * sums of |G|), at least 1: a voxel narrower than a lens (a sub-voxel) shares a ray
 * between two lenses only where its extent straddles their cells' edge. */
inline float2 pl_lens_iw(__global const float *c)
{
#if PL_LENS_EXTENT
    const float wx = pl_abs(c[0]) + pl_abs(c[1]), wy = pl_abs(c[2]) + pl_abs(c[3]);
    return (float2)(wx < 1.0f ? 1.0f / wx : 1.0f, wy < 1.0f ? 1.0f / wy : 1.0f);
#else
    return (float2)(1.0f, 1.0f);
#endif
}

/* The upper lens's share of a point at k0 + t between lenses k0 and k0 + 1: the paper's
 * t; with PL_LENS_EXTENT the share of a box 1/iw wide centred there in lens k0 + 1's cell
 * [k0 + 1/2, k0 + 3/2] (t itself, to the bit, for iw = 1). */
inline float pl_lens_t(float t, float iw)
{
#if PL_LENS_EXTENT
    const float s = 0.5f + (t - 0.5f) * iw;
    return iw == 1.0f ? t : (s < 0.0f ? 0.0f : (s > 1.0f ? 1.0f : s));
#else
    return t;
#endif
}

/* A lens's weight at signed distance d from the point: pl_tent, or with PL_LENS_EXTENT
 * the share of the box in its cell (pl_lens_t's, from either side). */
inline float pl_lens_tent(float d, float iw)
{
#if PL_LENS_EXTENT
    const float s = 0.5f + (0.5f - pl_abs(d)) * iw;
    return iw == 1.0f ? pl_tent(d) : (s < 0.0f ? 0.0f : (s > 1.0f ? 1.0f : s));
#else
    return pl_tent(d);
#endif
}

/* Lens index of voxel (0, 0) through aperture sample offsets (bu, bv) = (i - c, j - c). */
inline float2 pl_sample_offset(__global const float *c, float bu, float bv)
{
    return (float2)(c[6] * bu + (c[7] * bv + c[4]), c[8] * bu + (c[9] * bv + c[5]));
}

/* Fractional lens index (kx, ky) of voxel (fx, fy) given its sample offset o. */
inline float2 pl_lens_coord(__global const float *c, float2 o, float fx, float fy)
{
    return (float2)(c[0] * fx + (c[1] * fy + o.x), c[2] * fx + (c[3] * fy + o.y));
}

/* Separable path: kx of voxel column ix at offset b = pl_kx_offset(c, bu, iy). */
inline float pl_kx_at(__global const float *c, float b, int ix)
{
    return c[0] * (float)ix + b;
}

/* Separable path: the kx of voxel column 0 of voxel row iy through aperture column offset
 * bu. A hexagonal array's lens columns lean across the rows (G's c[1], docs/design.md
 * §5.3), so the row shifts its lens columns by c[1] iy; H's c[7] is 0 by the aperture's
 * sampling. With c[1] = 0 (a rectangular array) this is c[6] bu + c[4] exactly, and in
 * every case the general path's sum in its own order (pl_lens_coord). */
inline float pl_kx_offset(__global const float *c, float bu, int iy)
{
    return c[1] * (float)iy + (c[6] * bu + c[4]);
}

/* Separable path: kx of voxel (ix, iy) through aperture column offset bu. */
inline float pl_kx(__global const float *c, float bu, int ix, int iy)
{
    return pl_kx_at(c, pl_kx_offset(c, bu, iy), ix);
}

/* Separable path: ky of voxel row iy through aperture row offset bv. */
inline float pl_ky(__global const float *c, float bv, int iy)
{
    return c[3] * (float)iy + (c[9] * bv + c[5]);
}

/* Inclusive index range [lo, hi] (one wider each side, clamped to [0, n - 1]) of the
 * integers m with |a m + b - k| < 1, given a_inv = 1/a. */
inline int2 pl_hat_range(float a_inv, float b, float k, int n)
{
    const float e0 = (k - 1.0f - b) * a_inv, e1 = (k + 1.0f - b) * a_inv;
    const int lo = pl_floori(e0 < e1 ? e0 : e1), hi = pl_ceili(e0 < e1 ? e1 : e0);
    return (int2)(pl_maxi(lo, 0), pl_mini(hi, n - 1));
}

/* out[0:n) = out + w0 a + w1 b over n vectors (rows aligned to PL_VW floats). */
inline void pl_axpy2(__global float *out, __global const float *a, __global const float *b,
                     float w0, float w1, int n)
{
    __global pl_vec *o = (__global pl_vec *)out;
    __global const pl_vec *va = (__global const pl_vec *)a;
    __global const pl_vec *vb = (__global const pl_vec *)b;
    const pl_vec s0 = (pl_vec)(w0), s1 = (pl_vec)(w1);
    for (int m = 0; m < n; ++m)
        o[m] = o[m] + s0 * va[m] + s1 * vb[m];
}

/* Plane z's voxel columns [x0, x1) of the extent below (all nx without PL_EXTENT). */
inline int2 pl_columns(__global const int2 *xr, int z, int nx)
{
    return PL_EXTENT ? xr[z] : (int2)(0, nx);
}

/* A volume known to be zero outside a lateral extent per plane (a posed camera's frame
 * grid, docs/design.md §5.5): plane z's voxel columns [xr.x, xr.y) and, for aperture
 * column i, the T-row vectors [span.x, span.y) that those columns reach (host:
 * plenocl/projection/extent.py; without PL_EXTENT every row is whole and no span is
 * read). This is the part of segment t (seg vectors from t seg) that the span holds,
 * from the segment's start. */
inline int2 pl_seg_span(__global const int2 *span, int ncols, int z, int i, int t, int seg)
{
    if (!PL_EXTENT)
        return (int2)(0, seg);
    const int2 s = span[z * ncols + i];
    return (int2)(pl_maxi(s.x - t * seg, 0), pl_mini(s.y - t * seg, seg));
}

inline void pl_zero(__global float *out, int n)
{
    __global pl_vec *o = (__global pl_vec *)out;
    for (int m = 0; m < n; ++m)
        o[m] = (pl_vec)(0.0f);
}

/* The 4 bilinear pixel taps (paper §III.A step 3) of an aperture sample that lands d
 * pixels from the image centre of a lens (c_k - u f_ml / d_p: -(u, v) f_ml/(d_p p_px),
 * d_p the exit pupil's distance from the array; one float2 per sample from the host, rotated into the sensor's axes when the
 * reconstruction frame is rotated) whose centre lies at rounded pixel r plus remainder f:
 * flat pixel indices (-1 off the sensor or for a missing lens) and weights (0 there). */
inline void pl_pixel_taps(int2 r, float2 f, float2 d, int width, int height, int *idx,
                          float *w)
{
    const float fc = f.x + d.x, fr = f.y + d.y;
    const int c0 = pl_floori(fc), r0 = pl_floori(fr);
    const float tc = fc - (float)c0, tr = fr - (float)r0;
    for (int b = 0; b < 4; ++b) {
        const int col = r.x + c0 + (b & 1), row = r.y + r0 + (b >> 1);
        const float wp = ((b & 1) ? tc : 1.0f - tc) * ((b >> 1) ? tr : 1.0f - tr);
        const int ok = r.x != PL_NO_LENS && col >= 0 && col < width && row >= 0
                       && row < height;
        idx[b] = ok ? row * width + col : -1;
        w[b] = ok ? wp : 0.0f;
    }
}

/* The 16 products (paper §III.A steps 2-3) of one aperture sample of a voxel whose
 * sample meets the array at fractional lens index p. idx[e] = -1 for lost products. */
inline void pl_sample_products(float2 p, float2 d, float2 iw,
                               __global const int2 *lens_rnd, __global const float2 *lens_frac,
                               int nkx, int nky, int width, int height, int *idx, float *w)
{
    const int fx = pl_floori(p.x), fy = pl_floori(p.y);
    const float tx = pl_lens_t(p.x - (float)fx, iw.x), ty = pl_lens_t(p.y - (float)fy, iw.y);
    for (int a = 0; a < 4; ++a) {
        const int kx = fx + (a & 1), ky = fy + (a >> 1);
        const float wl = ((a & 1) ? tx : 1.0f - tx) * ((a >> 1) ? ty : 1.0f - ty);
        int2 r = (int2)(PL_NO_LENS, PL_NO_LENS);
        float2 f = (float2)(0.0f, 0.0f);
        if (kx >= 0 && kx < nkx && ky >= 0 && ky < nky) {
            r = lens_rnd[ky * nkx + kx];
            f = lens_frac[ky * nkx + kx];
        }
        pl_pixel_taps(r, f, d, width, height, idx + 4 * a, w + 4 * a);
        for (int b = 0; b < 4; ++b)
            w[4 * a + b] *= wl;
    }
}

#endif /* PLENOCL_PROJECTOR_H */
