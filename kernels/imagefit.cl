/* The image fit's per-particle sums on the device (docs/design.md §7.2): the model image
 * of all particles, each particle's Gauss-Newton normal equations against the residual
 * and its residual's scatter, and the start intensity's least-squares sums. They read
 * the rows kernels/raybundle.cl renders (dense patches, one after another from each
 * particle's offset; value, d/dX', d/dY', d/dd', d/dI rows of `total` elements).
 * NumPy twin: plenocl.reference.imagefit (float64 there, float32 here).
 *
 * Three kernels, all gathers without atomics:
 * - patch_model: one work-item per (block of `block` columns, sensor row). It zeroes its
 *   pixels, then adds every patch that covers its row (the host's CSR table lists them
 *   in particle order), so each pixel is written by one item, in a fixed order.
 * - normal_sums: one work-group of PL_GROUP items per particle. The items share the
 *   patch's columns row by row (a row's sums kept apart, then added: two-level float32
 *   sums); a tree in local memory adds the items. Two passes: J^T J (10), J^T r (4) and
 *   the brightest value; then the lit elements (value above 1 % of the brightest) and
 *   their squared residuals. 16 floats per particle out.
 * - unit_sums: one work-group per particle: sum(unit * image) and sum(unit^2) of the unit
 *   image (the value row rendered at intensity 1).
 * The image is read as data * data_scale: the fit's image as the reconstruction's solver
 * read it (divided by its brightest pixel: plenocl.optics.rawimage.ScaledImage), where
 * the reconstruction left it on the device; one multiply a pixel, no second upload.
 * On a GPU PL_GROUP is wide (a group's items read adjacent elements of a row); on a CPU
 * it is 1 (one item loops over its particle's patch; KernelSet's looping rule). Sizes are
 * arguments: a new particle count, patch or sensor never recompiles. */
#include "groupreduce.h" /* PL_GROUP, pl_group_sum, pl_group_max */

#define PL_NORMALS 16 /* floats per particle out of normal_sums, layout below */
/* 0-9 J^T J upper triangle row by row (00 01 02 03 11 12 13 22 23 33), 10-13 J^T r,
 * 14 lit elements, 15 sum of their squared residuals */

/* The patch rows of particle p that lie on the sensor: *rows_on, *cols_on. */
inline void pl_on_sensor(int p, __global const int *col0, __global const int *row0,
                         __global const int *width, __global const int *height, int cols,
                         int rows, int *rows_on, int *cols_on)
{
    *rows_on = clamp(rows - row0[p], 0, height[p]);
    *cols_on = clamp(cols - col0[p], 0, width[p]);
}

/* values: the value row; row_start (rows + 1), row_list: the particles whose patch covers
 * each sensor row, in particle order; model: rows x cols. */
__kernel void patch_model(__global const float *values, __global const long *offset,
                          __global const int *col0, __global const int *row0,
                          __global const int *width, __global const int *row_start,
                          __global const int *row_list, int cols, int block,
                          __global float *model)
{
    int b = get_global_id(0), r = get_global_id(1);
    int lo = b * block, hi = min(lo + block, cols);
    __global float *line = model + (long)r * cols;
    for (int c = lo; c < hi; ++c)
        line[c] = 0.0f;
    for (int k = row_start[r]; k < row_start[r + 1]; ++k) {
        int p = row_list[k], c0 = col0[p], wd = width[p];
        __global const float *src = values + offset[p] + (long)(r - row0[p]) * wd - c0;
        int from = max(lo, c0), to = min(hi, c0 + wd);
        for (int c = from; c < to; ++c)
            line[c] += src[c];
    }
}

/* rows: 5 rows of `total`; data, model: the sensor (rows x cols), the image being
 * data * data_scale (see unit_sums); jac: per particle d (X', Y', d') / d (x, y, z),
 * 3 x 3 row-major; out: PL_NORMALS per particle. */
__kernel void normal_sums(__global const float *patch_rows, long total,
                          __global const float *data, float data_scale,
                          __global const float *model,
                          __global const long *offset, __global const int *col0,
                          __global const int *row0, __global const int *width,
                          __global const int *height, int cols, int rows,
                          __global const float *jac, __global float *out)
{
    __local float scratch[PL_GROUP];
    int p = get_group_id(0), lid = get_local_id(0), wd = width[p];
    int rows_on, cols_on;
    pl_on_sensor(p, col0, row0, width, height, cols, rows, &rows_on, &cols_on);
    float m[9];
    for (int i = 0; i < 9; ++i)
        m[i] = jac[9 * p + i];
    float sums[14] = {0.0f}, peak = 0.0f;
    for (int r = 0; r < rows_on; ++r) {
        long base = offset[p] + (long)r * wd, pix = (long)(row0[p] + r) * cols + col0[p];
        float line[14] = {0.0f};
        for (int c = lid; c < cols_on; c += PL_GROUP) {
            __global const float *e = patch_rows + base + c;
            float a = e[total], b = e[2 * total], d = e[3 * total];
            float j[4] = {a * m[0] + b * m[3] + d * m[6], a * m[1] + b * m[4] + d * m[7],
                          a * m[2] + b * m[5] + d * m[8], e[4 * total]};
            float res = data[pix + c] * data_scale - model[pix + c];
            peak = fmax(peak, e[0]);
            for (int i = 0, k = 0; i < 4; ++i) {
                for (int q = i; q < 4; ++q, ++k)
                    line[k] += j[i] * j[q];
                line[10 + i] += j[i] * res;
            }
        }
        for (int k = 0; k < 14; ++k)
            sums[k] += line[k];
    }
    for (int k = 0; k < 14; ++k) {
        float total_k = pl_group_sum(scratch, sums[k]);
        if (lid == 0)
            out[PL_NORMALS * p + k] = total_k;
    }
    float lit_from = 0.01f * pl_group_max(scratch, peak), count = 0.0f, square = 0.0f;
    for (int r = 0; r < rows_on; ++r) {
        long base = offset[p] + (long)r * wd, pix = (long)(row0[p] + r) * cols + col0[p];
        float line = 0.0f;
        for (int c = lid; c < cols_on; c += PL_GROUP) {
            float res = data[pix + c] * data_scale - model[pix + c];
            int lit = patch_rows[base + c] > lit_from;
            count += lit;
            line += lit ? res * res : 0.0f;
        }
        square += line;
    }
    count = pl_group_sum(scratch, count);
    square = pl_group_sum(scratch, square);
    if (lid == 0) {
        out[PL_NORMALS * p + 14] = count;
        out[PL_NORMALS * p + 15] = square;
    }
}

/* unit: the value row at intensity 1; the image is data * data_scale (1: an image
 * uploaded as it is; a reconstruction's image divided by its maximum, times that
 * maximum: read where the reconstruction left it); out: sum(unit * image), sum(unit^2)
 * per particle. */
__kernel void unit_sums(__global const float *unit, __global const float *data,
                        float data_scale,
                        __global const long *offset, __global const int *col0,
                        __global const int *row0, __global const int *width,
                        __global const int *height, int cols, int rows,
                        __global float *out)
{
    __local float scratch[PL_GROUP];
    int p = get_group_id(0), lid = get_local_id(0), wd = width[p];
    int rows_on, cols_on;
    pl_on_sensor(p, col0, row0, width, height, cols, rows, &rows_on, &cols_on);
    float cross = 0.0f, square = 0.0f;
    for (int r = 0; r < rows_on; ++r) {
        long base = offset[p] + (long)r * wd, pix = (long)(row0[p] + r) * cols + col0[p];
        float line_cross = 0.0f, line_square = 0.0f;
        for (int c = lid; c < cols_on; c += PL_GROUP) {
            float u = unit[base + c];
            line_cross += u * (data[pix + c] * data_scale);
            line_square += u * u;
        }
        cross += line_cross;
        square += line_square;
    }
    cross = pl_group_sum(scratch, cross);
    square = pl_group_sum(scratch, square);
    if (lid == 0) {
        out[2 * p] = cross;
        out[2 * p + 1] = square;
    }
}
