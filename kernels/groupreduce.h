/* A work-group's sum or maximum by a tree in local memory (kernels/imagefit.cl,
 * kernels/sightline.cl, kernels/fftcorr.cl). PL_GROUP, the work-group size, is a power of two: wide on a GPU
 * (the group's items share a particle's work), 1 on a CPU (one item loops over it). */
#ifndef PLENOCL_GROUPREDUCE_H
#define PLENOCL_GROUPREDUCE_H

#ifndef PL_GROUP
#define PL_GROUP 64
#endif

/* The sum (largest = 0) or the largest (1) of each item's v over the work-group, by a
 * tree in local memory; every item gets it. */
inline float pl_group_reduce(__local float *scratch, float v, int largest)
{
    int lid = get_local_id(0);
    scratch[lid] = v;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int stride = PL_GROUP / 2; stride > 0; stride >>= 1) {
        if (lid < stride) {
            const float a = scratch[lid], b = scratch[lid + stride];
            scratch[lid] = largest ? fmax(a, b) : a + b;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    float out = scratch[0];
    barrier(CLK_LOCAL_MEM_FENCE);
    return out;
}
#define pl_group_sum(scratch, v) pl_group_reduce(scratch, v, 0)
#define pl_group_max(scratch, v) pl_group_reduce(scratch, v, 1)

#endif
