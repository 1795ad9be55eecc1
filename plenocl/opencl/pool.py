"""Device memory kept for reuse: one pyopencl memory pool per command queue.

A pair makes and drops hundreds of device arrays (volumes, images, window stacks,
per-particle tables). Made fresh, each costs the driver an allocation and, on a CPU
device, a page fault per 4 KiB at its first touch inside a kernel; dropped, it costs the
host the release (a 50 MB buffer: 6 ms to free, 76 ms for its first fill against 3 ms
for the next, PoCL). :func:`empty` takes its arrays from a
:class:`pyopencl.tools.MemoryPool` attached to the queue, which keeps a dropped array's
memory and hands it to the next array of about its size: the 116 x 78 pair 4 % faster
on both CPU runtimes (``benchmarks/memory_pool.py``; docs/design.md §7.5, "Device memory
kept for reuse").

Safety: a pool belongs to one in-order queue, so a block handed out again is written
only by commands enqueued after every command that used it before. An array made here
and read on another queue of the same context must be finished there before it is
dropped (plenocl's stages that take another queue's arrays read their results back
before returning). The pool frees what it holds and tries again when one of its own
allocations fails; :func:`made` does the same for the allocations made outside it
(uploads, kept scratch buffers), so memory held here does not make plenocl's own
allocations fail where they fitted before (a GPU driver that reports a failure only at
a kernel's launch is beyond that). Other programs on the device, or other processes of a
batch sharing it, see the held memory as used: :func:`use_pool` switches a queue's pool
off for them. After each pair :func:`settle` gives the held memory back once it passes
:data:`HELD_SHARE` of the device's memory, so arrays whose sizes vary from pair to pair
(one block kept per size class) cannot grow it without bound. A request whose pooled
size (rounded up by at most 1/16) would pass the device's largest buffer is made
directly.

Contents are undefined, as for any new OpenCL buffer: a block may hold an earlier
array's values.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import pyopencl.tools as cl_tools

__all__ = ["HELD_SHARE", "empty", "fits_pooled", "made", "pool_of", "release_held",
           "settle", "use_pool"]

#: The queue attribute holding its pool (it lives and goes with the queue object).
ATTRIBUTE = "plenocl_pool"
#: The share of the device's memory a queue's pool may hold after a pair (:func:`settle`).
HELD_SHARE = 0.25

T = TypeVar("T")


def pool_of(queue: cl.CommandQueue) -> cl_tools.MemoryPool | None:
    """``queue``'s memory pool, made at the first call; ``None`` where the queue object
    cannot hold one or its pool is switched off (:func:`use_pool`): then arrays are made
    directly."""
    pool = getattr(queue, ATTRIBUTE, None)
    if pool is False:
        return None
    if pool is None:
        pool = cl_tools.MemoryPool(cl_tools.ImmediateAllocator(queue))
        try:
            setattr(queue, ATTRIBUTE, pool)
        except AttributeError:
            return None
    return pool


def empty(queue: cl.CommandQueue, shape, dtype=np.float32) -> cl_array.Array:
    """An uninitialised device array on ``queue``, its memory from the queue's pool
    (:func:`pool_of`) where the pooled size fits the device's largest buffer."""
    pool = pool_of(queue)
    nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    if pool is None or not fits_pooled(pool, nbytes, queue.device.max_mem_alloc_size):
        return made(queue, lambda: cl_array.empty(queue, shape, dtype))
    return cl_array.empty(queue, shape, dtype, allocator=pool)


def made(queue: cl.CommandQueue, make: Callable[[], T]) -> T:
    """``make()``, an allocation outside ``queue``'s pool; where the driver refuses it
    for want of memory, made again after the pool's held memory is given back."""
    try:
        return make()
    except cl.MemoryError:
        if not release_held(queue):
            raise
        return make()


def fits_pooled(pool: cl_tools.MemoryPool, nbytes: int, largest: int) -> bool:
    """Whether ``pool`` hands out ``nbytes`` (more than 0): the block it takes them from
    (``nbytes`` rounded up by at most 1/16) within the device's ``largest`` buffer."""
    return 0 < nbytes and pool.alloc_size(pool.bin_number(nbytes)) <= largest


def use_pool(queue: cl.CommandQueue, on: bool = True) -> None:
    """Switch ``queue``'s pool on (the default) or off: off, its held memory is given
    back (:func:`release_held`) and every later array is made directly, as before the
    pool (a benchmark's baseline; a device shared with other programs). A queue object
    that cannot hold a pool has none either way."""
    if on:
        if getattr(queue, ATTRIBUTE, None) is False:
            setattr(queue, ATTRIBUTE, None)
        return
    release_held(queue)
    try:
        setattr(queue, ATTRIBUTE, False)
    except AttributeError:
        pass


def release_held(queue: cl.CommandQueue) -> int:
    """Give the memory ``queue``'s pool holds (dropped arrays kept for reuse) back to
    the driver; returns the bytes it held. Arrays still in use keep theirs."""
    pool = getattr(queue, ATTRIBUTE, None)
    if not pool:
        return 0
    before = int(pool.managed_bytes)
    pool.free_held()
    return before - int(pool.managed_bytes)


def settle(queue: cl.CommandQueue, share: float = HELD_SHARE) -> int:
    """After a pair: give the held memory back where it passes ``share`` of the device's
    global memory; returns the bytes given back (0: kept for the next pair)."""
    pool = getattr(queue, ATTRIBUTE, None)
    if not pool:
        return 0
    held = int(pool.managed_bytes) - int(pool.active_bytes)
    if held <= share * queue.device.global_mem_size:
        return 0
    return release_held(queue)
