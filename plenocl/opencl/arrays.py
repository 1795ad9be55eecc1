"""Device arrays filled with one value by the driver's own fill (``clEnqueueFillBuffer``),
host arrays uploaded without waiting for the queue, volumes placed inside zeros or inside
another volume on the device and a box cut out of one there (one rectangular copy each),
and the check of two volumes'
device copies handed from one stage to the next.

pyopencl's ``Array.fill`` runs an element-wise kernel whose work-items each loop over a
strided range; PoCL runs it 25-40x slower than the driver's fill (a 12.6-million-voxel
volume: 45 ms against 1.8 ms; a 2.6-million-pixel image: 8.6 ms against 0.2 ms), and a
reconstruction fills an image and a light buffer every iteration (docs/design.md §5.2).
"""

from __future__ import annotations

import weakref

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from . import pool

__all__ = ["KeptUpload", "buffer_from_host", "copy_inside", "copy_region", "copy_slabbed",
           "device_copies", "fill", "inside_zeros", "queue_kept", "read", "upload"]


def upload(queue: cl.CommandQueue, host) -> cl_array.Array:
    """A device copy of a host array (any layout, its shape kept) on ``queue``, copied as
    the driver makes its buffer (:func:`buffer_from_host`): no command on the queue, so
    the host does not wait for the kernels before it. pyopencl's ``to_device`` enqueues a
    blocking write, which waits for every kernel enqueued before it: a pair's 800 small
    uploads (window lists, tables, geometry) were as many hidden synchronisations (issue
    46)."""
    host = np.asarray(host)
    if not host.nbytes:
        return cl_array.to_device(queue, host)
    packed = np.ascontiguousarray(host)  # (a 0-d array comes out 1-d: the shape is host's)
    data = pool.made(queue, lambda: buffer_from_host(queue.context, packed))
    return cl_array.Array(queue, host.shape, host.dtype, data=data)


class KeptUpload:
    """Device copies of the host arrays last given, uploaded again only when one of them
    changes: for tables that kernels only read and that a run gives again and again (a
    pair's PIV passes, its refinement's calls).

    Parameters
    ----------
    queue
        The device's queue.
    dtype
        The copies' type (each array is converted to it, as the comparison is made).

    Replacing the kept copies is one assignment, so threads sharing the object each get
    copies of what they gave.
    """

    def __init__(self, queue: cl.CommandQueue, dtype) -> None:
        self.queue, self.dtype = queue, np.dtype(dtype)
        self._kept: tuple[tuple, tuple] | None = None

    def __call__(self, *arrays) -> tuple[cl_array.Array | None, ...]:
        """Device copies of ``arrays`` (``None`` stays ``None``), the kept ones where
        every array equals the last call's (shape and values)."""
        host = tuple(None if a is None else np.array(a, self.dtype) for a in arrays)
        kept = self._kept
        if kept is None or not _all_same(kept[0], host):
            kept = self._kept = (host, tuple(None if a is None else upload(self.queue, a)
                                             for a in host))
        return kept[1]


# Per context, the last array kept under each name (queue_kept): the buffers are the
# context's, so every queue on it reads them. A kept array holds its queue and so its
# context: the entries stay for the process's life, one array per name and context.
_QUEUE_KEPT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def queue_kept(queue: cl.CommandQueue, name: str, host: np.ndarray) -> cl_array.Array:
    """A device copy of ``host`` on ``queue``, the same one for every caller that gives
    ``name`` and equal values (the last array given under each name is kept, per
    context, for the process's life): a camera's tables that each pair's objects would
    upload again (the image fit's lens table, 0.45 MB a paper-size pair; a missing
    lens's NaN equals NaN). Callers only read it."""
    host = np.ascontiguousarray(host)
    kept = _QUEUE_KEPT.setdefault(queue.context, {})  # a queue is not weakly referable
    last = kept.get(name)
    if (last is None or last[0].dtype != host.dtype
            or not np.array_equal(last[0], host, equal_nan=host.dtype.kind in "fc")):
        last = kept[name] = (host.copy(), upload(queue, host))
    return last[1]


def _all_same(kept: tuple, given: tuple) -> bool:
    """Whether two tuples of optional arrays hold the same ``None`` s and equal arrays."""
    return len(kept) == len(given) and all(
        a is b if a is None or b is None else np.array_equal(a, b)
        for a, b in zip(kept, given))


def read(*arrays: cl_array.Array) -> list[np.ndarray]:
    """Host copies of contiguous device arrays, read with one wait: each copy enqueued
    without blocking (after the array's own events), then all waited for at once (three
    ``.get()`` calls wait three times). The same values as ``.get()``."""
    out, events = [], []
    for array in arrays:
        if not array.flags.forc:
            raise ValueError("read needs contiguous device arrays (a whole array or a "
                             "slice along its first axis)")
        host = np.empty(array.shape, array.dtype)
        if array.size:
            events.append(cl.enqueue_copy(array.queue, host, array.base_data,
                                          src_offset=array.offset, is_blocking=False,
                                          wait_for=array.events or None))
        out.append(host)
    if events:
        cl.wait_for_events(events)
    return out


def buffer_from_host(context: cl.Context, host: np.ndarray) -> cl.Buffer:
    """A read-write buffer of ``context`` holding a copy of the contiguous, non-empty
    ``host`` array, copied when it is made (``COPY_HOST_PTR``); the one place uploads go
    through, where :class:`plenocl.bench.clprofile.OpenCLProfile` counts their bytes."""
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    return cl.Buffer(context, flags, hostbuf=host)


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
    out = fill(pool.empty(queue, tuple(shape), np.float32), 0.0)
    return copy_inside(out, vol, corner)


def copy_inside(out: cl_array.Array, vol, corner: tuple[int, int, int]) -> cl_array.Array:
    """``vol`` (a float32 host array, or a whole float32 device array on ``out``'s
    context) copied into the whole float32 device array ``out`` ``(z, y, x)``, its first
    voxel at ``corner`` (one rectangular copy, enqueued on ``out``'s queue); returns
    ``out``."""
    nz, ny, nx = vol.shape
    shape = out.shape
    if any(c < 0 or c + n > s for c, n, s in zip(corner, vol.shape, shape, strict=True)):
        raise ValueError(f"a {tuple(vol.shape)} volume at {tuple(corner)} does not fit in "
                         f"{tuple(shape)}")
    if not vol.size:
        return out
    if isinstance(vol, cl_array.Array):
        return copy_region(out, corner, vol, (0, 0, 0), vol.shape)
    cl.enqueue_copy(out.queue, out.data, np.ascontiguousarray(vol, np.float32),
                    region=(4 * nx, ny, nz),
                    **{f"buffer_{k}": v for k, v in _pitched(shape, corner).items()},
                    **{f"host_{k}": v for k, v in _pitched(vol.shape, (0, 0, 0)).items()})
    return out


def copy_region(out: cl_array.Array, out_corner: tuple[int, int, int], vol: cl_array.Array,
                vol_corner: tuple[int, int, int], size: tuple[int, int, int]
                ) -> cl_array.Array:
    """The box of ``size`` ``(z, y, x)`` at ``vol_corner`` in the whole float32 device
    array ``vol`` copied into the whole float32 device array ``out`` at ``out_corner``
    (one rectangular copy on ``out``'s queue, device to device: nothing crosses to the
    host); returns ``out``."""
    for name, arr, corner in (("source", vol, vol_corner), ("target", out, out_corner)):
        if any(c < 0 or c + n > s for c, n, s in zip(corner, size, arr.shape, strict=True)):
            raise ValueError(f"a {tuple(size)} box at {tuple(corner)} does not fit in the "
                             f"{name} {tuple(arr.shape)}")
    if all(size):
        cl.enqueue_copy(out.queue, out.data, vol.data, region=(4 * size[2], *size[1::-1]),
                        **{f"dst_{k}": v for k, v in _pitched(out.shape, out_corner).items()},
                        **{f"src_{k}": v for k, v in _pitched(vol.shape, vol_corner).items()})
    return out


def copy_slabbed(out: list, out_slabs, out_corner: tuple[int, int, int], vol: list,
                 vol_slabs, vol_corner: tuple[int, int, int], size: tuple[int, int, int]
                 ) -> list:
    """:func:`copy_region` between volumes held as depth slabs (a projector's plan: slab
    ``k`` holds depths ``[z0, z1)`` of ``*_slabs``, its arrays ``(z1 - z0, ny, nx)``): the
    box of ``size`` at ``vol_corner`` of ``vol`` into ``out`` at ``out_corner``, one
    rectangular copy per pair of slabs the box crosses; returns ``out``."""
    shift = out_corner[0] - vol_corner[0]  # a depth of vol, plus shift, is one of out
    for (a, b), part in zip(out_slabs, out, strict=True):
        for (c, d), slab in zip(vol_slabs, vol, strict=True):
            lo = max(a - shift, c, vol_corner[0])
            hi = min(b - shift, d, vol_corner[0] + size[0])
            if lo < hi:
                copy_region(part, (lo + shift - a, *out_corner[1:]), slab,
                            (lo - c, *vol_corner[1:]), (hi - lo, *size[1:]))
    return out


def _pitched(shape: tuple[int, int, int], corner: tuple[int, int, int]) -> dict:
    """A rectangular copy's origin (bytes, rows, slices) and pitches in a packed float32
    array of ``shape`` ``(z, y, x)``, its box starting at ``corner``."""
    return {"origin": (4 * corner[2], corner[1], corner[0]),
            "pitches": (4 * shape[2], 4 * shape[2] * shape[1])}


def device_copies(on_device, shape: tuple[int, ...], context: cl.Context | None = None,
                  who: str = "on_device") -> tuple[cl_array.Array, cl_array.Array] | None:
    """Two volumes' device copies ``(dev_a, dev_b)`` (a reconstruction's
    ``info.volume_on_device``, handed to the next stage), checked: whole contiguous
    float32 device arrays of the volumes' ``shape``, on ``context`` where given;
    ``None`` for ``None``. A wrong one is refused by name, with the fix."""
    if on_device is None:
        return None
    copies = tuple(on_device)
    if len(copies) != 2:
        raise ValueError(f"{who} takes the two volumes' device copies (dev_a, dev_b), got "
                         f"{len(copies)}")
    for name, dev in zip(("a", "b"), copies):
        if not (isinstance(dev, cl_array.Array) and dev.shape == tuple(shape)
                and dev.dtype == np.float32 and dev.flags.c_contiguous and dev.offset == 0
                and (context is None or dev.context == context)):
            raise ValueError(
                f"{who}'s copy of volume {name} must be a whole float32 device array of "
                f"the volumes' shape {tuple(shape)}"
                f"{'' if context is None else ' on the context the stage runs on'} (a "
                f"reconstruction's info.volume_on_device); got "
                f"{getattr(dev, 'shape', type(dev).__name__)}. Pass the host volumes alone "
                f"({who}=None) to upload them")
    return copies
