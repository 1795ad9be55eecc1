/* FFT cross-correlation of interrogation windows on the device (docs/design.md §7,
 * plenocl.piv.devicefft.DeviceCorrelation): the windows of two volumes gathered, made
 * zero-mean and weighted, correlated circularly over an FFT shape (the window, or a
 * zero-padded first pass) and their correlation peaks fitted, so that only six numbers per
 * window come back. NumPy twin: plenocl.piv.correlation.correlate (the host's FFTW or
 * SciPy path, with the same preparation and peak fit) and plenocl.reference.fftcorr (each
 * kernel on its own).
 *
 * Layout. A batch of B windows, each window's FFT box P = pz x py x px complex values
 * (float2, x fastest) at data[b P ..]. Window b has its low corner lows[3 b ..] (z, y, x,
 * voxels) in the volumes (nz, ny, nx), its size wz x wy x wx in the box's leading corner,
 * zeros beyond it. Both windows of a pair share one complex box, a in the real part and b
 * in the imaginary part, so one complex FFT transforms both (their spectra are separated
 * in cross_spectrum by the symmetry of real signals).
 *
 * window_moments: per window and volume (v: 0 a, 1 b), its mean, the sum of squares about
 * it (spread), the sum of squares (raw) and the energy after the weight, sum ((x - mean)
 * w)^2, at moments[(2 b + v) 4 ..].
 * fill_windows: the complex boxes from both volumes and the moments.
 * gather_windows: the windows of one volume as they are (B x wz x wy x wx floats), for the
 * host's FFT of a device volume (only the windows go to the host).
 * fft_lines: Stockham passes of radix 8, 4, 2, 3, 5 along one axis of every box (or of
 * the lines that hold window values): length n (a product of 2, 3 and 5), elements
 * `step` apart; `sign` -1 forward, +1 inverse (not normalised, as FFTW).
 * cross_spectrum: S = conj(A(k)) B(k) from the packed spectrum Z = A + i B: A(k) = (Z(k)
 * + conj(Z(-k))) / 2, B(k) = (Z(k) - conj(Z(-k))) / 2i; the inverse FFT of S is P times
 * the circular correlation c(s) = sum_p a'(p) b'(p + s), which is real, so windows 2 j
 * and 2 j + 1 share one box, S_2j + i S_2j+1, and one inverse gives both planes (its real
 * and imaginary parts).
 * peak_fit: per window its plane's highest value (the lowest index among equals, as
 * np.argmax), normalised by P sqrt(energy_a energy_b) where both windows have signal;
 * the three-point Gaussian offset along each axis (parabolic where a value is <= 0, as
 * plenocl.peaks.gaussian_subpixel), the peak wrapped to [-n/2, n/2); the ratio to the
 * highest value outside the +-`exclude` cube around it. out[6 b ..]: dz, dy, dx, peak,
 * ratio (INFINITY where the second is not positive), signal (1 or 0).
 *
 * Parallel structure. window_moments and peak_fit: one work-group of PL_GROUP items per
 * window (and volume), the items striding over its voxels and reducing in local memory
 * (kernels/groupreduce.h); tens of groups per batch, each over 10^4-10^5 values.
 * fill_windows, gather_windows and cross_spectrum: one work-item per value of the batch,
 * no shared writes. fft_lines: one work-group of PL_GROUP items per line (B P / n lines, 10^4
 * to 10^5 per pass), the line in local memory, the items striding over its butterflies
 * between barriers (a pass of radix r has n / r butterflies: a 64-point line's radix-8
 * passes keep 8 of a GPU's 64 items busy, left so while the passes are memory-bound, not
 * yet measured on a GPU; on a CPU one item walks the line); lines along x read contiguous
 * memory, along y and z a strided column (on a GPU uncoalesced reads of a few megabytes
 * per pass). No atomics anywhere; every
 * result is one item's or one group's tree, so results do not depend on the core count.
 * Sizes are arguments; PL_GROUP (a power of two) and PL_MAXN (the longest line) are -D
 * defines. */

#include "groupreduce.h" /* PL_GROUP, pl_group_sum, pl_group_max */
#include "subpixel.h"    /* pl_subpixel, in float */

#ifndef PL_MAXN
#define PL_MAXN 512
#endif

/* Moments of each window of both volumes; global (B PL_GROUP, 2), local (PL_GROUP, 1). The
 * items stride over the window's rows, each row read along x. */
__kernel void window_moments(__global const float *vol_a, __global const float *vol_b,
                             int ny, int nx, __global const int *lows,
                             int wz, int wy, int wx, __global const float *weight,
                             int weighted, __global float *moments)
{
    __local float scratch[PL_GROUP];
    const int b = get_group_id(0), v = get_global_id(1), lid = get_local_id(0);
    __global const float *vol = (v ? vol_b : vol_a)
        + ((long)lows[3 * b] * ny + lows[3 * b + 1]) * nx + lows[3 * b + 2];
    float sum = 0.0f, raw = 0.0f;
    for (int row = lid; row < wz * wy; row += PL_GROUP) {
        __global const float *q = vol + ((long)(row / wy) * ny + row % wy) * nx;
        for (int x = 0; x < wx; x++) {
            sum += q[x];
            raw += q[x] * q[x];
        }
    }
    const float mean = pl_group_sum(scratch, sum) / (float)(wz * wy * wx);
    raw = pl_group_sum(scratch, raw);
    float spread = 0.0f, energy = 0.0f;
    for (int row = lid; row < wz * wy; row += PL_GROUP) {
        __global const float *q = vol + ((long)(row / wy) * ny + row % wy) * nx;
        __global const float *w = weight + row * wx;
        for (int x = 0; x < wx; x++) {
            const float d = q[x] - mean;
            const float dw = weighted ? d * w[x] : d;
            spread += d * d;
            energy += dw * dw;
        }
    }
    spread = pl_group_sum(scratch, spread);
    energy = pl_group_sum(scratch, energy);
    if (lid == 0) {
        __global float *m = moments + 4 * (2 * b + v);
        m[0] = mean;
        m[1] = spread;
        m[2] = raw;
        m[3] = energy;
    }
}

/* The complex boxes; global (px, py, pz B). */
__kernel void fill_windows(__global const float *vol_a, __global const float *vol_b,
                           int ny, int nx, __global const int *lows, int wz, int wy, int wx,
                           int pz, __global const float *weight, int weighted,
                           __global const float *moments, __global float2 *data)
{
    const int x = get_global_id(0), y = get_global_id(1), zb = get_global_id(2);
    const int px = get_global_size(0), py = get_global_size(1);
    const int z = zb % pz, b = zb / pz;
    float2 out = (float2)(0.0f, 0.0f);
    if (z < wz && y < wy && x < wx) {
        const long at = ((long)(lows[3 * b] + z) * ny + lows[3 * b + 1] + y) * nx
                        + lows[3 * b + 2] + x;
        const float w = weighted ? weight[(z * wy + y) * wx + x] : 1.0f;
        out = (float2)((vol_a[at] - moments[8 * b]) * w, (vol_b[at] - moments[8 * b + 4]) * w);
    }
    data[((long)zb * py + y) * px + x] = out;
}

/* The windows of one volume; global (wx, wy, wz B). */
__kernel void gather_windows(__global const float *vol, int ny, int nx,
                             __global const int *lows, int wz, __global float *out)
{
    const int x = get_global_id(0), y = get_global_id(1), zb = get_global_id(2);
    const int wx = get_global_size(0), wy = get_global_size(1);
    const int z = zb % wz, b = zb / wz;
    out[((long)zb * wy + y) * wx + x] =
        vol[((long)(lows[3 * b] + z) * ny + lows[3 * b + 1] + y) * nx + lows[3 * b + 2] + x];
}

inline float2 pl_cmul(float2 a, float2 b)
{
    return (float2)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

/* sign i x */
inline float2 pl_rot(float2 x, float sign)
{
    return sign * (float2)(-x.y, x.x);
}

/* The radix-4 DFT of v0..v3 in place. */
inline void pl_dft4(float2 *v0, float2 *v1, float2 *v2, float2 *v3, float sign)
{
    const float2 s0 = *v0 + *v2, d0 = *v0 - *v2, s1 = *v1 + *v3, d1 = pl_rot(*v1 - *v3, sign);
    *v0 = s0 + s1;
    *v1 = d0 + d1;
    *v2 = s0 - s1;
    *v3 = d0 - d1;
}

/* One radix-r butterfly of a Stockham pass: inputs j + q m of `src`, outputs to + q ns of
 * `dst`, k the butterfly's place in its sub-transform. Twiddles from the table tw[t] =
 * exp(sign 2 pi i t / n): the stage's at k q n / (ns r) (below n), the radix-3 and
 * radix-5 DFTs' roots at multiples of n / r; the radix-2, 4 and 8 DFTs are written out. */
inline void pl_butterfly(__local const float2 *src, __local float2 *dst, int j, int k,
                         int to, int n, int m, int r, int ns, float sign,
                         __global const float2 *tw)
{
    const int kt = k * (n / (ns * r));  /* input q's twiddle: tw[q kt] */
    if (r == 8) {
        const float h = 0.70710678118654752f;
        float2 v0 = src[j], v1 = pl_cmul(src[j + m], tw[kt]);
        float2 v2 = pl_cmul(src[j + 2 * m], tw[2 * kt]), v3 = pl_cmul(src[j + 3 * m], tw[3 * kt]);
        float2 v4 = pl_cmul(src[j + 4 * m], tw[4 * kt]), v5 = pl_cmul(src[j + 5 * m], tw[5 * kt]);
        float2 v6 = pl_cmul(src[j + 6 * m], tw[6 * kt]), v7 = pl_cmul(src[j + 7 * m], tw[7 * kt]);
        pl_dft4(&v0, &v2, &v4, &v6, sign);  /* even inputs */
        pl_dft4(&v1, &v3, &v5, &v7, sign);  /* odd inputs */
        v3 = h * (v3 + pl_rot(v3, sign));            /* times exp(sign i pi / 4) */
        v5 = pl_rot(v5, sign);                       /* times exp(sign i pi / 2) */
        v7 = h * (pl_rot(v7, sign) - v7);            /* times exp(sign 3 i pi / 4) */
        dst[to] = v0 + v1;
        dst[to + 4 * ns] = v0 - v1;
        dst[to + ns] = v2 + v3;
        dst[to + 5 * ns] = v2 - v3;
        dst[to + 2 * ns] = v4 + v5;
        dst[to + 6 * ns] = v4 - v5;
        dst[to + 3 * ns] = v6 + v7;
        dst[to + 7 * ns] = v6 - v7;
    } else if (r == 4) {
        float2 v0 = src[j], v1 = pl_cmul(src[j + m], tw[1 * kt]);
        float2 v2 = pl_cmul(src[j + 2 * m], tw[2 * kt]), v3 = pl_cmul(src[j + 3 * m], tw[3 * kt]);
        pl_dft4(&v0, &v1, &v2, &v3, sign);
        dst[to] = v0;
        dst[to + ns] = v1;
        dst[to + 2 * ns] = v2;
        dst[to + 3 * ns] = v3;
    } else if (r == 2) {
        const float2 v0 = src[j], v1 = pl_cmul(src[j + m], tw[1 * kt]);
        dst[to] = v0 + v1;
        dst[to + ns] = v0 - v1;
    } else {
        float2 v[5];
        v[0] = src[j];
        for (int q = 1; q < r; q++)
            v[q] = pl_cmul(src[j + q * m], tw[q * kt]);
        for (int q = 0; q < r; q++) { /* the radix-r DFT */
            float2 acc = v[0];
            for (int t = 1; t < r; t++)
                acc += pl_cmul(v[t], tw[((q * t) % r) * m]);
            dst[to + q * ns] = acc;
        }
    }
}

/* One radix-r Stockham pass from `src` to `dst` (lines of n), ns the length of the
 * sub-transforms done so far: butterfly j (of n / r) has k = j mod ns and writes from
 * (j / ns) ns r + k. A group's items stride over the butterflies; one item alone walks
 * them block by block without divisions. */
inline void pl_stockham(__local const float2 *src, __local float2 *dst, int n, int r,
                        int ns, float sign, __global const float2 *tw)
{
    const int m = n / r;
#if PL_GROUP == 1
    for (int blk = 0, j = 0; blk < m / ns; blk++)
        for (int k = 0; k < ns; k++, j++)
            pl_butterfly(src, dst, j, k, blk * ns * r + k, n, m, r, ns, sign, tw);
#else
    const float inv = 1.0f / (float)ns;
    for (int j = get_local_id(0); j < m; j += PL_GROUP) {
        const int blk = (int)(((float)j + 0.5f) * inv); /* j / ns without an integer divide */
        const int k = j - blk * ns;
        pl_butterfly(src, dst, j, k, blk * ns * r + k, n, m, r, ns, sign, tw);
    }
#endif
}

/* The radix of the next pass over the `left` length still to do: 8 first, then 4, 2, 3, 5. */
inline int pl_radix(int left)
{
    return left % 8 == 0 ? 8 : left % 4 == 0 ? 4 : left % 2 == 0 ? 2 : left % 3 == 0 ? 3 : 5;
}

/* 1-D FFTs of length n along one axis of every box; global (lines PL_GROUP), local
 * (PL_GROUP). The lines are (b, u, v), u < nu, v < nv, line (b nu + u) nv + v starting
 * at b box + u su + v sv, its elements `step` apart: every line of an axis, or only those
 * of a padded box that hold window values (the rest are zeros and stay so). tw: the n
 * twiddles exp(sign 2 pi i t / n). */
__kernel void fft_lines(__global float2 *data, int n, int step, int nu, int su, int nv,
                        int sv, long box, float sign, __global const float2 *tw)
{
    __local float2 buf[2][PL_MAXN];
    const int line = get_group_id(0), lid = get_local_id(0);
    const int v = line % nv, u = (line / nv) % nu, b = line / (nv * nu);
    __global float2 *at = data + b * box + (long)u * su + (long)v * sv;
    for (int i = lid; i < n; i += PL_GROUP)
        buf[0][i] = at[(long)i * step];
    barrier(CLK_LOCAL_MEM_FENCE);
    int cur = 0;
    for (int ns = 1; ns < n; ) {
        const int r = pl_radix(n / ns);
        pl_stockham(buf[cur], buf[1 - cur], n, r, ns, sign, tw);
        barrier(CLK_LOCAL_MEM_FENCE);
        cur = 1 - cur;
        ns *= r;
    }
    for (int i = lid; i < n; i += PL_GROUP)
        at[(long)i * step] = buf[cur][i];
}

/* conj(A(k)) B(k) of window b's packed spectrum Z at k (the box of b). */
inline float2 pl_cross(__global const float2 *spec, long box, int b, int z, int y, int x,
                       int pz, int py, int px)
{
    const int mx = (px - x) % px, my = (py - y) % py, mz = (pz - z) % pz;
    const float2 zk = spec[b * box + ((long)z * py + y) * px + x];
    const float2 zm = spec[b * box + ((long)mz * py + my) * px + mx];
    const float2 a = 0.5f * (float2)(zk.x + zm.x, zk.y - zm.y);   /* (Z + conj Zm) / 2 */
    const float2 d = 0.5f * (float2)(zk.x - zm.x, zk.y + zm.y);   /* (Z - conj Zm) / 2 */
    const float2 bk = (float2)(d.y, -d.x);                         /* d / i */
    return (float2)(a.x * bk.x + a.y * bk.y, a.x * bk.y - a.y * bk.x);
}

/* The cross spectra of windows 2 j and 2 j + 1 as one box, S_2j + i S_2j+1 (both planes
 * are real, so one inverse transform gives them as its real and imaginary parts; an odd
 * last window alone); global (px, py, pz ceil(B / 2)). */
__kernel void cross_spectrum(__global const float2 *spec, int pz, int count,
                             __global float2 *out)
{
    const int x = get_global_id(0), y = get_global_id(1), zj = get_global_id(2);
    const int px = get_global_size(0), py = get_global_size(1);
    const int z = zj % pz, j = zj / pz;
    const long box = (long)pz * py * px;
    const float2 even = pl_cross(spec, box, 2 * j, z, y, x, pz, py, px);
    const float2 odd = 2 * j + 1 < count ? pl_cross(spec, box, 2 * j + 1, z, y, x, pz, py, px)
                                         : (float2)(0.0f, 0.0f);
    out[((long)zj * py + y) * px + x] = (float2)(even.x - odd.y, even.y + odd.x);
}

/* The circular distance between i and c on n. */
inline int pl_wrap_distance(int i, int c, int n)
{
    const int d = abs(i - c);
    return min(d, n - d);
}

/* Window b's plane value at flat index p: the real (even b) or imaginary (odd b) part of
 * box b / 2. */
#define PL_PLANE(p) (odd ? plane[p].y : plane[p].x)

/* The peak of each window's plane; global (B PL_GROUP), local (PL_GROUP). The items
 * stride over the plane's rows. */
__kernel void peak_fit(__global const float2 *data, int pz, int py, int px,
                       __global const float *moments, int exclude, __global float *out)
{
    __local float best[PL_GROUP];
    __local int where[PL_GROUP];
    __local float scratch[PL_GROUP];
    const int b = get_group_id(0), lid = get_local_id(0), odd = b & 1;
    __global const float2 *plane = data + (long)(b / 2) * pz * py * px;
    __global const float *m = moments + 8 * b;
    const int signal = m[1] > 1e-9f * m[2] && m[3] > 0.0f && m[5] > 1e-9f * m[6] && m[7] > 0.0f;
    const float norm = signal ? (float)(pz * py * px) * sqrt(m[3] * m[7]) : 1.0f;
    float top = -INFINITY;
    int at = 0;
    for (int row = lid; row < pz * py; row += PL_GROUP)
        for (int x = 0; x < px; x++) {
            const float q = PL_PLANE(row * px + x) / norm;
            if (q > top) {
                top = q;
                at = row * px + x;
            }
        }
    best[lid] = top;
    where[lid] = at;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int stride = PL_GROUP / 2; stride > 0; stride >>= 1) {
        if (lid < stride) {
            const float o = best[lid + stride];
            const int oi = where[lid + stride];
            if (o > best[lid] || (o == best[lid] && oi < where[lid])) {
                best[lid] = o;
                where[lid] = oi;
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    const float peak = best[0];
    const int c = where[0];
    const int cz = c / (py * px), cy = (c / px) % py, cx = c % px;
    float second = -INFINITY;
    for (int row = lid; row < pz * py; row += PL_GROUP) {
        const int z = row / py, y = row % py;
        const int near = pl_wrap_distance(z, cz, pz) <= exclude
                         && pl_wrap_distance(y, cy, py) <= exclude;
        for (int x = 0; x < px; x++)
            if (!near || pl_wrap_distance(x, cx, px) > exclude)
                second = fmax(second, PL_PLANE(row * px + x) / norm);
    }
    second = pl_group_max(scratch, second);
    if (lid == 0) {
        const int n[3] = {pz, py, px}, idx[3] = {cz, cy, cx};
        for (int axis = 0; axis < 3; axis++) {
            int lo[3] = {cz, cy, cx}, hi[3] = {cz, cy, cx};
            lo[axis] = (idx[axis] - 1 + n[axis]) % n[axis];
            hi[axis] = (idx[axis] + 1) % n[axis];
            const float cm = PL_PLANE((lo[0] * py + lo[1]) * px + lo[2]) / norm;
            const float cp = PL_PLANE((hi[0] * py + hi[1]) * px + hi[2]) / norm;
            const int whole = idx[axis] >= (n[axis] + 1) / 2 ? idx[axis] - n[axis] : idx[axis];
            out[6 * b + axis] = signal ? (float)whole + pl_subpixel(cm, peak, cp) : 0.0f;
        }
        out[6 * b + 3] = signal ? peak : 0.0f;
        out[6 * b + 4] = !signal ? 0.0f : second > 0.0f ? peak / second : INFINITY;
        out[6 * b + 5] = (float)signal;
    }
}
