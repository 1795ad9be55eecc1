/* The image fit's forward model (docs/design.md §7.2): every particle's image on its
 * sensor patch and, with PL_DERIVATIVES, its derivatives by the image point
 * (X', Y', d') and by the intensity. NumPy twin: plenocl.optics.raybundle.RayBundle
 * (spots, render), float64 there, float32 here.
 *
 * Two kernels (ray_spots_hex replaces ray_spots for a hexagonal array), both gathers
 * without atomics:
 * - ray_spots: one work-item per (ray, particle), range (rays, particles). It traces the
 *   ray from the image point through its aperture sample to the array, takes the (up to)
 *   2 x 2 lenses that share it near a cell edge and writes one slot per lens choice: the
 *   nearest sensor pixel, the lens share and its derivatives, the landing point's
 *   derivatives by d' and the normalised pixel-integrated Gaussian of the blur over the
 *   5 x 5 pixels around it (per axis, with its derivative), and its key: the nearest row.
 *   A lens choice that gets no light (most of them), lies off the array or is missing
 *   (NaN centre) gets weight 0 and no key (PL_NO_KEY) and costs no spread. Each item
 *   writes its own 4 slots and keys. A lit slot's spread costs 2 x 2 exps and 12
 *   divisions (pl_spread: the edges' exps from two, erf from the edge's exp), no erf.
 * - render_rows: one work-item per band of `band` rows of one particle's patch, range
 *   (bands, particles), the bands of the tallest patch (an item past its own patch's
 *   end returns: patches differ by a few rows). It zeroes its band, then
 *   gathers over its particle's 4 x rays slots in ray order, adding the 5 x 5 pixels of
 *   each slot whose spread reaches the band: every patch element is written by one item
 *   only, in a fixed order (slot by slot, whatever the band), so the result is
 *   deterministic and the same for every band. It scans the slots' keys (4 bytes a slot)
 *   and reads a slot only near its band.
 * - ray_spots_hex (with PL_HEXAGONAL): ray_spots for a hexagonal array, same range and
 *   slots: the lens whose centre is nearest (the nearest corner of the axial lattice cell
 *   that holds the point: the two rows around it) and the first three of its six
 *   neighbours that share the ray near an edge or a vertex (at most three do,
 *   plenocl.optics.hexcells), each share normalised over all of them. NumPy twin:
 *   RayBundle on HexCells. The simulator's pl_lens_index (common.h) is not reused: it
 *   searches the nominal array (pitch, rotation, offset) for the nearest lens alone,
 *   while a ray's shares need the fitted lattice and the point's offset from the lens.
 * On a GPU both ranges are wide (rays x particles; band 1: rows x particles) and the
 * items of one particle read the same slots (cached broadcasts). On a CPU render_rows runs
 * in groups of one item (KernelSet's looping rule) with a particle's whole patch as its
 * band (a particle's keys scanned once instead of once a row: 3.5x faster on PoCL). No
 * builtin but exp in the hot paths (kernels/projector.h's note: PoCL's CPU driver calls
 * builtins out of line). Sizes are arguments: a new particle count or patch never
 * recompiles. */
#ifndef PL_DERIVATIVES
#define PL_DERIVATIVES 1
#endif
#ifndef PL_HEXAGONAL
#define PL_HEXAGONAL 0
#endif

#define PL_RAMP_FLOOR 1e-3f /* raybundle.RAMP_FLOOR */
#define PL_SLOT 28          /* floats per slot, layout below */
#define PL_NO_KEY (-(1 << 30)) /* the key of a slot without light: no row is near it */
/* slot: 0 near col, 1 near row, 2 weight, 3-5 d weight / d(X', Y', d'),
 * 6 d col / d d', 7 d row / d d', 8-12 column shares, 13-17 their d / d col,
 * 18-22 row shares, 23-27 their d / d row */

/* Plain-arithmetic stand-ins for builtins (kernels/projector.h's performance note: PoCL's
 * CPU driver calls rint, clamp, fabs, sign, isfinite, erf ... out of line). */
#include "arith.h" /* pl_abs */
inline float pl_clamp01(float x) { return x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x); }
/* rint (ties to even) for |x| < 2^22: adding and taking away 1.5 * 2^23 rounds at the
 * units (no -cl-fast-relaxed-math, so the compiler keeps both operations) */
inline float pl_rint(float x) { return (x + 12582912.0f) - 12582912.0f; }
/* whether x is finite: x - x is NaN for NaN and infinities */
inline int pl_finite(float x) { return x - x == 0.0f; }

/* erfc(a) for a >= 0 given g = exp(-a^2): t P(t) g with t = 1 / (1 + p a), P of degree 6
 * fitted to erfc(a) exp(a^2) (3.4e-8 in float64; 2.5e-7 absolute in float32 arithmetic,
 * about the builtin erf's rounding of values near 1). It reuses the exp the derivative
 * needs, so a pixel edge costs one exp and one division instead of exp and erf. */
inline float pl_erfc_g(float a, float g)
{
    float t = 1.0f / (1.0f + 0.7f * a);
    float q = -8.798170146e-02f;
    q = q * t + 4.316032998e-01f;
    q = q * t - 7.509929252e-01f;
    q = q * t + 3.509097379e-01f;
    q = q * t + 2.735411815e-01f;
    q = q * t + 3.859967628e-01f;
    q = q * t + 3.969236110e-01f;
    return q * t * g;
}

/* Share of a lattice axis (raybundle._shares): the own lens n and the neighbour n + side,
 * the neighbour's share w (the own one 1 - w), dw by the coordinate and dr by the ramp. */
inline void pl_share(float coord, float ramp, int *n, int *side, float *w, float *dw,
                     float *dr)
{
    float fn = pl_rint(coord), t = coord - fn;
    float up = pl_clamp01((t - (0.5f - ramp)) / (2.0f * ramp));
    float down = pl_clamp01(((ramp - 0.5f) - t) / (2.0f * ramp));
    int s = up > 0.0f ? 1 : (down > 0.0f ? -1 : 0);
    float share = s > 0 ? up : down;
    int inside = share > 0.0f && share < 1.0f;
    *n = (int)fn;
    *side = s;
    *w = share;
    *dw = inside ? s / (2.0f * ramp) : 0.0f;
    *dr = inside ? (s > 0 ? 0.5f - t : t + 0.5f) / (2.0f * ramp * ramp) : 0.0f;
}

/* The normalised shares of the 5 pixels around a landing point x (raybundle._spread):
 * g[i], dg[i] for pixel near - 2 + i; returns near. The 6 pixel edges lie at
 * e_j = t + (j - 5/2) delta (t = (near - x) delta, delta = 1 / (sqrt2 sigma)), so
 * exp(-e_j^2) = exp(-t^2) b^(2j - 5) c_|2j-5| with b = exp(-t delta) and the launch's
 * constants c_k = exp(-k^2 delta^2 / 4) (`gauss`: c_1, c_3, c_5): two exps for all six
 * edges. Where b^5 could overflow (delta^2 > 30, sigma < 0.13 px) the host passes
 * c_1 = -1 and each edge takes its own exp. */
inline float pl_spread(float x, float delta, float4 gauss, __global float *g,
                       __global float *dg)
{
    float near = pl_rint(x), t = (near - x) * delta, norm = delta * M_2_SQRTPI_F * 0.5f;
    float e[6], g2[6], f[6], gs[5], ds[5], total = 0.0f, dtotal = 0.0f;
    for (int j = 0; j < 6; ++j)
        e[j] = t + (j - 2.5f) * delta;
    if (gauss.x > 0.0f) {
        float a = exp(-t * t), b = exp(-t * delta), ib = 1.0f / b;
        float b3 = b * b * b, ib3 = ib * ib * ib;
        g2[0] = a * (ib3 * ib * ib) * gauss.z;
        g2[1] = a * ib3 * gauss.y;
        g2[2] = a * ib * gauss.x;
        g2[3] = a * b * gauss.x;
        g2[4] = a * b3 * gauss.y;
        g2[5] = a * (b3 * b * b) * gauss.z;
    } else {
        for (int j = 0; j < 6; ++j)
            g2[j] = exp(-e[j] * e[j]);
    }
    for (int j = 0; j < 6; ++j) { /* erf(e) = sign(e) (1 - erfc(|e|)) */
        float s = e[j] < 0.0f ? -1.0f : 1.0f;
        f[j] = s - s * pl_erfc_g(s * e[j], g2[j]);
    }
    for (int i = 0; i < 5; ++i) {
        gs[i] = 0.5f * (f[i + 1] - f[i]);
        ds[i] = (g2[i] - g2[i + 1]) * norm;
        total += gs[i];
        dtotal += ds[i];
    }
    float inv = 1.0f / total;
    for (int i = 0; i < 5; ++i) {
        float gi = gs[i] * inv;
        g[i] = gi;
        dg[i] = (ds[i] - gi * dtotal) * inv;
    }
    return near;
}

/* points: the image points (x', y', s') of every particle, this launch's from `first`
 * (slot p of the launch is particle first + p); lattice: [x, y, 1] @ lattice (3 x 2,
 * row-major) = (kx, ky); lenses: (rows, cols) of
 * (col, row) sensor pixels of a lens's landing point for a ray along the axis (NaN:
 * missing); optics: d_p (exit pupil to array; a thin lens: s_i), f_ml / pixel pitch,
 * ramp spacing, delta = 1 / (sqrt2 blur sigma)
 * (px) and gauss = (c_1, c_3, c_5) of pl_spread (c_1 = -1: an exp per edge). */
__kernel void ray_spots(__global const float *points, int first,
                        __global const float *aperture, int rays, __global const float *lenses, int rows, int cols,
                        float l00, float l01, float l10, float l11, float l20, float l21,
                        float d_p, float f_px, float spacing, float delta, float4 gauss,
                        __global float *slots, __global int *keys)
{
    int ray = get_global_id(0), p = get_global_id(1);
    points += 3 * (long)first; /* this launch's particles */
    float s = points[3 * p + 2], rho = d_p / s;
    float ux = aperture[2 * ray], uy = aperture[2 * ray + 1];
    float ex = points[3 * p] - ux, ey = points[3 * p + 1] - uy;
    float x = ux + ex * rho, y = uy + ey * rho;
    float ramp = spacing * pl_abs(1.0f - rho);
    float sgn = 1.0f - rho > 0.0f ? 1.0f : (1.0f - rho < 0.0f ? -1.0f : 0.0f);
    float slope = spacing * sgn * d_p / (s * s);
    if (ramp < PL_RAMP_FLOOR) {
        ramp = PL_RAMP_FLOOR;
        slope = 0.0f;
    }
    int nx, sx, ny, sy;
    float wx, dwx, rwx, wy, dwy, rwy;
    pl_share(x * l00 + y * l10 + l20, ramp, &nx, &sx, &wx, &dwx, &rwx);
    pl_share(x * l01 + y * l11 + l21, ramp, &ny, &sy, &wy, &dwy, &rwy);
    float dsx = -ex * d_p / (s * s), dsy = -ey * d_p / (s * s); /* d array point / d d' */
    float dlx[3] = {rho * l00, rho * l10, dsx * l00 + dsy * l10};  /* d kx / d X', Y', s' */
    float dly[3] = {rho * l01, rho * l11, dsx * l01 + dsy * l11};  /* d ky / d X', Y', s' */
    for (int a = 0; a < 2; ++a) {
        for (int b = 0; b < 2; ++b) {
            long index = ((long)p * rays + ray) * 4 + 2 * a + b;
            __global float *slot = slots + index * PL_SLOT;
            keys[index] = PL_NO_KEY;
            int kx = nx + a * sx, ky = ny + b * sy;
            float shx = a ? wx : 1.0f - wx, shy = b ? wy : 1.0f - wy;
            float gx = a ? dwx : -dwx, gy = b ? dwy : -dwy;
            float hx = a ? rwx : -rwx, hy = b ? rwy : -rwy;
            float lx = NAN, ly = NAN, w = shx * shy;
            /* a lens choice without light (w = 0: most of them away from cell edges)
             * reads no lens and spreads nothing */
            if (w > 0.0f && kx >= 0 && ky >= 0 && kx < cols && ky < rows) {
                lx = lenses[2 * ((long)ky * cols + kx)];
                ly = lenses[2 * ((long)ky * cols + kx) + 1];
            }
            if (!(pl_finite(lx) && pl_finite(ly))) {
                slot[2] = 0.0f;
                continue;
            }
            slot[2] = w;
            for (int d = 0; d < 3; ++d)
                slot[3 + d] = gx * shy * dlx[d] + shx * gy * dly[d];
            slot[5] += (hx * shy + shx * hy) * slope; /* the ramp widens with defocus */
            slot[6] = -f_px * ex / (s * s);
            slot[7] = -f_px * ey / (s * s);
            slot[0] = pl_spread(lx + f_px * ex / s, delta, gauss, slot + 8, slot + 13);
            slot[1] = pl_spread(ly + f_px * ey / s, delta, gauss, slot + 18, slot + 23);
            keys[index] = (int)slot[1];
        }
    }
}

/* points, intensity, patches (per particle offset (long), col0, row0, width, height): of
 * every particle, this launch's from `first`; slots, keys: this launch's (ray_spots with
 * the same `first`); range (bands, particles): item (b, p) renders `band` rows of
 * particle p (within the launch) from row b * band (fewer at the patch's end; none past
 * it); out: PL_DERIVATIVES ? 5 : 1 rows of `total` elements
 * (value, d / d X', Y', d', d / d intensity). */
__kernel void render_rows(__global const float *slots, __global const int *keys, int rays,
                          __global const float *points, __global const float *intensity,
                          __global const long *offset, __global const int *col0,
                          __global const int *row0, __global const int *width,
                          __global const int *height, int first, int band,
                          float f_px, long total, __global float *out)
{
    /* this launch's particles: the tables from `first`, the slots its own */
    points += 3 * (long)first;
    intensity += first;
    offset += first;
    col0 += first;
    row0 += first;
    width += first;
    height += first;
    int p = get_global_id(1), r0 = (int)get_global_id(0) * band;
    if (r0 >= height[p])
        return; /* a band past this particle's patch (a taller patch set the range) */
    int wd = width[p], c0 = col0[p], srow = row0[p] + r0;
    int nr = height[p] - r0 < band ? height[p] - r0 : band;
    long base = offset[p] + (long)r0 * wd;
    float inv_rays = 1.0f / rays, scale = intensity[p] * inv_rays;
    float dcol_dx = f_px / points[3 * p + 2];
#if PL_DERIVATIVES
    const int n_out = 5;
#else
    const int n_out = 1;
#endif
    for (int k = 0; k < n_out; ++k)
        for (int c = 0; c < nr * wd; ++c)
            out[k * total + base + c] = 0.0f;
    __global const float *slot = slots + (long)p * rays * 4 * PL_SLOT;
    __global const int *key = keys + (long)p * rays * 4;
    for (int i = 0; i < 4 * rays; ++i, slot += PL_SLOT) {
        int kr = key[i] - srow; /* the slot's nearest row in the band */
        if (kr < -2 || kr > nr + 1)
            continue;
        /* the slot in private variables (the stores to out could alias it) and its
         * factors by pixel share: a patch element costs a few products per row */
        int lo = kr - 2 < 0 ? 0 : kr - 2, hi = kr + 2 < nr ? kr + 2 : nr - 1;
        int lc0 = (int)slot[0] - 2 - c0;
        int clo = lc0 < 0 ? -lc0 : 0, chi = wd - lc0 < 5 ? wd - lc0 : 5;
        float w = slot[2], ws = w * scale, gx[5], dgx[5];
        for (int c = 0; c < 5; ++c) {
            gx[c] = slot[8 + c];
            dgx[c] = slot[13 + c];
        }
#if PL_DERIVATIVES
        float as = slot[3] * scale, bs = slot[4] * scale, cs = slot[5] * scale;
        float wd_s = w * dcol_dx * scale, w6 = w * slot[6] * scale, w7 = w * slot[7] * scale;
        float wr = w * inv_rays;
#endif
        for (int r = lo; r <= hi; ++r) {
            float gy = slot[20 + r - kr], dgy = slot[25 + r - kr];
            __global float *o = out + base + (long)r * wd + lc0;
#pragma unroll
            for (int c = 0; c < 5; ++c) { /* unrolled: gx, dgx stay in registers */
                if (c < clo || c >= chi)
                    continue;
                float g = gx[c] * gy;
                o[c] += g * ws;
#if PL_DERIVATIVES
                float px = dgx[c] * gy, py = gx[c] * dgy;
                o[total + c] += g * as + px * wd_s;
                o[2 * total + c] += g * bs + py * wd_s;
                o[3 * total + c] += g * cs + (px * w6 + py * w7);
                o[4 * total + c] += g * wr;
#endif
            }
        }
    }
}

#if PL_HEXAGONAL
#include "common.h" /* pl_floori */

#define PL_HEX_RAMP_MAX 0.45f /* hexcells.HEX_RAMP_MAX */

/* The nearest lens (axial indices q, r) of the fractional axial point (fq, fr): the
 * nearest corner of its lattice cell in the metric gram = (G00, G01, G11) (pitches^2),
 * the first on a tie (HexCells.nearest). */
inline void pl_hex_nearest(float fq, float fr, float4 gram, int *q, int *r)
{
    int q0 = pl_floori(fq), r0 = pl_floori(fr);
    float best = INFINITY;
    for (int c = 0; c < 4; ++c) {
        float a = fq - (float)(q0 + (c & 1)), b = fr - (float)(r0 + (c >> 1));
        float d2 = a * a * gram.x + 2.0f * a * b * gram.y + b * b * gram.z;
        if (d2 < best) {
            best = d2;
            *q = q0 + (c & 1);
            *r = r0 + (c >> 1);
        }
    }
}

/* As ray_spots, on hexagonal cells (HexCells.shares). gram: pl_hex_nearest's metric;
 * steps: the six neighbours' axial steps (q, r); table: per neighbour its squared length
 * (pitches^2), the metric times the step (2) and d delta / d(x, y) (per mm, 2), where
 * delta = length^2 / 2 - v . (metric step) is the point's distance (pitches) from the
 * bisector with the nearest lens (v: the point's offset from it, axial units). A
 * neighbour with delta < ramp gets the weight (ramp - delta) / (ramp + delta) against
 * the nearest lens's 1; the shares are the weights over their sum. */
__kernel void ray_spots_hex(__global const float *points, int first,
                            __global const float *aperture, int rays, __global const float *lenses, int rows, int cols,
                            float l00, float l01, float l10, float l11, float l20,
                            float l21, float d_p, float f_px, float spacing, float delta,
                            float4 gauss, float4 gram, __global const int *steps,
                            __global const float *table, __global float *slots,
                            __global int *keys)
{
    int ray = get_global_id(0), p = get_global_id(1);
    points += 3 * (long)first; /* this launch's particles */
    float s = points[3 * p + 2], rho = d_p / s;
    float ux = aperture[2 * ray], uy = aperture[2 * ray + 1];
    float ex = points[3 * p] - ux, ey = points[3 * p + 1] - uy;
    float x = ux + ex * rho, y = uy + ey * rho;
    float ramp = spacing * pl_abs(1.0f - rho);
    float sgn = 1.0f - rho > 0.0f ? 1.0f : (1.0f - rho < 0.0f ? -1.0f : 0.0f);
    float slope = spacing * sgn * d_p / (s * s);
    if (ramp < PL_RAMP_FLOOR || ramp > PL_HEX_RAMP_MAX) {
        ramp = ramp < PL_RAMP_FLOOR ? PL_RAMP_FLOOR : PL_HEX_RAMP_MAX;
        slope = 0.0f;
    }
    float fq = x * l00 + y * l10 + l20, fr = x * l01 + y * l11 + l21;
    int qa = 0, ra = 0;
    pl_hex_nearest(fq, fr, gram, &qa, &ra);
    float vq = fq - (float)qa, vr = fr - (float)ra;
    /* the lens choices: the nearest (weight 1) and the first three lit neighbours; the
     * weights' derivatives by x, y (mm) and the ramp, and their sums */
    int lq[4] = {qa, 0, 0, 0}, lr[4] = {ra, 0, 0, 0}, n = 1;
    float w[4] = {1.0f, 0.0f, 0.0f, 0.0f}, wx[4] = {0.0f}, wy[4] = {0.0f}, wr[4] = {0.0f};
    float total = 1.0f, tx = 0.0f, ty = 0.0f, tr = 0.0f;
    for (int j = 0; j < 6; ++j) {
        __global const float *h = table + 5 * j;
        float dl = 0.5f * h[0] - (vq * h[1] + vr * h[2]);
        if (!(dl < ramp))
            continue;
        float den = ramp + dl, wj = (ramp - dl) / den;
        float dd = -2.0f * ramp / (den * den), dr = 2.0f * dl / (den * den);
        total += wj;
        tx += dd * h[3];
        ty += dd * h[4];
        tr += dr;
        if (n < 4) {
            lq[n] = qa + steps[2 * j];
            lr[n] = ra + steps[2 * j + 1];
            w[n] = wj;
            wx[n] = dd * h[3];
            wy[n] = dd * h[4];
            wr[n] = dr;
            ++n;
        }
    }
    float inv = 1.0f / total;
    float dsx = -ex * d_p / (s * s), dsy = -ey * d_p / (s * s); /* d array point / d d' */
    for (int i = 0; i < 4; ++i) {
        long index = ((long)p * rays + ray) * 4 + i;
        __global float *slot = slots + index * PL_SLOT;
        keys[index] = PL_NO_KEY;
        float lx = NAN, ly = NAN;
        if (i < n && lq[i] >= 0 && lr[i] >= 0 && lq[i] < cols && lr[i] < rows) {
            lx = lenses[2 * ((long)lr[i] * cols + lq[i])];
            ly = lenses[2 * ((long)lr[i] * cols + lq[i]) + 1];
        }
        if (!(pl_finite(lx) && pl_finite(ly))) {
            slot[2] = 0.0f;
            continue;
        }
        float share = w[i] * inv;
        float gx = (wx[i] - share * tx) * inv, gy = (wy[i] - share * ty) * inv;
        slot[2] = share;
        slot[3] = rho * gx;
        slot[4] = rho * gy;
        slot[5] = gx * dsx + gy * dsy + (wr[i] - share * tr) * inv * slope;
        slot[6] = -f_px * ex / (s * s);
        slot[7] = -f_px * ey / (s * s);
        slot[0] = pl_spread(lx + f_px * ex / s, delta, gauss, slot + 8, slot + 13);
        slot[1] = pl_spread(ly + f_px * ey / s, delta, gauss, slot + 18, slot + 23);
        keys[index] = (int)slot[1];
    }
}
#endif /* PL_HEXAGONAL */
