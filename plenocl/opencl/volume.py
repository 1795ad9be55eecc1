"""A volume kept on the device and read back only when asked (issue 46: the host sends
the raw images and receives the vectors, volumes only when asked).

A reconstruction handed to the stages after it (:func:`plenocl.process_pair`) returns
its volume as a :class:`DeviceVolume`: the float32 device array, its summary (extremes,
values not finite, non-zero values: ``kernels/volume.cl`` ``row_summary``) and any
voxels' face neighbourhoods (``neighbourhoods``), which is what the checks of
:func:`plenocl.piv3d` and the particle levels of :func:`plenocl.peaks.find_particles`
read. A stage that needs the whole volume on the host takes :meth:`DeviceVolume.get`
(or NumPy's ``np.asarray``), copied once and kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cl_array

from .arrays import read
from .program import KernelSet

__all__ = ["SUMMARY_PARTS", "DeviceVolume", "VolumeSummary", "host_volume", "resident"]

#: The partial summaries a volume's rows are combined into on the device before the host
#: reads them: enough work-items to spread the rows (a few hundred), few bytes back.
SUMMARY_PARTS = 256


@dataclass(frozen=True)
class VolumeSummary:
    """A volume's smallest and largest finite value (``inf`` and ``-inf`` without one),
    its values that are not finite and its non-zero values (NaN counted, as NumPy's
    ``count_nonzero``)."""

    low: float
    high: float
    nonfinite: int
    nonzero: int


class DeviceVolume:
    """A whole, contiguous float32 volume ``(nz, ny, nx)`` on a device.

    Parameters
    ----------
    array
        The device array (kept, not copied).
    """

    def __init__(self, array: cl_array.Array) -> None:
        if not (array.ndim == 3 and array.dtype == np.float32 and array.flags.c_contiguous
                and array.offset == 0):
            raise ValueError("a DeviceVolume is a whole, contiguous float32 device array "
                             f"(nz, ny, nx); got {array.dtype} {array.shape}")
        self.array = array
        self._host: np.ndarray | None = None
        self._summary: VolumeSummary | None = None
        self._kernels: KernelSet | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nz, ny, nx)``."""
        return tuple(self.array.shape)

    @property
    def ndim(self) -> int:
        """3."""
        return 3

    @property
    def size(self) -> int:
        """The voxels."""
        return int(self.array.size)

    @property
    def dtype(self) -> np.dtype:
        """float32."""
        return np.dtype(np.float32)

    def get(self) -> np.ndarray:
        """The volume on the host (copied the first time, then kept: the same array each
        time, not to be written to; ``np.array(volume)`` gives a copy of it)."""
        if self._host is None:
            self._host = read(self.array)[0]
        return self._host

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        host = self.get()
        if dtype is not None:
            host = host.astype(dtype, copy=False)
        return host.copy() if copy and host is self._host else host

    def summary(self) -> VolumeSummary:
        """The volume's :class:`VolumeSummary`, found on the device (by rows, the rows
        combined there into at most :data:`SUMMARY_PARTS` parts, and those on the host:
        exact), once."""
        if self._summary is None and not self.size:
            self._summary = VolumeSummary(np.inf, -np.inf, 0, 0)
        if self._summary is None:
            nz, ny, nx = self.shape
            rows = nz * ny
            k = self._set()
            lo, hi = k.array(rows), k.array(rows)
            bad, lit = k.array(rows, np.int32), k.array(rows, np.int32)
            k.launch("row_summary", (rows,), self.array, np.int32(nx), lo, hi, bad, lit)
            parts = min(rows, SUMMARY_PARTS)
            out = [k.array(parts), k.array(parts), k.array(parts, np.int64),
                   k.array(parts, np.int64)]
            k.launch("summary_parts", (parts,), lo, hi, bad, lit, np.int32(rows), *out)
            lo, hi, bad, lit = read(*out)
            self._summary = VolumeSummary(float(lo.min()), float(hi.max()),
                                          int(bad.sum(dtype=np.int64)),
                                          int(lit.sum(dtype=np.int64)))
        return self._summary

    def maximum(self) -> float:
        """The volume's maximum as NumPy gives it: found on the device where every voxel
        is finite, else (NaN or inf) of the host copy; ``-inf`` for an empty volume."""
        summary = self.summary()
        return summary.high if not summary.nonfinite else float(self.get().max())

    def neighbourhoods(self, flat: np.ndarray) -> np.ndarray:
        """``(n, 7)`` float32: the voxels at ``flat`` (C-order indices) and their face
        neighbours (x - 1, x + 1, y - 1, y + 1, z - 1, z + 1), 0 beyond the faces."""
        flat = np.asarray(flat, np.int64).reshape(-1)
        if not len(flat):
            return np.zeros((0, 7), np.float32)
        if flat.min() < 0 or flat.max() >= self.size:
            raise IndexError(f"voxel indices must lie in [0, {self.size}) of the volume "
                             f"{self.shape}, got {flat.min()} to {flat.max()}")
        k = self._set()
        out = k.array(7 * len(flat))
        nz, ny, nx = self.shape
        k.launch("neighbourhoods", (len(flat),), self.array, *map(np.int32, (nz, ny, nx)),
                 k.to_device(flat), np.int32(len(flat)), out)
        return read(out)[0].reshape(-1, 7)

    def _set(self) -> KernelSet:
        """The kernels of ``kernels/volume.cl`` on the array's queue (built once per
        context)."""
        if self._kernels is None:
            self._kernels = KernelSet(self.array.queue, "volume.cl",
                                      ["row_summary", "summary_parts", "neighbourhoods"],
                                      looping=["row_summary", "summary_parts"])
        return self._kernels


def host_volume(vol):
    """``vol`` on the host: a :class:`DeviceVolume`'s copy (:meth:`DeviceVolume.get`),
    anything else as it is."""
    return vol.get() if isinstance(vol, DeviceVolume) else vol


def resident(vol_a, vol_b, context) -> tuple[cl_array.Array, cl_array.Array] | None:
    """The device arrays of two :class:`DeviceVolume` on ``context`` (what a stage on
    that context reads instead of uploading the volumes); ``None`` unless both are."""
    arrays = tuple(v.array for v in (vol_a, vol_b) if isinstance(v, DeviceVolume))
    if len(arrays) != 2 or any(a.context != context for a in arrays):
        return None
    return arrays
