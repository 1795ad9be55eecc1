"""Lateral supersampling of a reconstruction (docs/design.md §6.4): the volume is
reconstructed on a grid with ``f x f`` lateral sub-voxels per voxel and summed back.

The paper's voxel (0.18 mm) images onto about one microlens, so on that grid a particle
between two voxel centres can only be drawn as a mixture of two voxels whose light
fields differ by a whole lens; the solver then explains the particle's image with light
at the wrong depth. Sub-voxels place it within a third of a lens, and the depth follows
(``benchmarks/accuracy.py``).

:func:`bin_lateral` is the NumPy form; :class:`LateralBinning` bins device slabs with
``kernels/supersample.cl`` (its twin), so that only the binned volume is copied to the host.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..opencl.arrays import read
from ..opencl.program import KernelSet

#: Largest accepted factor (memory and time grow as its square).
MAX_SUPERSAMPLE = 4


def bin_lateral(vol: np.ndarray, factor: int) -> np.ndarray:
    """Sum each ``factor x factor`` lateral block: ``(nz, ny f, nx f)`` to ``(nz, ny, nx)``
    (intensity conserved)."""
    nz, nyf, nxf = vol.shape
    if nyf % factor or nxf % factor:
        raise ValueError(f"a {vol.shape} volume does not bin by {factor} laterally")
    out = vol.reshape(nz, nyf // factor, factor, nxf // factor, factor).sum(axis=(2, 4))
    return out.astype(np.float32)


def spread_lateral(vol: np.ndarray, factor: int) -> np.ndarray:
    """Each voxel's intensity shared equally by its ``factor x factor`` sub-voxels: the
    inverse of :func:`bin_lateral` for a volume that is flat within each voxel."""
    v = np.asarray(vol, np.float32) / np.float32(factor * factor)
    return np.repeat(np.repeat(v, factor, axis=1), factor, axis=2)


class LateralBinning:
    """:func:`bin_lateral` on the device (``kernels/supersample.cl``): one work-item per
    output voxel, a gather of its sub-voxels; the sums agree with :func:`bin_lateral` of
    the scaled volume to float32 rounding (same order of additions). And its flat
    inverse, :func:`spread_lateral`, from a host volume into device slabs
    (:meth:`spread_into`).

    Parameters
    ----------
    queue
        The queue of the slabs to bin.
    """

    def __init__(self, queue: cl.CommandQueue) -> None:
        self._k = KernelSet(queue, "supersample.cl", ("bin_lateral", "spread_lateral",
                                                      "grown_support", "spread_support",
                                                      "row_peaks", "support_rows"),
                            looping=["row_peaks", "support_rows"])

    def to_host(self, slabs: list[cla.Array], factor: int, offset: tuple[int, int] = (0, 0),
                scale: float = 1.0) -> np.ndarray:
        """The binned host volume of device slabs ``(dz, nyf, nxf)``, times ``scale``.

        ``offset`` ``(oy, ox)``, each in ``[0, factor)``: the slabs' lateral start in the
        fine grid lies that far past a block boundary (a cropped volume); the output then
        covers every block the slabs touch, ``ceil((o + n) / factor)`` per axis, and the
        sub-voxels outside the slabs count as zero.
        """
        return np.concatenate([p.get() for p in self.binned(slabs, factor, offset, scale)],
                              axis=0)

    def binned(self, slabs: list[cla.Array], factor: int, offset: tuple[int, int] = (0, 0),
               scale: float = 1.0) -> list[cla.Array]:
        """:meth:`to_host`'s binned slabs, left on the device (one per slab)."""
        oy, ox = offset
        if not (0 <= oy < factor and 0 <= ox < factor):
            raise ValueError(f"offset {offset} must lie in [0, {factor}) per axis")
        return [self._bin(s, factor, oy, ox, scale) for s in slabs]

    def _bin(self, slab: cla.Array, factor: int, oy: int, ox: int,
             scale: float) -> cla.Array:
        """Launch the kernel on one slab; returns the binned device slab."""
        nz, nyf, nxf = slab.shape
        ny, nx = -(-(oy + nyf) // factor), -(-(ox + nxf) // factor)
        out = self._k.array((nz, ny, nx))
        i32 = np.int32
        if out.size:
            self._k.launch("bin_lateral", (out.size,), slab, i32(nyf), i32(nxf), i32(oy),
                           i32(ox), i32(factor), np.float32(scale), out, i32(ny), i32(nx),
                           i32(out.size))
        return out

    def spread_into(self, coarse: np.ndarray, factor: int, slabs: list[cla.Array],
                    scale: float = 1.0) -> None:
        """Fill the device ``slabs`` (consecutive depth slabs ``(dz, ny f, nx f)`` of one
        volume) with :func:`spread_lateral` of the host volume ``coarse`` ``(nz, ny, nx)``,
        times ``scale``: only the coarse volume crosses to the device."""
        _check_slabs(coarse.shape, factor, slabs)
        _, ny, nx = coarse.shape
        z0, i32 = 0, np.int32
        for slab in slabs:
            part = self._k.to_device(np.ascontiguousarray(coarse[z0:z0 + slab.shape[0]],
                                                          np.float32))
            z0 += slab.shape[0]
            if slab.size:
                self._k.launch("spread_lateral", slab.shape[::-1], part, i32(ny), i32(nx),
                               i32(factor), np.float32(scale / factor**2), slab,
                               i32(ny * factor), i32(nx * factor))

    def row_peaks(self, coarse: cla.Array) -> np.ndarray:
        """The largest value of each ``(z, y)`` row of the device volume ``coarse``
        ``(nz, ny, nx)``, ``(nz * ny,)`` float32 (a row of at least one voxel)."""
        rows = coarse.size // coarse.shape[-1]
        out = self._k.array(rows)
        self._k.launch("row_peaks", (rows,), coarse, np.int32(coarse.shape[-1]), out)
        return out.get()

    def support_rows(self, coarse: cla.Array, floor: float) -> tuple[np.ndarray, np.ndarray]:
        """The support of the device volume ``coarse`` above ``floor`` (the 3 x 3 x 3 box
        grown, as :meth:`spread_support` finds it) by ``(z, y)`` row: its values' float32
        sums along x, in x order, and its voxel counts (``(nz * ny,)`` each)."""
        nz, ny, nx = coarse.shape
        keep = self._grown_support(coarse, floor)
        sums, counts = self._k.array(nz * ny), self._k.array(nz * ny, np.int32)
        self._k.launch("support_rows", (nz * ny,), coarse, keep, np.int32(nx), sums, counts)
        return tuple(read(sums, counts))

    def _grown_support(self, coarse: cla.Array, floor: float) -> cla.Array:
        """The voxels of ``coarse`` ``(nz, ny, nx)`` whose 3 x 3 x 3 box holds one above
        ``floor`` (the ``grown_support`` kernel), a uint8 device volume."""
        nz, ny, nx = coarse.shape
        keep, i32 = self._k.array(coarse.shape, np.uint8), np.int32
        self._k.launch("grown_support", (nx, ny, nz), coarse, i32(nz), i32(ny), i32(nx),
                       np.float32(floor), keep)
        return keep

    def spread_support(self, coarse: cla.Array, floor: float, level: float, factor: int,
                       slabs: list[cla.Array], scale: float = 1.0) -> None:
        """Fill the device ``slabs`` (consecutive depth slabs of one volume, ``factor``
        times finer laterally) with the support of the device volume ``coarse``
        ``(nz, ny, nx)`` spread over its sub-voxels: ``level`` times ``scale /
        factor**2`` where a voxel of the coarse voxel's 3 x 3 x 3 box is above ``floor``,
        else 0 (:func:`spread_lateral` of :meth:`plenocl.reconstruction.schedule.
        SupportStart.flat`, found on the device: nothing crosses)."""
        _, ny, nx = coarse.shape
        _check_slabs(coarse.shape, factor, slabs)
        if not coarse.size:
            return
        keep, i32, z0 = self._grown_support(coarse, floor), np.int32, 0
        for slab in slabs:
            if slab.size:
                self._k.launch("spread_support", slab.shape[::-1], keep, i32(z0), i32(ny),
                               i32(nx), i32(factor), np.float32(level),
                               np.float32(scale / factor**2), slab, i32(ny * factor),
                               i32(nx * factor))
            z0 += slab.shape[0]


def _check_slabs(shape: tuple[int, int, int], factor: int, slabs: list[cla.Array]) -> None:
    """Refuse device ``slabs`` that are not a volume of ``shape`` ``(nz, ny, nx)`` made
    ``factor`` times finer laterally (the spreading's target)."""
    nz, ny, nx = shape
    if sum(s.shape[0] for s in slabs) != nz or any(
            s.shape[1:] != (ny * factor, nx * factor) for s in slabs):
        raise ValueError(f"a {tuple(shape)} volume does not spread by {factor} into slabs "
                         f"{[s.shape for s in slabs]}")
