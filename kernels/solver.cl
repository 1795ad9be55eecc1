/* Element-wise steps of the multiplicative solvers (docs/design.md §6). NumPy twin:
 * plenocl/reference/reconstruct.py. Guards: the ratio I / max(P, eps) is clamped,
 * exponents are clamped, and a non-finite or negative voxel becomes 0, so no NaN or
 * Inf ever leaves a kernel. Sizes are arguments; one build serves every shape.
 *
 * Parallel structure: one work-item per pixel (ratio, prepare_image) or per voxel
 * (update_*, mlos, mask_dark, add_into); partial_sums is the first level of a deterministic
 * two-level reduction (1024 work-items, each a strided or contiguous run; the host adds
 * their partial sums in double precision); row_extent has one work-item per volume row.
 * No atomics anywhere. */

#define PL_EPS 1e-12f
#define PL_RATIO_MIN 1e-6f
#define PL_RATIO_MAX 1e6f
#define PL_EXP_CLAMP 30.0f
#define PL_VOXEL_MAX 1e30f

inline float pl_clean(float v)
{
    return (isfinite(v) && v > 0.0f) ? fmin(v, PL_VOXEL_MAX) : 0.0f;
}

/* out = I / max(P, eps) (clamped) or log(max(ratio, ratio_min)); pixels at or below
 * threshold are dark (I = 0). ratio_min is PL_RATIO_MIN for the literal SMART/MART (a dark
 * pixel's log ratio is -13.8) or a larger documented floor (ReconstructionSettings
 * .ratio_floor). With a block map, pixels outside block `block` get 0 (no update). With
 * use_observed, a pixel whose observed[i] is 0 holds no data and gets 0 too: it is left
 * out of the update, and the solver's sensitivity is then A^T observed (MLEM of the
 * observed pixels alone). */
__kernel void ratio(__global const float *img, __global const float *proj,
                    __global const int *block_of, int block, float threshold,
                    int log_mode, float ratio_min, __global const float *observed,
                    int use_observed, __global float *out, int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    if (block >= 0 && block_of[i] != block) { out[i] = 0.0f; return; }
    if (use_observed && observed[i] == 0.0f) { out[i] = 0.0f; return; }
    float value = img[i] > threshold ? img[i] : 0.0f;
    float r = clamp(value / fmax(proj[i], PL_EPS), 0.0f, PL_RATIO_MAX);
    out[i] = log_mode ? log(fmax(r, fmax(ratio_min, PL_RATIO_MIN))) : r;
}

/* f^mu for f >= 0: the two relaxations in use (1, and MLEM's over-relaxation 1.5: a
 * square root instead of pow, 5.5x faster on PoCL over a sub-voxel grid:
 * benchmarks/reconstruct.py --relax-only) exactly as written, any other by pow. */
inline float pl_power(float f, float mu)
{
    if (mu == 1.0f) return f;
    if (mu == 1.5f) return f * sqrt(f);
    return pow(f, mu);
}

/* Multiplicative EM: E <- E (b / s)^mu with b = W^T r (the arithmetic mean of ratios).
 * Voxels whose sensitivity s (the fraction of their light that reaches the sensor) is
 * at or below smin are not constrained by the image and stay 0. */
__kernel void update_mlem(__global float *vol, __global const float *b,
                          __global const float *sens, float relax, float smin, int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    float s = sens[j], e = vol[j];
    if (s <= smin || !(e > 0.0f)) { vol[j] = 0.0f; return; }
    float f = fmax(b[j], 0.0f) / s;
    vol[j] = pl_clean(e * pl_power(f, relax));
}

/* Exponential update: E <- E exp(mu b / s) (SMART, by_sens = 1) or E exp(mu b) (MART
 * block, the paper's exponent mu w_ij), with b = W^T log r. */
__kernel void update_exp(__global float *vol, __global const float *b,
                         __global const float *sens, float relax, float smin, int by_sens,
                         int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    float s = sens[j], e = vol[j];
    if (s <= smin || !(e > 0.0f)) { vol[j] = 0.0f; return; }
    float x = relax * b[j] / (by_sens ? s : 1.0f);
    vol[j] = pl_clean(e * exp(clamp(x, -PL_EXP_CLAMP, PL_EXP_CLAMP)));
}

/* a += b: several cameras' back projections summed (reconstruction/joint.py). A plain
 * kernel, one item per voxel: pyopencl's Array arithmetic loops each work-item over a
 * strided range, which PoCL runs 50-70x slower on a paper-size sub-voxel volume. */
__kernel void add_into(__global float *a, __global const float *b, int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    a[j] += b[j];
}

/* MLOS first guess: the weighted geometric mean of the pixels a voxel reaches,
 * E = exp(b / s) with b = W^T log(max(I, floor)). */
__kernel void mlos(__global float *vol, __global const float *b, __global const float *sens,
                   float smin, int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    float s = sens[j];
    vol[j] = s > smin ? pl_clean(exp(clamp(b[j] / s, -80.0f, 80.0f))) : 0.0f;
}

/* Zero-pixel masking: zero the voxels that send more than `fraction` of their light
 * onto dark pixels (b = W^T dark, dark = 1 on pixels at or below the threshold). */
__kernel void mask_dark(__global float *vol, __global const float *b,
                        __global const float *sens, float fraction, int n)
{
    const int j = get_global_id(0);
    if (j >= n) return;
    float s = sens[j];
    if (s <= PL_EPS || b[j] > fraction * s) vol[j] = 0.0f;
}

/* dark = 1 where I <= threshold, else 0 (a pixel without data, use_observed and
 * observed[i] = 0, is not dark); logimg = log(max(I, floor)). */
__kernel void prepare_image(__global const float *img, float threshold, float floor_value,
                            __global const float *observed, int use_observed,
                            __global float *dark, __global float *logimg, int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    float v = img[i];
    const int unseen = use_observed && observed[i] == 0.0f;
    dark[i] = (v <= threshold && !unseen) ? 1.0f : 0.0f;
    logimg[i] = log(fmax(v, floor_value));
}

/* Partial sums for the host to finish, of a (mode 0) or of (a - b)^2 (mode 1), with
 * Kahan compensation; deterministic. Work-item g sums elements g, g + G, g + 2G, ...
 * (chunk = 0: coalesced, for GPUs) or the contiguous run [g chunk, (g + 1) chunk)
 * (chunk > 0: one cache line after the other, for CPUs). */
__kernel void partial_sums(__global const float *a, __global const float *b, int mode,
                           int chunk, __global float *out, int n)
{
    const int g = get_global_id(0);
    const int start = chunk ? g * chunk : g, step = chunk ? 1 : (int)get_global_size(0);
    const int end = chunk ? min(start + chunk, n) : n;
    float sum = 0.0f, comp = 0.0f;
    for (int i = start; i < end; i += step) {
        float x = mode ? (a[i] - b[i]) * (a[i] - b[i]) : a[i];
        float y = x - comp, t = sum + y;
        comp = (t - sum) - y;
        sum = t;
    }
    out[g] = sum;
}

/* First and last non-zero voxel of every volume row (one work-item per (z, y) row of a
 * slab; (nx, -1) for an empty row). From them slice_extent (below) gives each depth
 * slice's extent, and the host the slices that can still be non-zero and the bounding
 * box of the non-zero voxels without copying the volume: multiplicative updates never
 * revive a zero voxel, so what is zero stays out of every later projection. */
__kernel void row_extent(__global const float *vol, int nx, __global int2 *out, int nrows)
{
    const int r = get_global_id(0);
    if (r >= nrows) return;
    __global const float *row = vol + (size_t)r * nx;
    int first = nx, last = -1;
    for (int i = 0; i < nx; ++i)
        if (row[i] != 0.0f) {
            first = first < nx ? first : i;
            last = i;
        }
    out[r] = (int2)(first, last);
}

/* Each depth slice's extent from its rows' (row_extent above): (first and last row with a
 * non-zero voxel, first and last non-zero x over those rows), (ny, -1, nx, -1) for an
 * empty slice; so only nz x 4 ints cross to the host each iteration (the slices still
 * active, the box to crop to). Parallel structure: one work-item per depth slice, a loop
 * over its rows' extents; no atomics. */
__kernel void slice_extent(__global const int2 *rows, int ny, int nx, __global int4 *out,
                           int nz)
{
    const int z = get_global_id(0);
    if (z >= nz) return;
    __global const int2 *slice = rows + (size_t)z * ny;
    int4 e = (int4)(ny, -1, nx, -1);
    for (int y = 0; y < ny; ++y) {
        const int2 r = slice[y];
        if (r.y < 0) continue;
        e.x = min(e.x, y);
        e.y = y;
        e.z = min(e.z, r.x);
        e.w = max(e.w, r.y);
    }
    out[z] = e;
}
