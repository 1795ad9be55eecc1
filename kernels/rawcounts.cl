/* A camera's raw integer counts made into the image the solver reads, on the device
 * (issue 46: the host sends the raw image; plenocl.reconstruction.deviceimage.DeviceCounts;
 * NumPy twin: plenocl.reference.rawcounts.scaled_counts).
 *
 * The median background and the scale come from the host's histogram of the counts
 * (exact: plenocl.optics.rawimage.CountHistogram); this writes each pixel's
 * max(count - median, 0) / scale as float32, to the bit the host's preparation
 * (plenocl.reconstruction.images.preprocess, which divides in float64 and rounds once to
 * float32). Here the difference is exact in float32 (counts of at most 16 bits, a median
 * of whole or half counts) and the division is float32's, correctly rounded (every
 * program is built with -cl-fp32-correctly-rounded-divide-sqrt): a quotient rounded to
 * float64 and then to float32 is the correctly rounded float32 one (53 >= 2 x 24 + 2),
 * so both give the same bits, and no double precision is needed.
 *
 * count_levels, sum_levels: that histogram, counted here where the frame already is (the
 * host reads PL_LEVELS counts back instead of counting every pixel; twin: np.bincount,
 * plenocl.reference.rawcounts.level_counts): the pixels at each level PL_LOW ..
 * PL_LOW + PL_LEVELS - 1, every value of PL_COUNT.
 *
 * level_blocks: the pixels in each block of PL_BLOCK consecutive levels (twin:
 * plenocl.reference.rawcounts.level_blocks): the host reads these first (1 kB for
 * 16-bit counts), then the levels of the blocks that hold pixels alone (a camera's
 * 16-bit frame often fills a few hundred of its 65,536 levels: 2-3 kB of them instead of
 * 256 kB).
 *
 * PL_COUNT: the counts' OpenCL type (uchar, ushort or short); PL_LOW, PL_LEVELS its
 * levels; PL_GROUP: count_levels' work-group size; PL_BLOCK: level_blocks' levels a
 * block. Sizes are arguments.
 * Parallel structure: scaled_counts one work-item per pixel, no atomics, no local
 * memory. count_levels: each work-group counts its own slice of the pixels into its own
 * histogram (`partial`, zeroed by the host's fill), its items reading the slice in
 * strides of the group (coalesced); with PL_GROUP > 1 (a GPU) they add with atomic_inc,
 * the groups' copies spreading the few background levels every item hits (65,536 levels
 * do not fit local memory); with PL_GROUP 1 (a CPU: one item a group) a plain increment.
 * sum_levels: one work-item per level adds the groups' counts (no atomics).
 * level_blocks: one work-item per block, a loop over its levels (no atomics). */
#pragma OPENCL FP_CONTRACT OFF

__kernel void scaled_counts(__global const PL_COUNT *raw, float median, float scale,
                            __global float *out)
{
    const size_t i = get_global_id(0);
    out[i] = fmax((float)raw[i] - median, 0.0f) / scale;
}

__kernel void count_levels(__global const PL_COUNT *raw, long size, long per_group,
                           __global uint *partial)
{
    const long lo = get_group_id(0) * per_group;
    const long hi = lo + per_group < size ? lo + per_group : size;
    __global uint *hist = partial + (long)get_group_id(0) * PL_LEVELS;
    for (long i = lo + get_local_id(0); i < hi; i += PL_GROUP) {
        const int level = (int)raw[i] - PL_LOW;
#if PL_GROUP == 1
        hist[level] += 1;
#else
        atomic_inc(hist + level);
#endif
    }
}

__kernel void sum_levels(__global const uint *partial, int groups, __global uint *total)
{
    const int level = get_global_id(0);
    uint n = 0;
    for (int g = 0; g < groups; ++g)
        n += partial[(long)g * PL_LEVELS + level];
    total[level] = n;
}

__kernel void level_blocks(__global const uint *total, __global uint *blocks)
{
    const int b = get_global_id(0);
    const int end = (b + 1) * PL_BLOCK < PL_LEVELS ? (b + 1) * PL_BLOCK : PL_LEVELS;
    uint n = 0;
    for (int level = b * PL_BLOCK; level < end; ++level)
        n += total[level];
    blocks[b] = n;
}
