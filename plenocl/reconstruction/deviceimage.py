"""A camera's raw integer image made into the solver's image on the OpenCL device
(issue 46: the host sends the raw images; docs/design.md §7.5, "A camera's counts
prepared on the device").

The frame goes to the device as its own integers (2 bytes a pixel for 16-bit counts,
against 4 for the float32 image); the device counts its levels
(:class:`plenocl.optics.rawimage.CountHistogram`, read back: its blocks of
:data:`LEVEL_BLOCK` levels, then the levels of the blocks that hold pixels), which give
the exposure checks, the median background, the noise and the scale exactly as the
host's preparation finds them, and ``kernels/rawcounts.cl`` writes the float32 image
there, to the bit the host's (:func:`plenocl.reconstruction.images.preprocess`). The host
makes no float copy of the frame and does not count it (a 16 MP frame's ``np.bincount``
took it 35-180 ms). :func:`plenocl.reconstruction.images.prepare_image` decides where an
image is prepared (:func:`prepares_on_device`).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..opencl.arrays import fill, read
from ..opencl.program import KernelSet, group_size
from ..optics.rawimage import CountHistogram

__all__ = ["COUNT_TYPES", "DeviceCounts", "occupied_runs", "prepares_on_device"]

#: The counts' types prepared on the device, with their OpenCL types: at most 16 bits,
#: so a count less a median (a whole or half count) is exact in float32.
COUNT_TYPES = {np.dtype(np.uint8): "uchar", np.dtype(np.uint16): "ushort",
               np.dtype(np.int16): "short"}
#: Work-groups counting the levels, each into its own histogram: with groups of several
#: items (a GPU) many (they add with atomics; the copies spread the few background levels
#: that every item hits), with one item a group (a CPU) a few per compute unit (plain
#: increments).
GPU_GROUPS, CPU_GROUPS_PER_UNIT = 64, 2
#: Levels a block of the histogram's first read (``level_blocks``): the host then reads
#: the levels of the blocks that hold pixels (:func:`occupied_runs`).
LEVEL_BLOCK = 256


def occupied_runs(blocks: np.ndarray, levels: int) -> list[tuple[int, int]]:
    """The levels ``[start, stop)`` of each run of consecutive blocks of
    :data:`LEVEL_BLOCK` levels that hold pixels (``blocks``: the pixels per block of a
    histogram of ``levels`` levels, the last block's run ending at ``levels``), in
    order; what :meth:`DeviceCounts.histogram` reads (the empty blocks between them stay
    on the device: a dark level and a few saturated pixels are two short runs)."""
    held = np.flatnonzero(np.asarray(blocks) > 0)
    cuts = np.flatnonzero(np.diff(held) > 1) + 1
    return [(int(run[0]) * LEVEL_BLOCK, min((int(run[-1]) + 1) * LEVEL_BLOCK, levels))
            for run in np.split(held, cuts)]


def prepares_on_device(image, background: str | None, smooth_px: float | None,
                       observed) -> bool:
    """Whether a reconstruction on a device prepares ``image`` there: a camera's counts
    (:data:`COUNT_TYPES`) prepared the default way (the median background or none, no
    smoothing, no pixel mask). Other images (floats, wider integers, a mask, smoothing)
    are prepared on the host."""
    return (observed is None and not smooth_px and background in ("median", None)
            and isinstance(image, np.ndarray) and image.dtype in COUNT_TYPES)


class DeviceCounts:
    """``kernels/rawcounts.cl`` on ``queue`` for counts of ``dtype`` (one of
    :data:`COUNT_TYPES`): built once per context and option, its kernels fetched once
    (:class:`plenocl.opencl.program.KernelSet`'s caches), so one is made per image.
    ``group``: ``count_levels``' work-items per group (a power of two); ``None``: 1 on a
    CPU, :data:`plenocl.opencl.program.GPU_GROUP` elsewhere."""

    def __init__(self, queue: cl.CommandQueue, dtype, group: int | None = None) -> None:
        self.dtype = np.dtype(dtype)
        if self.dtype not in COUNT_TYPES:
            raise ValueError(f"counts of {self.dtype} are prepared on the host; the device "
                             f"takes {', '.join(str(t) for t in COUNT_TYPES)}")
        self.queue = queue
        info = np.iinfo(self.dtype)  # the levels counted: every value the type holds
        self.low, self.levels = int(info.min), int(info.max) - int(info.min) + 1
        self.group = group_size(queue, group)
        self._k = KernelSet(queue, "rawcounts.cl",
                            ("scaled_counts", "count_levels", "sum_levels",
                             "level_blocks"),
                            [f"-DPL_COUNT={COUNT_TYPES[self.dtype]}", f"-DPL_LOW={self.low}",
                             f"-DPL_LEVELS={self.levels}", f"-DPL_GROUP={self.group}",
                             f"-DPL_BLOCK={LEVEL_BLOCK}"],
                            looping=["count_levels", "level_blocks"])

    def upload(self, raw: np.ndarray) -> cl_array.Array:
        """A device copy of the counts ``raw`` as they are (for :meth:`histogram` and
        :meth:`scaled`: the frame goes up once)."""
        return self._k.to_device(np.asarray(raw, self.dtype))

    def histogram(self, raw: np.ndarray, on_device: cl_array.Array | None = None
                  ) -> CountHistogram | None:
        """The :class:`CountHistogram` of the counts ``raw``, counted on the device
        (``count_levels``, ``sum_levels``; the host's ``np.bincount`` the twin, the same
        integers) from ``on_device``, their copy from :meth:`upload` (uploaded here when
        ``None``); ``None`` for an empty frame. Only the levels of the blocks of
        :data:`LEVEL_BLOCK` that hold pixels come back (:meth:`level_blocks` first,
        then :func:`occupied_runs`)."""
        raw = self._k.on_device(raw if on_device is None else on_device, self.dtype)
        if not raw.size:
            return None
        if raw.size >= 2**32:
            raise ValueError(f"a frame of {raw.size:,} pixels is beyond the device's level "
                             "counts (32 bits): prepare it on the host (a float image)")
        units = self.queue.device.max_compute_units
        groups = GPU_GROUPS if self.group > 1 else CPU_GROUPS_PER_UNIT * units
        partial = fill(self._k.array((groups, self.levels), np.uint32), 0)
        self._k.launch("count_levels", (groups * self.group,), raw, np.int64(raw.size),
                       np.int64(-(-raw.size // groups)), partial, local_size=(self.group,))
        total = self._k.array(self.levels, np.uint32)
        self._k.launch("sum_levels", (self.levels,), partial, np.int32(groups), total)
        runs = occupied_runs(self.level_blocks(total), self.levels)
        start = runs[0][0]
        counts = np.zeros(runs[-1][1] - start, np.uint32)
        parts = read(*(total[a:b] for a, b in runs))  # one wait
        for (a, b), part in zip(runs, parts):
            counts[a - start:b - start] = part
        seen = np.flatnonzero(counts)
        return CountHistogram(self.low + start + int(seen[0]),
                              counts[seen[0]:seen[-1] + 1].astype(np.int64))

    def level_blocks(self, total: cl_array.Array) -> np.ndarray:
        """The pixels in each block of :data:`LEVEL_BLOCK` levels of the device histogram
        ``total`` (``level_blocks``; twin
        :func:`plenocl.reference.rawcounts.level_blocks`), read back."""
        blocks = self._k.array(-(-self.levels // LEVEL_BLOCK), np.uint32)
        self._k.launch("level_blocks", blocks.shape, total, blocks)
        return read(blocks)[0]

    def scaled(self, raw, median: float, scale: float) -> cl_array.Array:
        """``max(raw - median, 0) / scale`` as a float32 device image of ``raw``'s shape
        (:func:`plenocl.reference.rawcounts.scaled_counts`); ``raw`` on the host (uploaded
        as it is) or from :meth:`upload`. ``median`` a whole or half count, ``scale``
        positive."""
        if float(np.float32(median)) != median or float(np.float32(scale)) != scale \
                or not scale > 0:
            raise ValueError(f"scaled counts need a median and a positive scale exact in "
                             f"float32 (whole or half counts), got {median!r}, {scale!r}")
        raw = self._k.on_device(raw, self.dtype)
        out = self._k.array(raw.shape)
        if raw.size:
            self._k.launch("scaled_counts", (raw.size,), raw, np.float32(median),
                           np.float32(scale), out)
        return out
