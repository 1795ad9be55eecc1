"""A camera's raw integer image made into the solver's image on the OpenCL device
(issue 46: the host sends the raw images; docs/design.md §7.5, "A camera's counts
prepared on the device").

The host counts the frame's levels once (:class:`plenocl.optics.rawimage.CountHistogram`:
a bincount, a few kilobytes for 16-bit counts), which give the exposure checks, the
median background, the noise and the scale exactly as the host's preparation finds
them; the frame goes to the device as its own integers (2 bytes a pixel for 16-bit
counts, against 4 for the float32 image) and ``kernels/rawcounts.cl`` writes the
float32 image there, to the bit the host's (:func:`plenocl.reconstruction.images.preprocess`).
The host makes no float copy of the frame. :func:`plenocl.reconstruction.images.prepare_image`
decides where an image is prepared (:func:`prepares_on_device`).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..opencl.arrays import upload
from ..opencl.program import KernelSet

__all__ = ["COUNT_TYPES", "DeviceCounts", "prepares_on_device"]

#: The counts' types prepared on the device, with their OpenCL types: at most 16 bits,
#: so a count less a median (a whole or half count) is exact in float32.
COUNT_TYPES = {np.dtype(np.uint8): "uchar", np.dtype(np.uint16): "ushort",
               np.dtype(np.int16): "short"}


def prepares_on_device(image, background: str | None, smooth_px: float | None,
                       observed) -> bool:
    """Whether a reconstruction on a device prepares ``image`` there: a camera's counts
    (:data:`COUNT_TYPES`) prepared the default way (the median background or none, no
    smoothing, no pixel mask). Other images (floats, wider integers, a mask, smoothing)
    are prepared on the host."""
    return (observed is None and smooth_px is None and background in ("median", None)
            and isinstance(image, np.ndarray) and image.dtype in COUNT_TYPES)


class DeviceCounts:
    """``kernels/rawcounts.cl`` on ``queue`` for counts of ``dtype`` (one of
    :data:`COUNT_TYPES`): built once per context and option, its kernel fetched once
    (:class:`plenocl.opencl.program.KernelSet`'s caches), so one is made per image."""

    def __init__(self, queue: cl.CommandQueue, dtype) -> None:
        self.dtype = np.dtype(dtype)
        if self.dtype not in COUNT_TYPES:
            raise ValueError(f"counts of {self.dtype} are prepared on the host; the device "
                             f"takes {', '.join(str(t) for t in COUNT_TYPES)}")
        self.queue = queue
        self._k = KernelSet(queue, "rawcounts.cl", ("scaled_counts",),
                            [f"-DPL_COUNT={COUNT_TYPES[self.dtype]}"])

    def scaled(self, raw: np.ndarray, median: float, scale: float) -> cl_array.Array:
        """``max(raw - median, 0) / scale`` as a float32 device image of ``raw``'s shape
        (:func:`plenocl.reference.rawcounts.scaled_counts`); ``raw`` is uploaded as it is.
        ``median`` a whole or half count, ``scale`` positive."""
        raw = np.ascontiguousarray(raw, self.dtype)
        if float(np.float32(median)) != median or float(np.float32(scale)) != scale \
                or not scale > 0:
            raise ValueError(f"scaled counts need a median and a positive scale exact in "
                             f"float32 (whole or half counts), got {median!r}, {scale!r}")
        out = self._k.array(raw.shape)
        if raw.size:
            self._k.launch("scaled_counts", (raw.size,), upload(self.queue, raw),
                           np.float32(median), np.float32(scale), out)
        return out
