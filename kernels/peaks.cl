/* A volume's local maxima above a floor: the candidates of a volume's particles
 * (plenocl.peaks.find_particles; NumPy twin: plenocl.peaks.host_maxima, the voxels equal
 * to scipy.ndimage.maximum_filter(v, 2 reach + 1, mode="constant") and above the floor).
 *
 * local_maxima: voxel i (flat index, C order of nz x ny x nx) is a candidate where
 * v[i] > floor and no voxel within `reach` of it along every axis is larger (voxels beyond
 * the faces count as 0, as the filter's constant mode: a negative voxel at a face is no
 * maximum). Each candidate takes a slot of `found` from the counter `count`; slots at or
 * beyond `capacity` are counted but not written, so the host grows the list and runs
 * again. The order of the slots depends on the device's scheduling: the host sorts them.
 *
 * Parallel structure: one work-item per voxel over a 3-D range (x, y, z); each reads its
 * (2 reach + 1)^3 neighbourhood (neighbouring items read neighbouring voxels: caches on a
 * CPU, coalesced on a GPU) and stops at the first larger one. Only candidates touch the
 * counter (atomic_inc): under one voxel in a thousand of a particle volume above the floors
 * plenocl uses, so the atomic is not a contended hot spot. Sizes are arguments. */
__kernel void local_maxima(__global const float *v, int nz, int ny, int nx, int reach,
                           float floor, volatile __global int *count,
                           __global int *found, int capacity)
{
    const int ix = get_global_id(0), iy = get_global_id(1), iz = get_global_id(2);
    const long i = ((long)iz * ny + iy) * nx + ix;
    const float c = v[i];
    if (!(c > floor))
        return;
    for (int z = iz - reach; z <= iz + reach; ++z)
        for (int y = iy - reach; y <= iy + reach; ++y)
            for (int x = ix - reach; x <= ix + reach; ++x) {
                const int inside = z >= 0 && z < nz && y >= 0 && y < ny && x >= 0 && x < nx;
                const float n = inside ? v[((long)z * ny + y) * nx + x] : 0.0f;
                if (n > c)
                    return;
            }
    const int slot = atomic_inc(count);
    if (slot < capacity)
        found[slot] = (int)i;
}
