/* Dark-microlens skipping (docs/design.md §5.3, plenocl.projection.lenses): which lenses
 * an image lights. NumPy twin: plenocl.projection.lenses.lit_lenses (the host path, lit
 * pixels counted along rows).
 *
 * lit_patches: lens k is lit when a pixel of the square patch of half-width `reach`
 * around its rounded centre (centres[2 k ..] as (column, row), clipped to the sensor) is
 * above `threshold`; out[k] is 1 or 0. A lens whose patch lies off the sensor is dark.
 *
 * pack_flags: those flags eight to a byte (bit i of byte j lens 8 j + i; twin:
 * numpy.packbits with bitorder="little"), what the host reads (a paper-size array's
 * 55,777 lenses: 7 kB back, not 56 kB).
 *
 * Parallel structure: lit_patches one work-item per lens (10^3 to 10^5 per image),
 * looping over its patch's rows and stopping at the first lit pixel; no shared writes.
 * pack_flags one work-item per byte, eight reads. Neighbouring
 * lenses' patches are neighbouring pixels, so a GPU's neighbouring items read nearby
 * rows and a CPU's caches hold them. Sizes are arguments. */

__kernel void lit_patches(__global const float *image, int width, int height,
                          __global const int *centres, int reach, float threshold,
                          __global uchar *out)
{
    const int k = get_global_id(0);
    const int x0 = max(centres[2 * k] - reach, 0), x1 = min(centres[2 * k] + reach + 1, width);
    const int y0 = max(centres[2 * k + 1] - reach, 0);
    const int y1 = min(centres[2 * k + 1] + reach + 1, height);
    uchar lit = 0;
    for (int y = y0; y < y1 && !lit; y++) {
        __global const float *row = image + (long)y * width;
        for (int x = x0; x < x1; x++)
            lit |= row[x] > threshold;
    }
    out[k] = lit;
}

__kernel void pack_flags(__global const uchar *flags, int n, __global uchar *packed)
{
    const int j = get_global_id(0);
    uchar byte = 0;
    for (int i = 0; i < 8 && 8 * j + i < n; i++)
        byte |= (uchar)((flags[8 * j + i] != 0) << i);
    packed[j] = byte;
}
