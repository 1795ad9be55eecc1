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
from ..opencl.device import DeviceInfo
from ..opencl.program import KernelSet

#: Largest accepted factor (memory and time grow as its square).
MAX_SUPERSAMPLE = 4
#: The parts a coarse volume's support sums come in (:func:`row_parts`): what
#: :meth:`LateralBinning.support_sums` reads back instead of one sum per row.
SUPPORT_PARTS = 256


def row_parts(row_sums: np.ndarray, parts: int = SUPPORT_PARTS) -> np.ndarray:
    """``(parts,)`` float64: the float32 ``row_sums`` combined into ``parts`` parts, part
    ``p`` the rows ``p, p + parts, p + 2 parts, ...`` added in that order in float64
    (0 for a part without rows): the order of the device's ``support_parts``, so the
    same bits from either."""
    rows = np.asarray(row_sums, np.float32).reshape(-1)
    padded = np.zeros(-(-rows.size // parts) * parts)
    padded[:rows.size] = rows
    out = np.zeros(parts)
    for block in padded.reshape(-1, parts):  # row by row: the kernel's order
        out += block
    return out


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
    fp64
        Whether :meth:`support_sums` combines the rows into parts on the device
        (``support_parts``, double precision); ``None``: where the device has
        ``cl_khr_fp64``.
    """

    def __init__(self, queue: cl.CommandQueue, fp64: bool | None = None) -> None:
        self.fp64 = DeviceInfo.probe(queue.device).fp64 if fp64 is None else bool(fp64)
        looping = ["support_rows"] + (["support_parts"] if self.fp64 else [])
        self._k = KernelSet(queue, "supersample.cl",
                            ["bin_lateral", "spread_lateral", "grown_support",
                             "spread_support", *looping],
                            ["-DPL_DOUBLE"] if self.fp64 else [], looping=looping)

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

    def support_sums(self, coarse: cla.Array, floor: float) -> tuple[np.ndarray, int]:
        """The support of the device volume ``coarse`` above ``floor`` (the 3 x 3 x 3 box
        grown, as :meth:`spread_support` finds it): its values' sums as
        :data:`SUPPORT_PARTS` float64 parts (:func:`row_parts` of its ``(z, y)`` rows'
        float32 sums along x, in x order; the parts made on the device with
        :attr:`fp64`, else the rows read and combined here: the same bits) and its voxel
        count."""
        nz, ny, nx = coarse.shape
        rows = nz * ny
        keep = self._grown_support(coarse, floor)
        sums, counts = self._k.array(rows), self._k.array(rows, np.int32)
        self._k.launch("support_rows", (rows,), coarse, keep, np.int32(nx), sums, counts)
        if not self.fp64:
            sums, counts = read(sums, counts)
            return row_parts(sums), int(counts.sum(dtype=np.int64))
        parts = self._k.array(SUPPORT_PARTS, np.float64), self._k.array(SUPPORT_PARTS,
                                                                        np.int64)
        self._k.launch("support_parts", (SUPPORT_PARTS,), sums, counts, np.int32(rows),
                       *parts)
        sums, counts = read(*parts)
        return sums, int(counts.sum(dtype=np.int64))

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
