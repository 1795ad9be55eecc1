"""How the projector splits its work so that every buffer fits the device: plain NumPy.

A volume larger than the device's largest allocation is held as depth slabs; the
light-field buffer ``L[ky, s, kx]`` is filled for a chunk of consecutive aperture
columns at a time, and the per-axis intermediates for a chunk of depth slices. Nothing
here touches a device, so the plan is tested on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..grid import Grid
from .weighting import ApertureGrid


@dataclass(frozen=True)
class Plan:
    """How the work is split: volume slabs, aperture-column chunks, depth chunks."""

    slabs: tuple[tuple[int, int], ...]    # [z0, z1) of each volume buffer
    columns: tuple[tuple[int, int], ...]  # [i0, i1) aperture columns per light-field chunk
    zchunk: int                           # depth slices per intermediate (T) chunk
    scratch_bytes: int                    # bytes of the light-field + T scratch buffers


@dataclass(frozen=True)
class SampleColumns:
    """Where each aperture column's in-aperture samples sit in the flat sample list.

    Column ``i`` holds samples ``j = lo[i] … hi[i]`` (none when ``hi[i] < lo[i]``), stored
    from flat index ``offset[i]`` on (``i`` major, as :meth:`ApertureGrid.samples`).
    """

    lo: np.ndarray
    hi: np.ndarray
    offset: np.ndarray

    @classmethod
    def of(cls, aperture: ApertureGrid) -> SampleColumns:
        """The column layout of ``aperture``'s samples."""
        lo, hi = aperture.column_ranges()
        return cls(lo, hi, np.concatenate([[0], np.cumsum(hi - lo + 1)[:-1]]))

    def sample_range(self, i0: int, i1: int) -> tuple[int, int]:
        """Flat ``[s0, s1)`` of the samples of aperture columns ``[i0, i1)``."""
        end = self.offset[i1 - 1] + (self.hi[i1 - 1] - self.lo[i1 - 1]) + 1
        return int(self.offset[i0]), int(end)


def make_plan(grid: Grid, camera: Camera, aperture: ApertureGrid, nkxp: int,
              max_alloc: int, scratch_bytes: int, method: str) -> Plan:
    """Split the volume into slabs and the light field into column chunks that fit.

    Parameters
    ----------
    grid, camera, aperture
        The geometry.
    nkxp
        Light-field row length (lens columns padded to the vector width).
    max_alloc
        Largest single device buffer, in bytes.
    scratch_bytes
        Upper bound of each scratch buffer (light field, intermediates).
    method
        ``"factorised"`` or ``"direct"`` (no scratch).

    Raises
    ------
    MemoryError
        When the image, one depth slice or one aperture column cannot be allocated.
    """
    nz, ny, nx = grid.shape
    width, height = camera.pixels
    if 4 * width * height > max_alloc:
        raise MemoryError(f"the {width} x {height} image needs {4 * width * height} bytes but "
                          f"the device allocates at most {max_alloc} bytes per buffer")
    slice_bytes = 4 * ny * nx
    if slice_bytes > max_alloc:
        raise MemoryError(f"one {ny} x {nx} depth slice needs {slice_bytes} bytes but the "
                          f"device allocates at most {max_alloc} bytes per buffer")
    depth = max(1, max_alloc // slice_bytes)
    slabs = tuple((z, min(z + depth, nz)) for z in range(0, nz, depth))
    if method == "direct":
        return Plan(slabs, ((0, aperture.n),), 1, 0)
    budget = min(max_alloc, scratch_bytes)
    lo, hi = aperture.column_ranges()
    row = 4 * camera.ml_count[1] * nkxp  # one sample's light-field plane
    t_row = 4 * ny * nkxp                # one (depth, column) intermediate
    columns = column_chunks((hi - lo + 1) * row, t_row, budget)
    widest = max(b - a for a, b in columns)
    zchunk = max(1, min(nz, budget // (widest * t_row)))
    l_bytes = max((hi[a:b] - lo[a:b] + 1).sum() * row for a, b in columns)
    return Plan(slabs, tuple(columns), zchunk, int(l_bytes + zchunk * widest * t_row))


def column_chunks(column_bytes: np.ndarray, t_row: int, budget: int) -> list[tuple[int, int]]:
    """Consecutive aperture columns whose light field (and one T slice) fit ``budget``."""
    if column_bytes.max() > budget or t_row > budget:
        raise MemoryError(f"one aperture column of the light field needs "
                          f"{max(column_bytes.max(), t_row)} bytes but at most {budget} bytes "
                          "may be allocated per buffer")
    columns, start, size = [], 0, 0
    for i, need in enumerate(column_bytes):
        if size + need > budget or (i - start + 1) * t_row > budget:
            columns.append((start, i))
            start, size = i, 0
        size += need
    columns.append((start, len(column_bytes)))
    return columns


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[a, b)`` ranges of consecutive ``True`` entries of a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, np.int8), [0]]))
    return list(zip(np.nonzero(edges == 1)[0].tolist(), np.nonzero(edges == -1)[0].tolist()))


def depth_chunks(z0: int, z1: int, active: np.ndarray, zchunk: int):
    """``(zc, nzc)`` chunks of at most ``zchunk`` consecutive active slices in ``[z0, z1)``."""
    for a, b in runs(active[z0:z1]):
        for zc in range(z0 + a, z0 + b, zchunk):
            yield zc, min(zchunk, z0 + b - zc)
