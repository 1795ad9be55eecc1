/* The image fit's forward model (docs/design.md §7.2): every particle's image on its
 * sensor patch and, with PL_DERIVATIVES, its derivatives by the image point
 * (X', Y', s_i') and by the intensity. NumPy twin: plenocl.optics.raybundle.RayBundle
 * (spots, render), float64 there, float32 here.
 *
 * Two kernels, both gathers without atomics:
 * - ray_spots: one work-item per (ray, particle). It traces the ray from the image point
 *   through its aperture sample to the array, takes the (up to) 2 x 2 lenses that share
 *   it near a cell edge and writes one slot per lens choice: the nearest sensor pixel,
 *   the lens share and its derivatives, the landing point's derivatives by s_i' and the
 *   normalised pixel-integrated Gaussian of the blur over the 5 x 5 pixels around it
 *   (per axis, with its derivative), and its key: the nearest row. A lens choice that
 *   gets no light, lies off the array or is missing (NaN centre) gets weight 0 and no
 *   key (PL_NO_KEY). Each item writes its own 4 slots and keys.
 * - render_rows: one work-item per patch row (all particles' rows in one flat range;
 *   the host's table names the particle and the row). It zeroes its row, then gathers
 *   over its particle's 4 x rays slots in ray order, adding the 5 pixels of each slot
 *   whose spread reaches the row: every patch element is written by one item only, in a
 *   fixed order, so the result is deterministic. It scans the slots' keys (4 bytes a
 *   slot, cached for all the particle's rows) and reads a slot only near its row.
 * On a GPU both ranges are wide (rays x particles; rows x particles) and the items of one
 * particle read the same slots (cached broadcasts); on a CPU render_rows runs in groups
 * of one item (KernelSet's looping rule). Sizes are arguments: a new particle count or
 * patch never recompiles. */
#ifndef PL_DERIVATIVES
#define PL_DERIVATIVES 1
#endif

#define PL_RAMP_FLOOR 1e-3f /* raybundle.RAMP_FLOOR */
#define PL_SLOT 28          /* floats per slot, layout below */
#define PL_NO_KEY (-(1 << 30)) /* the key of a slot without light: no row is near it */
/* slot: 0 near col, 1 near row, 2 weight, 3-5 d weight / d(X', Y', s_i'),
 * 6 d col / d s_i', 7 d row / d s_i', 8-12 column shares, 13-17 their d / d col,
 * 18-22 row shares, 23-27 their d / d row */

/* Share of a lattice axis (raybundle._shares): the own lens n and the neighbour n + side,
 * the neighbour's share w (the own one 1 - w), dw by the coordinate and dr by the ramp. */
inline void pl_share(float coord, float ramp, int *n, int *side, float *w, float *dw,
                     float *dr)
{
    float fn = rint(coord), t = coord - fn;
    float up = clamp((t - (0.5f - ramp)) / (2.0f * ramp), 0.0f, 1.0f);
    float down = clamp(((ramp - 0.5f) - t) / (2.0f * ramp), 0.0f, 1.0f);
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
 * g[i], dg[i] for pixel near - 2 + i; returns near. */
inline float pl_spread(float x, float sigma, __global float *g, __global float *dg)
{
    float near = rint(x), s2 = M_SQRT2_F * sigma, norm = M_2_SQRTPI_F / (2.0f * s2);
    float e[6], f[6], g2[6], gs[5], ds[5], total = 0.0f, dtotal = 0.0f;
    for (int j = 0; j < 6; ++j) {
        e[j] = (near - 2.5f + j - x) / s2;
        f[j] = erf(e[j]); /* each pixel edge's erf and exp once, shared by its pixels */
        g2[j] = exp(-e[j] * e[j]);
    }
    for (int i = 0; i < 5; ++i) {
        gs[i] = 0.5f * (f[i + 1] - f[i]);
        ds[i] = (g2[i] - g2[i + 1]) * norm;
        total += gs[i];
        dtotal += ds[i];
    }
    for (int i = 0; i < 5; ++i) {
        g[i] = gs[i] / total;
        dg[i] = (ds[i] - g[i] * dtotal) / total;
    }
    return near;
}

/* lattice: [x, y, 1] @ lattice (3 x 2, row-major) = (kx, ky); lenses: (rows, cols) of
 * (col, row) sensor pixels of a lens's landing point for a ray along the axis (NaN:
 * missing); optics: s_i, f_ml / pixel pitch, ramp spacing, blur sigma (px). */
__kernel void ray_spots(__global const float *points, __global const float *aperture,
                        int rays, __global const float *lenses, int rows, int cols,
                        float l00, float l01, float l10, float l11, float l20, float l21,
                        float s_i, float f_px, float spacing, float sigma,
                        __global float *slots, __global int *keys)
{
    int ray = get_global_id(0), p = get_global_id(1);
    float s = points[3 * p + 2], rho = s_i / s;
    float ux = aperture[2 * ray], uy = aperture[2 * ray + 1];
    float ex = points[3 * p] - ux, ey = points[3 * p + 1] - uy;
    float x = ux + ex * rho, y = uy + ey * rho;
    float ramp = spacing * fabs(1.0f - rho);
    float slope = spacing * sign(1.0f - rho) * s_i / (s * s);
    if (ramp < PL_RAMP_FLOOR) {
        ramp = PL_RAMP_FLOOR;
        slope = 0.0f;
    }
    int nx, sx, ny, sy;
    float wx, dwx, rwx, wy, dwy, rwy;
    pl_share(x * l00 + y * l10 + l20, ramp, &nx, &sx, &wx, &dwx, &rwx);
    pl_share(x * l01 + y * l11 + l21, ramp, &ny, &sy, &wy, &dwy, &rwy);
    float dsx = -ex * s_i / (s * s), dsy = -ey * s_i / (s * s); /* d array point / d s' */
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
            if (w > 0.0f && kx >= 0 && ky >= 0 && kx < cols && ky < rows) {
                lx = lenses[2 * ((long)ky * cols + kx)];
                ly = lenses[2 * ((long)ky * cols + kx) + 1];
            }
            if (!(isfinite(lx) && isfinite(ly))) {
                slot[2] = 0.0f;
                continue;
            }
            slot[2] = w;
            for (int d = 0; d < 3; ++d)
                slot[3 + d] = gx * shy * dlx[d] + shx * gy * dly[d];
            slot[5] += (hx * shy + shx * hy) * slope; /* the ramp widens with defocus */
            slot[6] = -f_px * ex / (s * s);
            slot[7] = -f_px * ey / (s * s);
            slot[0] = pl_spread(lx + f_px * ex / s, sigma, slot + 8, slot + 13);
            slot[1] = pl_spread(ly + f_px * ey / s, sigma, slot + 18, slot + 23);
            keys[index] = (int)slot[1];
        }
    }
}

/* patches: per particle offset (long), col0, row0, width; row_pid, row_local: the
 * particle and patch row of each work-item; out: PL_DERIVATIVES ? 5 : 1 rows of `total`
 * elements (value, d / d X', Y', s_i', d / d intensity). */
__kernel void render_rows(__global const float *slots, __global const int *keys, int rays,
                          __global const float *points, __global const float *intensity,
                          __global const long *offset, __global const int *col0,
                          __global const int *row0, __global const int *width,
                          __global const int *row_pid, __global const int *row_local,
                          float f_px, long total, __global float *out)
{
    int item = get_global_id(0), p = row_pid[item], r = row_local[item];
    int wd = width[p], c0 = col0[p], srow = row0[p] + r;
    long base = offset[p] + (long)r * wd;
    float inv_rays = 1.0f / rays, scale = intensity[p] * inv_rays;
    float dcol_dx = f_px / points[3 * p + 2];
#if PL_DERIVATIVES
    const int n_out = 5;
#else
    const int n_out = 1;
#endif
    for (int k = 0; k < n_out; ++k)
        for (int c = 0; c < wd; ++c)
            out[k * total + base + c] = 0.0f;
    __global const float *slot = slots + (long)p * rays * 4 * PL_SLOT;
    __global const int *key = keys + (long)p * rays * 4;
    for (int i = 0; i < 4 * rays; ++i, slot += PL_SLOT) {
        int dr = srow - key[i];
        if (dr < -2 || dr > 2)
            continue;
        float w = slot[2];
        float gy = slot[20 + dr], dgy = slot[25 + dr];
        int lc0 = (int)slot[0] - 2 - c0;
        for (int c = 0; c < 5; ++c) {
            int lc = lc0 + c;
            if (lc < 0 || lc >= wd)
                continue;
            float gx = slot[8 + c], g = gx * gy;
            long e = base + lc;
            out[e] += w * g * scale;
#if PL_DERIVATIVES
            float dgx = slot[13 + c];
            out[total + e] += (slot[3] * g + w * dgx * gy * dcol_dx) * scale;
            out[2 * total + e] += (slot[4] * g + w * gx * dgy * dcol_dx) * scale;
            out[3 * total + e] += (slot[5] * g + w * (dgx * gy * slot[6] + gx * dgy * slot[7]))
                                  * scale;
            out[4 * total + e] += w * g * inv_rays;
#endif
        }
    }
}
