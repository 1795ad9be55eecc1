/* Row lists: for each row of a table, the items whose range of rows holds it, in item
 * order, as one CSR list (docs/design.md §7.5). The host counts each row's items from the
 * ranges alone (a difference array: items + rows operations) and sums the counts into
 * each row's start; these kernels write the items, so only the ranges and the starts
 * cross to the device, not the lists. NumPy twin: plenocl.reference.rowlists.
 *
 * - rows_fill: the items of rows [0, rows), item p holding rows [lo[p], hi[p]).
 * - boxes_fill: the rows of a (na, nb) table (row a * nb + b); item p holds the box
 *   [lo_a[p], hi_a[p]) x [lo_b[p], hi_b[p]).
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
