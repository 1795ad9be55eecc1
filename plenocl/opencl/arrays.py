"""Device arrays filled with one value by the driver's own fill (``clEnqueueFillBuffer``),
and volumes placed inside zeros on the device (one rectangular copy).

pyopencl's ``Array.fill`` runs an element-wise kernel whose work-items each loop over a
strided range; PoCL runs it 25-40x slower than the driver's fill (a 12.6-million-voxel
volume: 45 ms against 1.8 ms; a 2.6-million-pixel image: 8.6 ms against 0.2 ms), and a
reconstruction fills an image and a light buffer every iteration (docs/design.md §5.2).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

__all__ = ["fill", "inside_zeros"]


def fill(array: cl_array.Array, value) -> cl_array.Array:
    """``array`` (contiguous: a whole array or a slice along its first axis) set to
    ``value`` in its own dtype, enqueued on its queue; returns ``array``."""
    if not array.flags.forc:
        raise ValueError("fill needs a contiguous device array (a whole array or a slice "
                         "along its first axis)")
    if array.size:
        cl.enqueue_fill_buffer(array.queue, array.base_data, np.asarray(value, array.dtype),
                               array.offset, array.nbytes)
    return array


def inside_zeros(queue: cl.CommandQueue, vol, shape: tuple[int, int, int],
                 corner: tuple[int, int, int]) -> cl_array.Array:
    """A float32 device array of ``shape`` ``(z, y, x)`` of zeros with ``vol`` (a host
    array, or a float32 device array on ``queue``'s context) copied in, its first voxel
    at ``corner``: a padded volume made on the device, without a padded host copy."""
    nz, ny, nx = vol.shape
    out = fill(cl_array.empty(queue, tuple(shape), np.float32), 0.0)
    region = (4 * nx, ny, nz)
    inside = {"origin": (4 * corner[2], corner[1], corner[0]),
              "pitches": (4 * shape[2], 4 * shape[2] * shape[1])}
    packed = {"origin": (0, 0, 0), "pitches": (4 * nx, 4 * nx * ny)}
    if isinstance(vol, cl_array.Array):
        cl.enqueue_copy(queue, out.data, vol.data, region=region,
                        **{f"dst_{k}": v for k, v in inside.items()},
                        **{f"src_{k}": v for k, v in packed.items()})
    else:
        cl.enqueue_copy(queue, out.data, np.ascontiguousarray(vol, np.float32), region=region,
                        **{f"buffer_{k}": v for k, v in inside.items()},
                        **{f"host_{k}": v for k, v in packed.items()})
    return out
