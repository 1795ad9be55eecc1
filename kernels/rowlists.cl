/* Row lists: for each row of a table, the items whose range of rows holds it, in item
 * order, as one CSR list (docs/design.md §7.5). The host counts each row's items from the
 * ranges alone (a difference array: items + rows operations) and sums the counts into
 * each row's start; these kernels write the items, so only the ranges and the starts
 * cross to the device, not the lists. NumPy twin: plenocl.reference.rowlists.
 *
 * - rows_fill: the items of rows [0, rows), item p holding rows [lo[p], hi[p]).
 * - boxes_fill: the rows of a (na, nb) table (row a * nb + b); item p holds the box
 *   [lo_a[p], hi_a[p]) x [lo_b[p], hi_b[p]).
 * - boxes_count: each such row's item count, where the ranges were made on the device
 *   (the window means' box_range): the host reads the counts (one int per row) and sums
 *   them into the starts, so the ranges never cross.
 *
 * - scan_starts: each row's start from the rows' counts made on the device (an exclusive
 *   prefix sum, start[n] the total) and the largest count, so that neither the counts
 *   nor the starts cross: one work-group of PL_SCAN items, each summing its own run of
 *   about n / PL_SCAN counts, the runs' sums scanned in local memory (Hillis-Steele,
 *   log2 PL_SCAN steps), then each item writing its run's starts. The tables scanned
 *   are the window means' (thousands to some hundred thousand windows): one group is
 *   a few microseconds of a GPU, not worth a second pass over several groups.
 *
 * Parallel structure: one work-item per row, looping over every item in order and
 * writing its own slice of `list` (from start[row]): no atomics, no shared writes, and
 * the order within a row is the items' whatever the device. Every item reads the same
 * ranges in the same order (a broadcast, cached on a GPU; vectorised across rows on a
 * CPU). The work is rows x items comparisons, a few milliseconds at the paper's size
 * (3,282 sensor rows x 2,789 particles) on two CPU cores. Sizes are arguments. */

__kernel void rows_fill(__global const int *lo, __global const int *hi, int items, int rows,
                        __global const int *start, __global int *list)
{
    const int r = get_global_id(0);
    if (r >= rows)
        return;
    int k = start[r];
    for (int p = 0; p < items; ++p)
        if (lo[p] <= r && r < hi[p])
            list[k++] = p;
}

__kernel void boxes_fill(__global const int *lo_a, __global const int *hi_a,
                         __global const int *lo_b, __global const int *hi_b, int items,
                         int na, int nb, __global const int *start, __global int *list)
{
    const int r = get_global_id(0);
    if (r >= na * nb)
        return;
    const int a = r / nb, b = r % nb;
    int k = start[r];
    for (int p = 0; p < items; ++p)
        if (lo_a[p] <= a && a < hi_a[p] && lo_b[p] <= b && b < hi_b[p])
            list[k++] = p;
}

__kernel void boxes_count(__global const int *lo_a, __global const int *hi_a,
                          __global const int *lo_b, __global const int *hi_b, int items,
                          int na, int nb, __global int *count)
{
    const int r = get_global_id(0);
    if (r >= na * nb)
        return;
    const int a = r / nb, b = r % nb;
    int n = 0;
    for (int p = 0; p < items; ++p)
        n += lo_a[p] <= a && a < hi_a[p] && lo_b[p] <= b && b < hi_b[p];
    count[r] = n;
}

#ifndef PL_SCAN
#define PL_SCAN 64
#endif

__kernel void scan_starts(__global const int *count, int n, __global int *start,
                          __global int *largest)
{
    __local int run_sum[PL_SCAN], run_max[PL_SCAN];
    const int t = get_local_id(0);
    const int per = (n + PL_SCAN - 1) / PL_SCAN;
    const int a = min(t * per, n), b = min(a + per, n);
    int sum = 0, most = 0;
    for (int i = a; i < b; ++i) {
        sum += count[i];
        most = max(most, count[i]);
    }
    run_sum[t] = sum;
    run_max[t] = most;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int d = 1; d < PL_SCAN; d <<= 1) {
        const int s = t >= d ? run_sum[t - d] : 0;
        const int m = t >= d ? run_max[t - d] : 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        run_sum[t] += s;
        run_max[t] = max(run_max[t], m);
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    int at = run_sum[t] - sum;  /* the counts before this item's run */
    for (int i = a; i < b; ++i) {
        start[i] = at;
        at += count[i];
    }
    if (t == PL_SCAN - 1) {
        start[n] = run_sum[t];
        largest[0] = run_max[t];
    }
}
