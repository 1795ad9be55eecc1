/* Matrix-free projector of the plenoptic weighting function (paper §III.A, docs/design.md
 * §5). NumPy twin: plenocl/reference/weights.py.
 *
 * The weight of pixel p for voxel j is a sum over aperture samples s and lenses k of
 * S[k, s; j] P[p; k, s]: S holds the bilinear lens weights of step 2 (they depend on the
 * voxel), P the bilinear pixel weights of step 3 (they depend only on the lens, with its
 * own calibrated centre, and the sample: the host's sample_px table gives where each
 * sample lands behind a lens). Both projections go through the light field
 * L[ky][s][kx] (rows padded to nkxp, a multiple of the vector width PL_VW):
 *   forward  image = P (S vol):  fwd_x + fwd_y (separable S) or fwd_gen / fwd_gen_gather,
 *                                then fwd_pix
 *   back     vol = S^T (P^T img): back_pix, then back_y (or back_y_scatter) + back_x,
 *                                or back_gen
 * In the grid's frame (docs/design.md §5: a frame that follows the lens rows) S
 * factorises per axis: fwd_x resamples voxel rows onto lens columns for each aperture
 * column i (T[(iz, i)][iy][kx]); fwd_y resamples those onto lens rows for each sample
 * (i, j), a few vectorised row updates per output row.
 *
 * Parallel structure (each kernel's own comment gives its work-item): every kernel is a
 * gather over thousands of independent outputs, or a race-free scatter that owns its
 * output (fwd_x: a T row; fwd_gen: a sample's plane; fwd_pix: one colour class of lenses
 * cs apart, whose pixel patches never overlap), so results do not depend on the work
 * split or the device's thread count. Two kernels use float atomics and are not the
 * default: back_y_scatter (Projector(back="atomic"), a scatter of each light-field row)
 * and fwd_direct (the unfactorised benchmark baseline). fwd_gen has one work-item per
 * aperture sample, enough for a CPU; GPUs run fwd_gen_gather, one per light-field element.
 * Sizes are arguments; PL_VW is a define. Row kernels take `seg`: each work-item updates
 * `seg` vectors of a row (a whole row on a CPU, so it stays in cache; one element on a
 * GPU, for coalesced access).
 *
 * The separable kernels take a plane extent (xr: each plane's voxel columns [x0, x1);
 * span: per plane and aperture column, the T-row vectors those columns reach; plenocl/
 * projection/extent.py): a posed camera's frame grid is 0 beyond its tilted band, so
 * fwd_x_row splats the band's voxels, fwd_y and back_y update the spans' vectors, back_x
 * computes the band's voxels (0 beyond), each adding what it adds without an extent in
 * the same order. Those kernels are built with PL_EXTENT; a projector's own extent is the
 * whole grid, run by its kernels built without it, which read no extent.
 *
 * The direct kernels (voxel_footprint, fwd_direct, back_direct) evaluate the 16 products
 * per sample per voxel without the factorisation: one voxel's column, and the
 * unfactorised baseline the benchmark measures. */
#include "projector.h"

/* ---- forward, separable, element form (GPUs; CPUs run fwd_x_row below):
 * T[(izl, il)][iy][kx] = sum_ix hat(kx(ix, i) - kx) vol[iz][iy][ix].
 * One work-item per T element (kx, iy, (izl, il)): it sums the few voxels of its row
 * whose lens coordinate lies within one lens of kx (pl_hat_range), with the weights
 * fwd_x_row and back_x compute, so the transposes stay exact. Consecutive work-items
 * are consecutive kx of one row: a CPU driver vectorises across them, a GPU coalesces
 * the writes; no work-item writes another's output. Padding (kx >= nkx) is written 0. */
__kernel void fwd_x(__global const float *restrict vol, __global float *restrict T,
                    __global const float *restrict coef,
                    int nx, int ny, int nkx, int nkxp, int zv0, int zc0, int i0, int nic,
                    float ic, __global const int2 *restrict xr,
                    __global const int2 *restrict span, int ncols)
{
    const int kx = get_global_id(0), iy = get_global_id(1), q = get_global_id(2);
    if (kx >= nkxp) return;
    const int izl = q / nic, i = i0 + q - izl * nic;
    __global const float *c = coef + 16 * (zc0 + izl);
    const float bu = (float)i - ic;
    __global const float *row = vol + ((size_t)(zc0 + izl - zv0) * ny + iy) * nx;
    const int2 sp = pl_seg_span(span, ncols, zc0 + izl, i, 0, nkxp / PL_VW);
    float acc = 0.0f;
    if (kx < nkx && kx >= sp.x * PL_VW && kx < sp.y * PL_VW) {  /* else 0: beyond the extent */
        const float b = pl_kx_offset(c, bu, iy);
        const float iw = pl_lens_iw(c).x;
        const int2 r = pl_hat_range(c[10], b, (float)kx, nx);
        for (int ix = r.x; ix <= r.y; ++ix) {
            const float kxf = pl_kx_at(c, b, ix);
            const int kx0 = pl_floori(kxf);
            const float tx = pl_lens_t(kxf - (float)kx0, iw);
            const float w = kx0 == kx ? 1.0f - tx : (kx0 + 1 == kx ? tx : 0.0f);
            acc += w * row[ix];
        }
    }
    T[((size_t)q * ny + iy) * nkxp + kx] = acc;
}

/* ---- forward, separable, row form (CPUs): the same T, one work-item per voxel row
 * (iy, izl) and every aperture column: the row's non-zero voxels, read once and listed
 * (PL_XLIST at a time), splat onto their two lens columns of each column's T row, column
 * by column (the row's T rows stay in cache): a vectorisable loop over the list gives
 * their lens columns and weights, then the splats follow in the row's order, each T
 * element's sum in the order of before (1.4x faster than voxel by voxel on the paper's
 * sparse sub-voxels, 2x on its dense voxels). */
__kernel void fwd_x_row(__global const float *restrict vol, __global float *restrict T,
                    __global const float *restrict coef,
                    int nx, int ny, int nkx, int nkxp, int zv0, int zc0, int i0, int nic,
                    float ic, __global const int2 *restrict xr,
                    __global const int2 *restrict span, int ncols)
{
    const int iy = get_global_id(0), izl = get_global_id(1);
    const int2 cols = pl_columns(xr, zc0 + izl, nx);  /* the row's voxels beyond them are 0 */
    __global const float *c = coef + 16 * (zc0 + izl);
    __global const float *row = vol + ((size_t)(zc0 + izl - zv0) * ny + iy) * nx;
    __global float *base = T + ((size_t)izl * nic * ny + iy) * nkxp;
    const size_t stride = (size_t)ny * nkxp;  /* from one column's T row to the next */
    const float iw = pl_lens_iw(c).x;
    for (int il = 0; il < nic; ++il) {  /* the spans (fwd_y reads nothing beyond) */
        const int2 m = pl_seg_span(span, ncols, zc0 + izl, i0 + il, 0, nkxp / PL_VW);
        if (m.y > m.x) pl_zero(base + il * stride + m.x * PL_VW, m.y - m.x);
    }
    int idx[PL_XLIST], k0[PL_XLIST];  /* the row's non-zero voxels (sparse volumes: */
    float val[PL_XLIST], t[PL_XLIST];  /* most are zero), PL_XLIST at a time */
    for (int ix = cols.x; ix < cols.y;) {
        int n = 0;
        for (; ix < cols.y && n < PL_XLIST; ++ix) {
            const float e = row[ix];
            if (e != 0.0f) {
                idx[n] = ix;
                val[n++] = e;
            }
        }
        for (int il = 0; il < nic; ++il) {  /* column by column: their lens columns and */
            const float bu = (float)(i0 + il) - ic;  /* weights (a vectorisable loop), */
            for (int k = 0; k < n; ++k) {  /* then the splats in the row's order */
                const float kxf = pl_kx(c, bu, idx[k], iy);
                k0[k] = pl_floori(kxf);
                t[k] = pl_lens_t(kxf - (float)k0[k], iw);
            }
            __global float *out = base + il * stride;
            for (int k = 0; k < n; ++k) {
                const int kx0 = k0[k];
                const float tx = t[k], e = val[k];
                if (kx0 >= 0 && kx0 < nkx) out[kx0] += (1.0f - tx) * e;
                if (kx0 + 1 >= 0 && kx0 + 1 < nkx) out[kx0 + 1] += tx * e;
            }
        }
    }
}

/* ---- forward, separable:
 * L[ky][s(i, j)][kx] (+)= sum_iz,iy hat(ky(iy, j) - ky) T[(izl, il)][iy][kx].
 * One work-item per (segment, ky, aperture column i): it owns the L rows of the column's
 * samples (kept in cache) and reads each T row once per depth for all of them.
 * With PL_SCALAR_ROWS (a GPU's layout: one element per segment) it owns one element of
 * each of those rows and sums each in a register over every depth, aperture row by
 * aperture row, writing it once: the same terms in the same order as the depth-by-depth
 * form (which reads and writes every L element once per depth through global memory). */
/* The next pair of voxel rows under lens row ky's hat at aperture row offset bv, from row
 * *iy on (within r, pl_hat_range's): rows a, b with weights wa, wb (a row left without a
 * partner comes as b = a, wb = 0); 0 when none is left. Both forms of fwd_y add the
 * pairs in this order. */
inline int pl_fwd_y_pair(__global const float *c, float bv, int ky, float iwy, int2 r,
                         int *iy, int *a, int *b, float *wa, float *wb)
{
    int pending = -1;  /* a row with a positive weight waiting for a partner */
    float wp = 0.0f;
    for (; *iy <= r.y + 1; ++*iy) {
        const int y = *iy;
        const float w = y <= r.y ? pl_lens_tent(pl_ky(c, bv, y) - (float)ky, iwy) : 0.0f;
        if (w <= 0.0f && !(y > r.y && pending >= 0)) continue;
        if (pending < 0) {
            pending = y;
            wp = w;
            continue;
        }
        *a = pending;
        *wa = wp;
        *b = w > 0.0f ? y : pending;
        *wb = w;
        ++*iy;
        return 1;
    }
    return 0;
}

#if PL_SCALAR_ROWS
/* One L element's sum over the depths of the chunk: acc + its weighted T elements. */
inline float pl_fwd_y_sum(__global const float *T, __global const float *coef, float acc,
                          __global const int2 *span, int ncols, int ny, int nkxp, int zc0,
                          int nzc, int i, int il, int nic, int t, size_t off, int ky, float bv)
{
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        const int2 m = pl_seg_span(span, ncols, zc0 + izl, i, t, 1);  /* T's lit part */
        if (m.y <= m.x) continue;
        const float iwy = pl_lens_iw(c).y;
        __global const float *src = T + (size_t)(izl * nic + il) * ny * nkxp + off;
        const int2 r = pl_hat_range(c[13], c[9] * bv + c[5], (float)ky, ny);
        int iy = r.x, a, b;
        float wa, wb;
        while (pl_fwd_y_pair(c, bv, ky, iwy, r, &iy, &a, &b, &wa, &wb))
            acc = acc + wa * src[(size_t)a * nkxp] + wb * src[(size_t)b * nkxp];
    }
    return acc;
}
#endif

__kernel void fwd_y(__global const float *restrict T, __global float *restrict L,
                    __global const float *restrict coef, __global const int *restrict col_lo,
                    __global const int *restrict col_hi, __global const int *restrict col_off,
                    __global const uchar *restrict rows_lit,
                    int ny, int nkxp, int seg, int zc0, int nzc, int i0, int nic, int s0,
                    int nsc, float ic, int accumulate, __global const int2 *restrict span,
                    int ncols)
{
    const int t = get_global_id(0), ky = get_global_id(1), il = get_global_id(2);
    if (!rows_lit[ky]) return;  /* no listed lens: fwd_pix never reads this row */
    const int i = i0 + il, lo = col_lo[i], hi = col_hi[i];
    const size_t off = (size_t)t * seg * PL_VW;
    __global float *rows = L + ((size_t)ky * nsc + col_off[i] - s0) * nkxp + off;
#if PL_SCALAR_ROWS
    for (int j = lo; j <= hi; ++j) {
        __global float *out = rows + (size_t)(j - lo) * nkxp;
        *out = pl_fwd_y_sum(T, coef, accumulate ? *out : 0.0f, span, ncols, ny, nkxp, zc0,
                            nzc, i, il, nic, t, off, ky, (float)j - ic);
    }
#else
    if (!accumulate)
        for (int j = lo; j <= hi; ++j)
            pl_zero(rows + (size_t)(j - lo) * nkxp, seg);
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        const float iwy = pl_lens_iw(c).y;
        const int2 m = pl_seg_span(span, ncols, zc0 + izl, i, t, seg);  /* T's lit part */
        if (m.y <= m.x) continue;
        const size_t mo = (size_t)m.x * PL_VW;
        __global const float *src = T + (size_t)(izl * nic + il) * ny * nkxp + off + mo;
        for (int j = lo; j <= hi; ++j) {
            const float bv = (float)j - ic;
            const int2 r = pl_hat_range(c[13], c[9] * bv + c[5], (float)ky, ny);
            __global float *out = rows + (size_t)(j - lo) * nkxp + mo;
            int iy = r.x, a, b;
            float wa, wb;
            while (pl_fwd_y_pair(c, bv, ky, iwy, r, &iy, &a, &b, &wa, &wb))
                pl_axpy2(out, src + (size_t)a * nkxp, src + (size_t)b * nkxp, wa, wb,
                         m.y - m.x);
        }
    }
#endif
}

/* ---- forward, general (a sheared array, or a grid not in the lens rows' frame):
 * L[ky][sl][kx] (+)= sum_iz,iy,ix S vol. One work-item per aperture sample: it owns the
 * sample's light-field plane and splats every non-zero voxel of the chunk onto its four
 * lenses (race-free, in cache). A CPU runs a few hundred such items well; a GPU needs
 * more parallelism and runs fwd_gen_gather instead. */
__kernel void fwd_gen(__global const float *restrict vol, __global float *restrict L,
                      __global const float *restrict coef,
                      __global const int2 *restrict sample_ij,
                      int nx, int ny, int nkx, int nky, int nkxp, int zv0, int zc0, int nzc,
                      int s0, int nsc, float ic, int accumulate)
{
    const int sl = get_global_id(0);
    const int2 ij = sample_ij[s0 + sl];
    const float bu = (float)ij.x - ic, bv = (float)ij.y - ic;
    __global float *plane = L + (size_t)sl * nkxp;
    const size_t stride = (size_t)nsc * nkxp;  /* from one lens row to the next */
    if (!accumulate)
        for (int ky = 0; ky < nky; ++ky)
            pl_zero(plane + ky * stride, nkxp / PL_VW);
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        const float2 o = pl_sample_offset(c, bu, bv), iw = pl_lens_iw(c);
        __global const float *slice = vol + (size_t)(zc0 + izl - zv0) * ny * nx;
        for (int iy = 0; iy < ny; ++iy)
            for (int ix = 0; ix < nx; ++ix) {
                const float e = slice[(size_t)iy * nx + ix];
                if (e == 0.0f) continue;  /* sparse volumes: most voxels are zero */
                const float2 p = pl_lens_coord(c, o, (float)ix, (float)iy);
                const int kx = pl_floori(p.x), ky = pl_floori(p.y);
                const float dx = pl_lens_t(p.x - (float)kx, iw.x);
                const float dy = pl_lens_t(p.y - (float)ky, iw.y);
                const int x0 = pl_mini(pl_maxi(kx, 0), nkx - 1);
                const int x1 = pl_mini(pl_maxi(kx + 1, 0), nkx - 1);
                const int y0 = pl_mini(pl_maxi(ky, 0), nky - 1);
                const int y1 = pl_mini(pl_maxi(ky + 1, 0), nky - 1);
                const float ex0 = x0 == kx ? (1.0f - dx) * e : 0.0f;
                const float ex1 = x1 == kx + 1 ? dx * e : 0.0f;
                const float wy0 = y0 == ky ? 1.0f - dy : 0.0f, wy1 = y1 == ky + 1 ? dy : 0.0f;
                __global float *r0 = plane + y0 * stride, *r1 = plane + y1 * stride;
                r0[x0] += wy0 * ex0;
                r0[x1] += wy0 * ex1;
                r1[x0] += wy1 * ex0;
                r1[x1] += wy1 * ex1;
            }
    }
}

/* ---- forward, general, as a gather (GPUs): L[ky][sl][kx] (+)= sum_iz,iy,ix S vol.
 * One work-item per light-field element (lens kx, ky; sample sl): it visits the voxels of
 * the inverse image of its lens's [-1, 1]^2 box (coef[10..15]) depth by depth and sums
 * them in the voxel order fwd_gen uses, with the same weight expressions, so both give
 * the same light field bit for bit. Fully parallel, no atomics; it reads every voxel of
 * the box where fwd_gen skips zero voxels, so CPUs keep fwd_gen. */
__kernel void fwd_gen_gather(__global const float *restrict vol, __global float *restrict L,
                             __global const float *restrict coef,
                             __global const int2 *restrict sample_ij,
                             int nx, int ny, int nkx, int nky, int nkxp, int zv0, int zc0,
                             int nzc, int s0, int nsc, float ic, int accumulate)
{
    const int kx = get_global_id(0), ky = get_global_id(1), sl = get_global_id(2);
    if (kx >= nkx) return;
    const int2 ij = sample_ij[s0 + sl];
    const float bu = (float)ij.x - ic, bv = (float)ij.y - ic;
    __global float *out = L + ((size_t)ky * nsc + sl) * nkxp + kx;
    float acc = accumulate ? *out : 0.0f;
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        const float2 o = pl_sample_offset(c, bu, bv), iw = pl_lens_iw(c);
        const float rx = (float)kx - o.x, ry = (float)ky - o.y;
        const float fx = c[10] * rx + c[11] * ry, fy = c[12] * rx + c[13] * ry;
        const int xa = pl_maxi(pl_floori(fx - c[14] - 1e-3f), 0);
        const int xb = pl_mini(pl_ceili(fx + c[14] + 1e-3f), nx - 1);
        const int ya = pl_maxi(pl_floori(fy - c[15] - 1e-3f), 0);
        const int yb = pl_mini(pl_ceili(fy + c[15] + 1e-3f), ny - 1);
        __global const float *slice = vol + (size_t)(zc0 + izl - zv0) * ny * nx;
        for (int iy = ya; iy <= yb; ++iy)
            for (int ix = xa; ix <= xb; ++ix) {
                const float e = slice[(size_t)iy * nx + ix];
                if (e == 0.0f) continue;
                const float2 p = pl_lens_coord(c, o, (float)ix, (float)iy);
                const int fkx = pl_floori(p.x), fky = pl_floori(p.y);
                const float dx = pl_lens_t(p.x - (float)fkx, iw.x);
                const float dy = pl_lens_t(p.y - (float)fky, iw.y);
                const float ex = kx == fkx ? (1.0f - dx) * e : (kx == fkx + 1 ? dx * e : 0.0f);
                const float wy = ky == fky ? 1.0f - dy : (ky == fky + 1 ? dy : 0.0f);
                if (ex != 0.0f && wy != 0.0f) acc += wy * ex;
            }
    }
    *out = acc;
}

/* ---- forward, P: image (+)= scale * L of the listed lenses lens_ids[id0 + g] of one
 * colour class (lenses cs apart never share a pixel: race-free). Listing only the lenses
 * that see light (plenocl/lenses.py) skips the dark ones. */
__kernel void fwd_pix(__global const float *restrict L, __global float *restrict image,
                      __global const int *restrict lens_ids, int id0,
                      __global const int2 *restrict lens_rnd,
                      __global const float2 *restrict lens_frac,
                      __global const float2 *restrict sample_px,
                      int width, int height, int nkx, int nkxp, int s0, int ns, float scale)
{
    const int k = lens_ids[id0 + get_global_id(0)];
    const int ky = k / nkx, kx = k - ky * nkx;
    const int2 r = lens_rnd[k];
    const float2 f = lens_frac[k];
    __global const float *src = L + (size_t)ky * ns * nkxp + kx;
    for (int sl = 0; sl < ns; ++sl) {
        const float val = src[(size_t)sl * nkxp] * scale;
        if (val == 0.0f) continue;
        int idx[4];
        float w[4];
        pl_pixel_taps(r, f, sample_px[s0 + sl], width, height, idx, w);
        for (int b = 0; b < 4; ++b)
            if (idx[b] >= 0) image[idx[b]] += w[b] * val;
    }
}

/* ---- back, P^T: L[ky][sl][kx] = scale * sum of the 4 pixels of sample s behind lens k,
 * for the listed lenses k = lens_ids[g0] and samples [g1 sps, (g1 + 1) sps). The light
 * field is zeroed first: unlisted lenses (dark, missing, padding) stay 0. */
__kernel void back_pix(__global const float *restrict image, __global float *restrict L,
                       __global const int *restrict lens_ids,
                       __global const int2 *restrict lens_rnd,
                       __global const float2 *restrict lens_frac,
                       __global const float2 *restrict sample_px,
                       int width, int height, int nkx, int nkxp, int s0, int nsc, int sps,
                       float scale)
{
    const int k = lens_ids[get_global_id(0)];
    const int ky = k / nkx, kx = k - ky * nkx;
    const int sa = get_global_id(1) * sps, sb = pl_mini(sa + sps, nsc);
    const int2 r = lens_rnd[k];
    const float2 f = lens_frac[k];
    __global float *out = L + (size_t)ky * nsc * nkxp + kx;
    for (int sl = sa; sl < sb; ++sl) {
        int idx[4];
        float w[4];
        pl_pixel_taps(r, f, sample_px[s0 + sl], width, height, idx, w);
        float acc = 0.0f;
        for (int b = 0; b < 4; ++b)
            if (idx[b] >= 0) acc += w[b] * image[idx[b]];
        out[(size_t)sl * nkxp] = acc * scale;
    }
}

/* ---- back, separable: T[(izl, il)][iy][kx] = sum_j,ky hat(ky(iy, j) - ky) L[ky][s(i, j)][kx].
 * One work-item per (segment, iy, aperture column i), for every depth of the chunk: the
 * L rows it reads (near ky(iy)) stay in cache from one depth to the next. With
 * PL_SCALAR_ROWS (a GPU's layout: one element per segment) each depth's T element is
 * summed over the aperture rows in a register and written once (the same order).
 * With PL_BACK_ALLCOLS (CPUs, whole rows): one work-item per voxel row iy for every
 * column and depth of the chunk (global size (1, ny, 1)). It lists the weights of each
 * (aperture row j, depth) once for all columns (they depend on neither), j by j and depth
 * fastest, and applies them column by column: the depths of one j mostly read the same two
 * L rows, which stay in L1. Each T row gets the same terms in the same order (j) as in
 * the per-column form, so both give the same T bit for bit. */
/* Voxel row iy's two lens-row taps for aperture row offset bv at depth coefficients c:
 * rows ka, kb (clamped to the array) with weights w0, w1. Returns 0 when the row adds
 * nothing (both weights 0, or both rows dark). Both forms of back_y use it, so they add
 * the same terms. */
inline int pl_back_y_taps(__global const float *c, float bv, int iy, int nky,
                          __global const uchar *rows_lit, int *ka, int *kb, float *w0,
                          float *w1)
{
    const float kyf = pl_ky(c, bv, iy);
    const int ky0 = pl_floori(kyf);
    const float ty = pl_lens_t(kyf - (float)ky0, pl_lens_iw(c).y);
    *w0 = ky0 < 0 || ky0 >= nky ? 0.0f : 1.0f - ty;
    *w1 = ky0 + 1 < 0 || ky0 + 1 >= nky ? 0.0f : ty;
    if (*w0 == 0.0f && *w1 == 0.0f) return 0;
    *ka = pl_mini(pl_maxi(ky0, 0), nky - 1);
    *kb = pl_mini(pl_maxi(ky0 + 1, 0), nky - 1);
    return rows_lit[*ka] || rows_lit[*kb];
}

#if PL_BACK_ALLCOLS
__kernel void back_y(__global const float *restrict L, __global float *restrict T,
                     __global const float *restrict coef, __global const int *restrict col_lo,
                     __global const int *restrict col_hi, __global const int *restrict col_off,
                     __global const uchar *restrict rows_lit,
                     int ny, int nky, int nkxp, int seg, int zc0, int nzc, int i0, int nic,
                     int s0, int nsc, float ic, __global const int2 *restrict span, int ncols)
{
    const int t = get_global_id(0), iy = get_global_id(1);
    const size_t off = (size_t)t * seg * PL_VW;
    int jmin = 1 << 30, jmax = -1;  /* the aperture rows of the chunk's columns */
    for (int il = 0; il < nic; ++il) {
        if (col_hi[i0 + il] < col_lo[i0 + il]) continue;  /* a column without samples */
        jmin = pl_mini(jmin, col_lo[i0 + il]);
        jmax = pl_maxi(jmax, col_hi[i0 + il]);
    }
    const size_t ostride = (size_t)ny * nkxp;  /* from one column's T row to the next */
    __global float *out = T + (size_t)iy * nkxp + off;  /* (izl, il): + (izl nic + il) */
    for (int q = 0; q < nzc * nic; ++q) {  /* the spans (back_x reads nothing beyond) */
        const int2 m = pl_seg_span(span, ncols, zc0 + q / nic, i0 + q % nic, t, seg);
        if (m.y > m.x) pl_zero(out + q * ostride + m.x * PL_VW, m.y - m.x);
    }
    int je[PL_PAIRS], ez[PL_PAIRS], ia[PL_PAIRS], ib[PL_PAIRS], es[PL_PAIRS];
    float wa[PL_PAIRS], wb[PL_PAIRS];
    __global const int2 *spans = span + i0;  /* (plane, column i0 + il): es + il */
    for (int j = jmin, izl = 0; j <= jmax;) {
        int cnt = 0;  /* list (j, depth) pairs, depth fastest: a column's L rows stay in L1 */
        for (; j <= jmax && cnt < PL_PAIRS; izl = izl + 1 < nzc ? izl + 1 : 0, j += izl == 0) {
            int ka, kb;
            float w0, w1;
            if (!pl_back_y_taps(coef + 16 * (zc0 + izl), (float)j - ic, iy, nky, rows_lit,
                                &ka, &kb, &w0, &w1))
                continue;
            je[cnt] = j;
            ez[cnt] = izl * nic;
            es[cnt] = (zc0 + izl) * ncols;
            ia[cnt] = ka * nsc + j;  /* L row of (ka, j) less the column's offset */
            ib[cnt] = kb * nsc + j;
            wa[cnt] = w0;
            wb[cnt++] = w1;
        }
        for (int il = 0; il < nic; ++il) {
            const int i = i0 + il, lo = col_lo[i], hi = col_hi[i];
            __global const float *col = L + (long)(col_off[i] - s0 - lo) * nkxp + off;
            for (int e = 0; e < cnt; ++e) {
                if (je[e] < lo || je[e] > hi)
                    continue;
                /* the T row's part that the extent's voxels read (the rest stays 0); a
                 * CPU's row is one segment (t = 0) */
                const int2 m = PL_EXTENT ? spans[es[e] + il] : (int2)(0, seg);
                pl_axpy2(out + (ez[e] + il) * ostride + m.x * PL_VW,
                         col + (size_t)ia[e] * nkxp + m.x * PL_VW,
                         col + (size_t)ib[e] * nkxp + m.x * PL_VW, wa[e], wb[e], m.y - m.x);
            }
        }
    }
}
#else
__kernel void back_y(__global const float *restrict L, __global float *restrict T,
                     __global const float *restrict coef, __global const int *restrict col_lo,
                     __global const int *restrict col_hi, __global const int *restrict col_off,
                     __global const uchar *restrict rows_lit,
                     int ny, int nky, int nkxp, int seg, int zc0, int nzc, int i0, int nic,
                     int s0, int nsc, float ic, __global const int2 *restrict span, int ncols)
{
    const int t = get_global_id(0), iy = get_global_id(1), il = get_global_id(2);
    const int i = i0 + il, lo = col_lo[i], hi = col_hi[i];
    const size_t off = (size_t)t * seg * PL_VW;
    __global const float *col = L + (size_t)(col_off[i] - s0) * nkxp + off;
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        __global float *out = T + ((size_t)(izl * nic + il) * ny + iy) * nkxp + off;
        const int2 m = pl_seg_span(span, ncols, zc0 + izl, i, t, seg);  /* what back_x reads */
        if (m.y <= m.x) continue;
#if PL_SCALAR_ROWS  /* one element: summed in a register, written once (same order) */
        float acc = 0.0f;
        for (int j = lo; j <= hi; ++j) {
            int ka, kb;
            float w0, w1;
            if (!pl_back_y_taps(c, (float)j - ic, iy, nky, rows_lit, &ka, &kb, &w0, &w1))
                continue;
            __global const float *src = col + (size_t)(j - lo) * nkxp;
            acc = acc + w0 * src[(size_t)ka * nsc * nkxp] + w1 * src[(size_t)kb * nsc * nkxp];
        }
        *out = acc;
#else
        pl_zero(out + m.x * PL_VW, m.y - m.x);
        for (int j = lo; j <= hi; ++j) {
            int ka, kb;
            float w0, w1;
            if (!pl_back_y_taps(c, (float)j - ic, iy, nky, rows_lit, &ka, &kb, &w0, &w1))
                continue;
            __global const float *src = col + (size_t)(j - lo) * nkxp + m.x * PL_VW;
            pl_axpy2(out + m.x * PL_VW, src + (size_t)ka * nsc * nkxp,
                     src + (size_t)kb * nsc * nkxp, w0, w1, m.y - m.x);
        }
#endif
    }
}
#endif

/* Voxel (ix, iy)'s two lens taps in the T row of aperture column offset bu. */
inline float pl_back_x_tap(__global const float *c, __global const float *row, float bu,
                           int ix, int iy, int nkx, float iw)
{
    const float kxf = pl_kx(c, bu, ix, iy);
    const int kx0 = pl_floori(kxf);
    const float tx = pl_lens_t(kxf - (float)kx0, iw);
    const int k0 = pl_mini(pl_maxi(kx0, 0), nkx - 1);
    const int k1 = pl_mini(pl_maxi(kx0 + 1, 0), nkx - 1);
    const float w0 = kx0 == k0 ? 1.0f - tx : 0.0f, w1 = kx0 + 1 == k1 ? tx : 0.0f;
    return w0 * row[k0] + w1 * row[k1];
}

/* v + the taps of voxel ix in the T rows of every aperture column (base + il * stride),
 * column by column: the order both back_x forms sum in. */
inline float pl_back_x_sum(__global const float *c, __global const float *base,
                           size_t stride, int ix, int iy, int nkx, int i0, int nic, float ic,
                           float v)
{
    const float iw = pl_lens_iw(c).x;
    for (int il = 0; il < nic; ++il)
        v += pl_back_x_tap(c, base + (size_t)il * stride, (float)(i0 + il) - ic, ix, iy, nkx,
                           iw);
    return v;
}

/* ---- back, separable: vol[iz][iy][ix] (+)= sum_il,kx hat(kx(ix, i) - kx) T[(izl, il)][iy][kx].
 * With use_support, voxels whose support value is 0 may be skipped (0, or left as they
 * are when accumulating): a multiplicative update keeps a zero voxel at zero whatever its
 * back projection, so a sparse volume pays for its non-zero voxels only.
 * back_x (GPUs): one work-item per voxel (ix, iy, izl), consecutive work-items along a
 * row (coalesced). back_x_row (CPUs): one work-item per volume row, column by column
 * (a vectorisable loop along the row, in cache), or, for a row whose support is mostly
 * zero, over a list of its non-zero voxels (PL_XLIST at a time), column by column too
 * (a vectorisable loop over the list: 2.4x the voxel-by-voxel sums it replaced on the
 * paper's sub-voxels; a dense row computes every voxel: that is faster). Every form sums
 * in the same order. */
__kernel void back_x(__global const float *restrict T, __global float *restrict vol,
                     __global const float *restrict coef, __global const float *restrict sup,
                     int use_support, int nx, int ny, int nkx, int nkxp, int zv0, int zc0,
                     int i0, int nic, float ic, int accumulate,
                     __global const int2 *restrict xr)
{
    const int ix = get_global_id(0), iy = get_global_id(1), izl = get_global_id(2);
    if (ix >= nx) return;
    const size_t at = ((size_t)(zc0 + izl - zv0) * ny + iy) * nx + ix;
    const int2 cols = pl_columns(xr, zc0 + izl, nx);
    if ((use_support && sup[at] == 0.0f) || ix < cols.x || ix >= cols.y) {
        if (!accumulate) vol[at] = 0.0f;
        return;
    }
    __global const float *base = T + (size_t)izl * nic * ny * nkxp + (size_t)iy * nkxp;
    vol[at] = pl_back_x_sum(coef + 16 * (zc0 + izl), base, (size_t)ny * nkxp, ix, iy, nkx,
                            i0, nic, ic, accumulate ? vol[at] : 0.0f);
}

__kernel void back_x_row(__global const float *restrict T, __global float *restrict vol,
                         __global const float *restrict coef, __global const float *restrict sup,
                         int use_support, int nx, int ny, int nkx, int nkxp, int zv0, int zc0,
                         int i0, int nic, float ic, int accumulate,
                         __global const int2 *restrict xr)
{
    const int iy = get_global_id(0), izl = get_global_id(1);
    __global const float *c = coef + 16 * (zc0 + izl);
    const size_t at = ((size_t)(zc0 + izl - zv0) * ny + iy) * nx;
    __global float *out = vol + at;
    __global const float *s = sup + at;
    __global const float *base = T + (size_t)izl * nic * ny * nkxp + (size_t)iy * nkxp;
    const int2 cols = pl_columns(xr, zc0 + izl, nx);  /* beyond them: 0 (or left, accumulating) */
    if (!accumulate) {
        for (int ix = 0; ix < cols.x; ++ix) out[ix] = 0.0f;
        for (int ix = cols.y; ix < nx; ++ix) out[ix] = 0.0f;
    }
    int lit = 0;
    if (use_support)
        for (int ix = cols.x; ix < cols.y; ++ix) lit += s[ix] != 0.0f;
    const float iw = pl_lens_iw(c).x;
    if (use_support && 2 * lit < cols.y - cols.x) {  /* sparse: the non-zero voxels only */
        int idx[PL_XLIST];  /* up to PL_XLIST of them at a time, listed, then column by */
        float acc[PL_XLIST];  /* column: a vectorisable loop over the list */
        for (int ix = cols.x; ix < cols.y;) {
            int n = 0;
            for (; ix < cols.y && n < PL_XLIST; ++ix) {
                if (s[ix] != 0.0f) {
                    idx[n] = ix;
                    acc[n++] = accumulate ? out[ix] : 0.0f;
                } else if (!accumulate) {
                    out[ix] = 0.0f;
                }
            }
            for (int il = 0; il < nic; ++il) {
                const float bu = (float)(i0 + il) - ic;
                __global const float *row = base + (size_t)il * ny * nkxp;
                for (int k = 0; k < n; ++k)
                    acc[k] += pl_back_x_tap(c, row, bu, idx[k], iy, nkx, iw);
            }
            for (int k = 0; k < n; ++k)
                out[idx[k]] = acc[k];
        }
        return;
    }
    for (int il = 0; il < nic; ++il) {  /* column by column: a vectorisable row loop */
        const float bu = (float)(i0 + il) - ic;
        const int keep = accumulate || il > 0;
        __global const float *row = base + (size_t)il * ny * nkxp;
        for (int ix = cols.x; ix < cols.y; ++ix) {
            const float v = pl_back_x_tap(c, row, bu, ix, iy, nkx, iw);
            out[ix] = keep ? out[ix] + v : v;
        }
    }
}

/* ---- back, general: vol[iz][iy][ix] (+)= sum_s,k S L. One work-item per volume row,
 * sample-major: the light-field rows a sample needs stay in cache along the row. */
__kernel void back_gen(__global const float *restrict L, __global float *restrict vol,
                       __global const float *restrict coef,
                       __global const int2 *restrict sample_ij,
                       int nx, int ny, int nkx, int nky, int nkxp, int zv0, int zc0, int s0,
                       int ns, float ic, int accumulate)
{
    const int iy = get_global_id(0), izl = get_global_id(1);
    __global const float *c = coef + 16 * (zc0 + izl);
    __global float *out = vol + ((size_t)(zc0 + izl - zv0) * ny + iy) * nx;
    const size_t stride = (size_t)ns * nkxp;
    for (int sl = 0; sl < ns; ++sl) {
        const int2 ij = sample_ij[s0 + sl];
        const float2 o = pl_sample_offset(c, (float)ij.x - ic, (float)ij.y - ic);
        const float2 iw = pl_lens_iw(c);
        const int keep = accumulate || sl > 0;
        __global const float *ls = L + (size_t)sl * nkxp;
        for (int ix = 0; ix < nx; ++ix) {
            const float2 p = pl_lens_coord(c, o, (float)ix, (float)iy);
            const int kx = pl_floori(p.x), ky = pl_floori(p.y);
            const float dx = pl_lens_t(p.x - (float)kx, iw.x);
            const float dy = pl_lens_t(p.y - (float)ky, iw.y);
            const int x0 = pl_mini(pl_maxi(kx, 0), nkx - 1);
            const int x1 = pl_mini(pl_maxi(kx + 1, 0), nkx - 1);
            const int y0 = pl_mini(pl_maxi(ky, 0), nky - 1);
            const int y1 = pl_mini(pl_maxi(ky + 1, 0), nky - 1);
            const float wx0 = x0 == kx ? 1.0f - dx : 0.0f, wx1 = x1 == kx + 1 ? dx : 0.0f;
            const float wy0 = y0 == ky ? 1.0f - dy : 0.0f, wy1 = y1 == ky + 1 ? dy : 0.0f;
            const float v = wy0 * (wx0 * ls[y0 * stride + x0] + wx1 * ls[y0 * stride + x1])
                            + wy1 * (wx0 * ls[y1 * stride + x0] + wx1 * ls[y1 * stride + x1]);
            out[ix] = keep ? out[ix] + v : v;
        }
    }
}

/* ---- one voxel's 16 products per aperture sample (voxel_weights, stored matrices) */
__kernel void voxel_footprint(__global const int4 *restrict voxels, __global int *restrict idx,
                              __global float *restrict wts, __global const float *restrict coef,
                              __global const int2 *restrict sample_ij,
                              __global const float2 *restrict sample_px,
                              __global const int2 *restrict lens_rnd,
                              __global const float2 *restrict lens_frac,
                              int nkx, int nky, int width, int height, int ns, float ic,
                              float scale)
{
    const int s = get_global_id(0), vb = get_global_id(1);
    const int4 v = voxels[vb];
    __global const float *c = coef + 16 * v.z;
    const float2 iw = pl_lens_iw(c);
    const int2 ij = sample_ij[s];
    const float bu = (float)ij.x - ic, bv = (float)ij.y - ic;
    const float2 p = pl_lens_coord(c, pl_sample_offset(c, bu, bv), (float)v.x, (float)v.y);
    int id[16];
    float w[16];
    pl_sample_products(p, sample_px[s], iw, lens_rnd, lens_frac, nkx, nky, width, height, id, w);
    const size_t base = ((size_t)vb * ns + s) * 16;
    for (int e = 0; e < 16; ++e) {
        idx[base + e] = id[e];
        wts[base + e] = w[e] * scale;
    }
}

/* ---- direct (unfactorised) forward: each voxel scatters its 16 x ns products, atomics */
__kernel void fwd_direct(__global const float *restrict vol, volatile __global float *image,
                         __global const float *restrict coef,
                         __global const int2 *restrict sample_ij,
                         __global const float2 *restrict sample_px,
                         __global const int2 *restrict lens_rnd,
                         __global const float2 *restrict lens_frac,
                         int nx, int ny, int nkx, int nky, int width, int height, int zv0,
                         int ns, float ic, float scale)
{
    const int ix = get_global_id(0), iy = get_global_id(1), izl = get_global_id(2);
    const float e = vol[((size_t)izl * ny + iy) * nx + ix] * scale;
    if (e == 0.0f) return;
    __global const float *c = coef + 16 * (zv0 + izl);
    const float2 iw = pl_lens_iw(c);
    for (int s = 0; s < ns; ++s) {
        const int2 ij = sample_ij[s];
        const float bu = (float)ij.x - ic, bv = (float)ij.y - ic;
        const float2 p = pl_lens_coord(c, pl_sample_offset(c, bu, bv), (float)ix, (float)iy);
        int id[16];
        float w[16];
        pl_sample_products(p, sample_px[s], iw, lens_rnd, lens_frac, nkx, nky, width, height,
                           id, w);
        for (int k = 0; k < 16; ++k)
            if (id[k] >= 0 && w[k] > 0.0f) pl_atomic_addf(image + id[k], w[k] * e);
    }
}

/* ---- direct (unfactorised) back: each voxel gathers its 16 x ns products */
__kernel void back_direct(__global const float *restrict image, __global float *restrict vol,
                          __global const float *restrict coef,
                          __global const int2 *restrict sample_ij,
                          __global const float2 *restrict sample_px,
                          __global const int2 *restrict lens_rnd,
                          __global const float2 *restrict lens_frac,
                          int nx, int ny, int nkx, int nky, int width, int height, int zv0,
                          int ns, float ic, float scale)
{
    const int ix = get_global_id(0), iy = get_global_id(1), izl = get_global_id(2);
    __global const float *c = coef + 16 * (zv0 + izl);
    const float2 iw = pl_lens_iw(c);
    float acc = 0.0f;
    for (int s = 0; s < ns; ++s) {
        const int2 ij = sample_ij[s];
        const float bu = (float)ij.x - ic, bv = (float)ij.y - ic;
        const float2 p = pl_lens_coord(c, pl_sample_offset(c, bu, bv), (float)ix, (float)iy);
        int id[16];
        float w[16];
        pl_sample_products(p, sample_px[s], iw, lens_rnd, lens_frac, nkx, nky, width, height,
                           id, w);
        for (int k = 0; k < 16; ++k)
            if (id[k] >= 0) acc += w[k] * image[id[k]];
    }
    vol[((size_t)izl * ny + iy) * nx + ix] = acc * scale;
}

/* ---- back, separable, atomic (Projector(back="atomic")): T (+)= scatter of each L row
 * segment with float atomic adds. One work-item per (segment, ky, sample); T is zeroed
 * first. The order of the adds varies from run to run (last-bit differences). */
__kernel void back_y_scatter(__global const float *restrict L, volatile __global float *T,
                             __global const float *restrict coef,
                             __global const int2 *restrict sample_ij,
                             int ny, int nkxp, int seg, int zc0, int nzc, int i0, int nic, int s0,
                             float ic)
{
    const int t = get_global_id(0), ky = get_global_id(1), sl = get_global_id(2);
    const int2 ij = sample_ij[s0 + sl];
    const float bv = (float)ij.y - ic;
    const int k0 = t * seg * PL_VW;
    __global const float *src = L + ((size_t)ky * get_global_size(2) + sl) * nkxp + k0;
    for (int izl = 0; izl < nzc; ++izl) {
        __global const float *c = coef + 16 * (zc0 + izl);
        const int2 r = pl_hat_range(c[13], c[9] * bv + c[5], (float)ky, ny);
        const float iwy = pl_lens_iw(c).y;
        volatile __global float *dst = T + (size_t)(izl * nic + ij.x - i0) * ny * nkxp + k0;
        for (int iy = r.x; iy <= r.y; ++iy) {
            const float w = pl_lens_tent(pl_ky(c, bv, iy) - (float)ky, iwy);
            if (w > 0.0f)
                for (int m = 0; m < seg * PL_VW; ++m)
                    if (src[m] != 0.0f) pl_atomic_addf(dst + (size_t)iy * nkxp + m, w * src[m]);
        }
    }
}
