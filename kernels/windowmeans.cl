/* The particle refinement's window means (docs/design.md §7.1, §7.5): per PIV window, the
 * local displacement gradient fitted to the pairs of its doubled box, then the mean of the
 * pairs of its box moved to its centre along that gradient, and its uncertainty.
 * NumPy twin: plenocl/piv/refinement.py (_local_gradients, _window_estimates, batched)
 * and plenocl/reference/refinement.py (window_means_reference, the per-window loop).
 *
 * In double precision (cl_khr_fp64; the host path serves devices without it): the pairs a
 * window keeps are a threshold on distances to medians, and in float32 a pair at the
 * threshold could flip, so the device keeps the host's decisions and its means agree with
 * the host's to rounding (about 1e-13 voxel).
 *
 * Data. Pairs p: midpoints mid[3p..] and displacements disp[3p..] (x, y, z voxels), the
 * weights weight[3p..] (per component; used where `weighted`), and the focal zone's
 * systematic depth uncertainty amb[p] (used where `focus`). Windows are listed: listed
 * window k is the grid window win[k] (flat over (nz, ny, nx), x fastest: centred at
 * (axes[kx], axes[nx + ky], axes[nx + ny + kz]), pl_centre), and its
 * pairs (at least one) are member[start[k] .. stop[k]), in pair order; the lists come from
 * box_tally, box_compact and box_fill below.
 *
 * A window's pairs near their median (near_median): per component c the median m_c of
 * its displacements d, and with spread >= 0 the reach min(search_c, max(spread x
 * median |d - m_c|, floor_c)) (spread: the robust rule's standard deviations times the
 * MAD's 1.4826, from the host; negative: no robust rule), else search_c; a pair is kept where
 * |d_c - m_c| <= reach_c for every c. Medians by selection on the window's own slice of
 * `scratch` (one double per member, at start[k]); an even count takes the mean of the two
 * middle values as NumPy does; once they are taken, the slice holds each pair's keep flag
 * (1 or 0), so the fits and sums below test it instead of the medians again.
 *
 * window_gradients: the gradient (3 x 3, component by axis) of the kept displacements over
 * the offsets from the window's centre, each component by least squares weighted by
 * its weights (or alike), from the normal equations of both centred on their weighted
 * means. Status 0: fewer than `min_keep` kept, gradient 0; 1: fitted; 2: a scatter
 * flatter than `well_posed` (least eigenvalue over largest) in some component: the host
 * fits it (np.linalg.lstsq, minimum norm). The gradient is written per grid window
 * (grad[9w..], which window_estimates reads), the status per listed window (status[k],
 * a byte: only the listed windows' statuses go back to the host).
 *
 * window_estimates: each pair's displacement moved to the centre, d - G (mid - centre);
 * the kept count; where at least `min_count` are kept, per component the weighted mean,
 * and its uncertainty: the random part sqrt(spread / n_eff) t[n] (t: Student's quantile
 * for n kept pairs, from the host), the focal zone's mean ambiguity (depth), and the
 * position sigma carried through the gradient, added in quadrature; NaN elsewhere. Written
 * per listed window (count[k], mean[3k..], error[3k..]): only the listed windows' results go
 * back to the host, which places them in the grid.
 *
 * box_range: per pair, along one axis, the windows whose box holds it as an index range
 * [lo, hi): the run of centres c with |m / box - c / box| <= radius (m: the pair's
 * midpoint on that axis; the same doubles and test as the host's _axis_range, whose
 * k-d tree twin is cKDTree.query_ball_point with p = inf), found by a binary search for
 * the first centre at or past m / box - radius, less one to spare, then a scan; an empty
 * run gives lo == hi. Made from the pairs already on the device, so no range crosses.
 *
 * box_counts, box_fill: the pairs within a box about each listed window's centre: the
 * host or box_range gives, per pair, the windows whose box holds it along each axis as
 * index ranges [x0, x1) (and the same in y and z); the pairs are bucketed by the (z, y)
 * row of windows they cover (bucket_start over nz * ny rows, bucket_pts in pair order:
 * from their z and y ranges on the device, kernels/rowlists.cl boxes_fill); a window
 * (kz, ky, kx) scans its row's bucket for the pairs with x0 <= kx < x1: box_tally counts
 * them, box_fill writes them (in pair order, as the host's box search lists them).
 *
 * box_tally, box_compact: the listed windows and their tables, made without the host.
 * box_tally counts every window of the grid (count[w]: 0 where not wanted, a byte per
 * window, wanted[w]), flags the windows listed (at least `least` pairs: listed[w], a
 * byte, which the next call may take as its wanted, and flag[w], an int to scan) and
 * their pair counts (held[w], 0 where not listed); the rows' scan
 * (kernels/rowlists.cl scan_starts) turns the flags into each listed window's slot and
 * the held counts into its first member; box_compact writes win, start and stop per
 * slot, for box_fill and the kernels above. Only the listed windows' indices go back.
 *
 * Parallel structure: one work-item per listed window (thousands per call), each looping
 * over its own pairs (box_range: one per pair, a search over one axis's centres;
 * box_tally and box_compact: one per grid window, each writing its own slot); no
 * atomics, no shared writes (each item writes its window's outputs, or its pair's range,
 * and its own scratch slice). Items read the pairs they list from global memory, so on a
 * GPU the reads are gathers; the work is a few hundred operations per pair and the
 * kernels take milliseconds. Sizes are arguments. */

#pragma OPENCL EXTENSION cl_khr_fp64 : enable

/* Window w's centre (x, y, z) from the field's axes (x: nx, then y: ny, then z). */
inline void pl_centre(__global const double *axes, int nx, int ny, int w, double *cen)
{
    cen[0] = axes[w % nx];
    cen[1] = axes[nx + (w / nx) % ny];
    cen[2] = axes[nx + ny + w / (nx * ny)];
}

/* Exchange a[i] and a[j]. */
inline void pl_swap(__global double *a, int i, int j)
{
    const double t = a[i];
    a[i] = a[j];
    a[j] = t;
}

/* The k-th smallest of a[0 .. n) (0-based), reordering a: quickselect with a
 * three-way partition about the middle element, so runs of equal values end it at once. */
double pl_select(__global double *a, int n, int k)
{
    int lo = 0, hi = n - 1;
    while (lo < hi) {
        const double pivot = a[lo + (hi - lo) / 2];
        int lt = lo, i = lo, gt = hi;
        while (i <= gt) {
            if (a[i] < pivot)
                pl_swap(a, lt++, i++);
            else if (a[i] > pivot)
                pl_swap(a, i, gt--);
            else
                ++i;
        }
        if (k < lt)
            hi = lt - 1;
        else if (k > gt)
            lo = gt + 1;
        else
            return pivot;
    }
    return a[k];
}

/* NumPy's median of a[0 .. n) (n >= 1), reordering a. */
double pl_median(__global double *a, int n)
{
    const double upper = pl_select(a, n, n / 2);
    if (n % 2)
        return upper;
    double lower = a[0];  /* the largest of the n / 2 values below the upper middle */
    for (int i = 1; i < n / 2; ++i)
        lower = fmax(lower, a[i]);
    return (lower + upper) / 2.0;
}

/* Pair p's displacement component c, moved to the centre cen along the gradient g
 * (NULL-like: moved = 0 leaves it). */
inline double pl_moved(__global const double *mid, __global const double *disp, int p,
                       int c, const double *cen, const double *g, int moved)
{
    double d = disp[3 * p + c];
    if (moved)
        for (int a = 0; a < 3; ++a)
            d -= g[3 * c + a] * (mid[3 * p + a] - cen[a]);
    return d;
}

/* The near-median test of one window's n pairs member[0 .. n): its medians `median` and
 * reaches `reach` (3 each), using scratch[0 .. n). */
void pl_near_median(__global const double *mid, __global const double *disp,
                    __global const int *member, int n, const double *cen, const double *g,
                    int moved, __global double *scratch, double3 search, double spread,
                    double3 floor_, double *median, double *reach)
{
    const double s[3] = {search.x, search.y, search.z};
    const double f[3] = {floor_.x, floor_.y, floor_.z};
    for (int c = 0; c < 3; ++c) {
        for (int i = 0; i < n; ++i)
            scratch[i] = pl_moved(mid, disp, member[i], c, cen, g, moved);
        median[c] = pl_median(scratch, n);
        reach[c] = s[c];
        if (spread >= 0.0) {
            for (int i = 0; i < n; ++i)
                scratch[i] = fabs(pl_moved(mid, disp, member[i], c, cen, g, moved) - median[c]);
            reach[c] = fmin(s[c], fmax(spread * pl_median(scratch, n), f[c]));
        }
    }
}

/* Whether pair p is kept by the medians and reaches. */
inline int pl_kept(__global const double *mid, __global const double *disp, int p,
                   const double *cen, const double *g, int moved, const double *median,
                   const double *reach)
{
    int keep = 1;
    for (int c = 0; c < 3; ++c)
        keep &= fabs(pl_moved(mid, disp, p, c, cen, g, moved) - median[c]) <= reach[c];
    return keep;
}

/* Eigenvalues' extremes of the symmetric 3 x 3 matrix m (row-major): the least and the
 * largest, by the trigonometric solution of the characteristic cubic. */
void pl_eig_extremes(const double *m, double *least, double *largest)
{
    const double p1 = m[1] * m[1] + m[2] * m[2] + m[5] * m[5];
    const double q = (m[0] + m[4] + m[8]) / 3.0;
    if (p1 == 0.0) {
        *least = fmin(fmin(m[0], m[4]), m[8]);
        *largest = fmax(fmax(m[0], m[4]), m[8]);
        return;
    }
    const double a = m[0] - q, e = m[4] - q, i = m[8] - q;
    const double p = sqrt((a * a + e * e + i * i + 2.0 * p1) / 6.0);
    /* det((m - q I) / p) / 2 */
    const double r = (a * (e * i - m[5] * m[5]) - m[1] * (m[1] * i - m[5] * m[2])
                      + m[2] * (m[1] * m[5] - e * m[2])) / (2.0 * p * p * p);
    const double phi = acos(clamp(r, -1.0, 1.0)) / 3.0;
    *largest = q + 2.0 * p * cos(phi);
    *least = q + 2.0 * p * cos(phi + 2.0943951023931957);
}

/* Solve the symmetric 3 x 3 system m x = b (row-major m) by Cramer's rule. */
void pl_solve3(const double *m, const double *b, double *x)
{
    const double c0 = m[4] * m[8] - m[5] * m[7];
    const double c1 = m[5] * m[6] - m[3] * m[8];
    const double c2 = m[3] * m[7] - m[4] * m[6];
    const double det = m[0] * c0 + m[1] * c1 + m[2] * c2;
    x[0] = (b[0] * c0 + m[1] * (m[5] * b[2] - b[1] * m[8]) + m[2] * (b[1] * m[7] - m[4] * b[2])) / det;
    x[1] = (m[0] * (b[1] * m[8] - m[5] * b[2]) + b[0] * c1 + m[2] * (m[3] * b[2] - b[1] * m[6])) / det;
    x[2] = (m[0] * (m[4] * b[2] - b[1] * m[7]) + m[1] * (b[1] * m[6] - m[3] * b[2]) + b[0] * c2) / det;
}

/* One component c of the weighted gradient fit of window `members`, the pairs whose
 * `keep` flag is set: g_row (3) and whether the scatter is well posed. */
int pl_fit_component(__global const double *mid, __global const double *disp,
                     __global const double *weight, int weighted, __global const int *member,
                     __global const double *keep, int n, const double *cen, int c,
                     double well_posed, double *g_row)
{
    double total = 0.0, xm[3] = {0}, ym = 0.0;
    for (int i = 0; i < n; ++i) {
        const int p = member[i];
        if (keep[i] == 0.0)
            continue;
        const double w = weighted ? weight[3 * p + c] : 1.0;
        total += w;
        for (int a = 0; a < 3; ++a)
            xm[a] += w * (mid[3 * p + a] - cen[a]);
        ym += w * disp[3 * p + c];
    }
    for (int a = 0; a < 3; ++a)
        xm[a] /= total;
    ym /= total;
    double m[9] = {0}, b[3] = {0};
    for (int i = 0; i < n; ++i) {
        const int p = member[i];
        if (keep[i] == 0.0)
            continue;
        const double w = weighted ? weight[3 * p + c] : 1.0;
        double x[3];
        for (int a = 0; a < 3; ++a)
            x[a] = mid[3 * p + a] - cen[a] - xm[a];
        const double y = disp[3 * p + c] - ym;
        for (int a = 0; a < 3; ++a) {
            for (int e = 0; e < 3; ++e)
                m[3 * a + e] += w * x[a] * x[e];
            b[a] += w * x[a] * y;
        }
    }
    double least, largest;
    pl_eig_extremes(m, &least, &largest);
    if (!(least > well_posed * largest))
        return 0;
    pl_solve3(m, b, g_row);
    return 1;
}

__kernel void window_gradients(__global const double *mid, __global const double *disp,
                               __global const double *weight, int weighted,
                               __global const int *win, __global const int *start,
                               __global const int *stop, __global const int *member,
                               __global const double *axes, int nx, int ny, int listed,
                               double3 search,
                               double spread, double3 floor_,
                               int min_keep, double well_posed, __global double *scratch,
                               __global double *grad, __global uchar *status)
{
    const int k = get_global_id(0);
    if (k >= listed)
        return;
    const int w = win[k], s = start[k], n = stop[k] - s;
    double cen[3];
    pl_centre(axes, nx, ny, w, cen);
    const double zero[9] = {0};
    double median[3], reach[3], g[9] = {0};
    pl_near_median(mid, disp, member + s, n, cen, zero, 0, scratch + s, search, spread,
                   floor_, median, reach);
    int kept = 0;
    for (int i = 0; i < n; ++i) {  /* the medians done, scratch holds the keep flags */
        const int keep = pl_kept(mid, disp, member[s + i], cen, zero, 0, median, reach);
        scratch[s + i] = keep;
        kept += keep;
    }
    int state = kept >= min_keep;
    for (int c = 0; c < 3 && state == 1; ++c)
        if (!pl_fit_component(mid, disp, weight, weighted, member + s, scratch + s, n, cen,
                              c, well_posed, g + 3 * c))
            state = 2;
    for (int e = 0; e < 9; ++e)
        grad[9 * w + e] = state == 1 ? g[e] : 0.0;
    status[k] = (uchar)state;
}

__kernel void window_estimates(__global const double *mid, __global const double *disp,
                               __global const double *weight, int weighted,
                               __global const double *amb, int focus,
                               __global const int *win, __global const int *start,
                               __global const int *stop, __global const int *member,
                               __global const double *axes, int nx, int ny, int listed,
                               __global const double *grad, double3 search, double spread,
                               double3 floor_, int min_count,
                               __global const double *t, double3 position_sigma,
                               __global double *scratch, __global int *count,
                               __global double *mean, __global double *error)
{
    const int k = get_global_id(0);
    if (k >= listed)
        return;
    const int w = win[k], s = start[k], n = stop[k] - s;
    __global const int *mem = member + s;
    double cen[3];
    pl_centre(axes, nx, ny, w, cen);
    double g[9];
    for (int e = 0; e < 9; ++e)
        g[e] = grad[9 * w + e];
    double median[3], reach[3];
    pl_near_median(mid, disp, mem, n, cen, g, 1, scratch + s, search, spread, floor_,
                   median, reach);
    __global double *keep = scratch + s;  /* the medians done: the keep flags */
    int kept = 0;
    double ambiguity = 0.0;
    for (int i = 0; i < n; ++i) {
        keep[i] = pl_kept(mid, disp, mem[i], cen, g, 1, median, reach);
        if (keep[i] != 0.0) {
            ++kept;
            ambiguity += focus ? amb[mem[i]] : 0.0;
        }
    }
    count[k] = kept;
    const double ps[3] = {position_sigma.x, position_sigma.y, position_sigma.z};
    for (int c = 0; c < 3; ++c) {
        double total = 0.0, total2 = 0.0, sum = 0.0;
        for (int i = 0; i < n; ++i)
            if (keep[i] != 0.0) {
                const double wt = weighted ? weight[3 * mem[i] + c] : 1.0;
                total += wt;
                total2 += wt * wt;
                sum += wt * pl_moved(mid, disp, mem[i], c, cen, g, 1);
            }
        const double mu = sum / total;
        double dev = 0.0;
        for (int i = 0; i < n; ++i)
            if (keep[i] != 0.0) {
                const double wt = weighted ? weight[3 * mem[i] + c] : 1.0;
                const double r = pl_moved(mid, disp, mem[i], c, cen, g, 1) - mu;
                dev += wt * r * r;
            }
        const double n_eff = total * total / total2;
        const double spread_c = dev / total * n_eff / (n_eff - 1.0);
        const double random = sqrt(spread_c / n_eff) * t[kept];
        const double systematic = (c == 2 && focus) ? ambiguity / kept : 0.0;
        double position = 0.0;
        for (int a = 0; a < 3; ++a)
            position += (g[3 * c + a] * ps[a]) * (g[3 * c + a] * ps[a]);
        position = sqrt(position);
        const int use = kept >= min_count;
        mean[3 * k + c] = use ? mu : NAN;
        error[3 * k + c] = use ? sqrt(random * random + systematic * systematic
                                      + position * position) : NAN;
    }
}

__kernel void box_range(__global const double *mid, int pairs, int axis, double box,
                        __global const double *axes, int first, int n, double radius,
                        __global int *lo, __global int *hi)
{
    const int p = get_global_id(0);
    if (p >= pairs)
        return;
    __global const double *c = axes + first;
    const double m = mid[3 * p + axis] / box;
    int a = 0, b = n;  /* the first centre with c / box >= m - radius */
    while (a < b) {
        const int h = (a + b) / 2;
        if (c[h] / box < m - radius)
            a = h + 1;
        else
            b = h;
    }
    int i = max(a - 1, 0);
    while (i < n && !(fabs(m - c[i] / box) <= radius) && c[i] / box < m)
        ++i;
    lo[p] = i;
    while (i < n && fabs(m - c[i] / box) <= radius)
        ++i;
    hi[p] = i;
}

__kernel void box_fill(__global const int *bucket_start, __global const int *bucket_pts,
                       __global const int *x0, __global const int *x1,
                       __global const int *win, int listed, int nx,
                       __global const int *start, __global int *member)
{
    const int k = get_global_id(0);
    if (k >= listed)
        return;
    const int kx = win[k] % nx, row = win[k] / nx;
    int j = start[k];
    for (int i = bucket_start[row]; i < bucket_start[row + 1]; ++i) {
        const int p = bucket_pts[i];
        if (x0[p] <= kx && kx < x1[p])
            member[j++] = p;
    }
}

__kernel void box_tally(__global const int *bucket_start, __global const int *bucket_pts,
                        __global const int *x0, __global const int *x1,
                        __global const uchar *wanted, int windows, int nx, int least,
                        __global uchar *listed, __global int *flag, __global int *count,
                        __global int *held)
{
    const int w = get_global_id(0);
    if (w >= windows)
        return;
    int n = 0;
    if (wanted[w]) {
        const int kx = w % nx, row = w / nx;
        for (int i = bucket_start[row]; i < bucket_start[row + 1]; ++i) {
            const int p = bucket_pts[i];
            n += x0[p] <= kx && kx < x1[p];
        }
    }
    const int use = wanted[w] && n >= least;
    listed[w] = (uchar)use;
    flag[w] = use;
    count[w] = n;
    held[w] = use ? n : 0;
}

__kernel void box_compact(__global const uchar *listed, __global const int *slot,
                          __global const int *first, __global const int *held, int windows,
                          __global int *win, __global int *start, __global int *stop)
{
    const int w = get_global_id(0);
    if (w >= windows || !listed[w])
        return;
    const int k = slot[w];
    win[k] = w;
    start[k] = first[w];
    stop[k] = first[w] + held[w];
}
