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
 * PL_COUNT: the counts' OpenCL type (uchar, ushort or short). Sizes are arguments.
 * Parallel structure: one work-item per pixel, no atomics, no local memory. */
#pragma OPENCL FP_CONTRACT OFF

__kernel void scaled_counts(__global const PL_COUNT *raw, float median, float scale,
                            __global float *out)
{
    const size_t i = get_global_id(0);
    out[i] = fmax((float)raw[i] - median, 0.0f) / scale;
}
