/* Shared helpers for plenocl kernels: counter-based random numbers, the microlens
 * lookup of docs/design.md §2, and deterministic image accumulation.
 * Every function here has a NumPy twin in plenocl/reference/ (same integer maths). */
#ifndef PLENOCL_COMMON_H
#define PLENOCL_COMMON_H

#include "arith.h" /* pl_floori, pl_atomic_addf */

#define PLENOCL_TWO_PI 6.283185307179586f

/* 32-bit integer finaliser ("lowbias32", C. Wellons): a bijection with good avalanche. */
inline uint pl_hash(uint x)
{
    x ^= x >> 16;
    x *= 0x7feb352dU;
    x ^= x >> 15;
    x *= 0x846ca68bU;
    x ^= x >> 16;
    return x;
}

/* Counter-based stream: random word k of ray `ray` of source `src` is
 * pl_word(pl_ray_key(pl_source_key(seed, src), ray), k). It depends only on
 * (seed, src, ray, k): the same on every device and for any split of the work.
 * The keys let a kernel hoist the per-source and per-ray hashing out of its loops. */
inline uint pl_source_key(uint seed, uint src)
{
    return pl_hash(pl_hash(seed ^ 0x9e3779b9U) ^ src);
}

inline uint pl_ray_key(uint source_key, uint ray)
{
    return pl_hash(source_key ^ ray);
}

inline uint pl_word(uint ray_key, uint k)
{
    return pl_hash(ray_key ^ k);
}

/* Uniform float in [0, 1) from the top 24 bits. */
inline float pl_uniform(uint word)
{
    return (float)(word >> 8) * (1.0f / 16777216.0f);
}


/* Microlens geometry on the array plane (docs/design.md §2), rotation (c, s) and offset.
 * A rectangular array has row = pitch and odd = 0; a hexagonal one row = pitch sqrt(3)/2
 * and its odd rows shifted by odd = +-0.5 pitches along the row. */
typedef struct {
    float pitch;    /* microlens pitch, mm */
    float c, s;     /* cos, sin of the array rotation */
    float ox, oy;   /* array offset, mm */
    int nx, ny;     /* lenses: columns, rows */
    float row;      /* distance between rows, mm */
    float odd;      /* shift of the odd rows, pitches */
} pl_mla;

/* Index of the microlens containing array-plane point (x, y); -1 when outside. */
inline int pl_lens_index(const pl_mla m, float x, float y, int *kx, int *ky)
{
    float dx = x - m.ox, dy = y - m.oy;
    float a = m.c * dx + m.s * dy;      /* rotate into the array frame */
    float b = -m.s * dx + m.c * dy;
    int ix, iy;
    if (m.odd == 0.0f) {
        ix = pl_floori(a / m.pitch + 0.5f * (float)m.nx);
        iy = pl_floori(b / m.pitch + 0.5f * (float)m.ny);
    } else {
        /* hexagonal: the nearest centre lies in one of the two rows around the point */
        float fy = b / m.row + 0.5f * (float)(m.ny - 1), best = INFINITY;
        int r0 = pl_floori(fy);
        ix = iy = -1;
        for (int r = r0; r <= r0 + 1; ++r) {
            float fx = a / m.pitch + 0.5f * (float)(m.nx - 1) - m.odd * (float)(r & 1);
            int k = pl_floori(fx + 0.5f);
            float ex = (fx - (float)k) * m.pitch, ey = (fy - (float)r) * m.row;
            float d2 = ex * ex + ey * ey;
            if (d2 < best) { best = d2; ix = k; iy = r; }
        }
    }
    if (ix < 0 || iy < 0 || ix >= m.nx || iy >= m.ny) return -1;
    *kx = ix;
    *ky = iy;
    return iy * m.nx + ix;
}

/* Centre of microlens (kx, ky) on the array plane, mm. */
inline float2 pl_lens_center(const pl_mla m, int kx, int ky)
{
    float a = ((float)kx - 0.5f * (float)(m.nx - 1) + m.odd * (float)(ky & 1)) * m.pitch;
    float b = ((float)ky - 0.5f * (float)(m.ny - 1)) * m.row;
    return (float2)(m.c * a - m.s * b + m.ox, m.s * a + m.c * b + m.oy);
}

/* Flat pixel index of sensor point (x, y) mm (from the optical axis, which lies edge_col,
 * edge_row pixels from the first pixel's outer edge), -1 off the sensor. */
inline int pl_pixel_index(float x, float y, float pixel_pitch, float edge_col, float edge_row,
                          int width, int height)
{
    int col = pl_floori(x / pixel_pitch + edge_col);
    int row = pl_floori(y / pixel_pitch + edge_row);
    if (col < 0 || row < 0 || col >= width || row >= height) return -1;
    return row * width + col;
}

/* Deterministic accumulation: each source carries a per-ray quantum prepared on the
 * host. With 64-bit atomics it is a fixed-point integer, so sums do not depend on the
 * order of the work-items; without them a float compare-and-swap loop adds it. */
#ifdef PL_INT64_ATOMICS
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
typedef long pl_acc_t;
inline void pl_accumulate(volatile __global pl_acc_t *img, int idx, pl_acc_t q)
{
    atom_add(img + idx, q);
}
#else
typedef float pl_acc_t;
inline void pl_accumulate(volatile __global pl_acc_t *img, int idx, pl_acc_t q)
{
    pl_atomic_addf(img + idx, q);
}
#endif

#endif /* PLENOCL_COMMON_H */
