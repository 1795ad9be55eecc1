"""Where a volume can be non-zero, plane by plane: a separable projector's lateral extent
(docs/design.md §5.5, issue 49).

A posed camera's frame grid is the box in the camera's own frame that holds the tilted
world grid (:func:`plenocl.projection.posed.posed_frame_grid`); each of its planes crosses
the world grid in a band of voxel columns, and on the whole sensor those bands fill 0.6 of
the box. Outside its band a plane's resampled volume is 0, and its back projection is
read by no world voxel. A :class:`PlaneExtent` says so to the separable kernels: plane
``z``'s voxel columns ``[x0, x1)``, and for each aperture column the vectors of the
intermediate rows ``T[(z, i)][y][kx]`` that those columns reach. ``fwd_x_row`` splats the
band's voxels only, ``fwd_y`` and ``back_y`` update the span's vectors only, and
``back_x`` computes the band's voxels only (0 beyond it). Inside the band every kernel
adds the same terms in the same order as without an extent, so the band's results, and
the world volume resampled from them, are the same to the last bit. The whole extent
(every column, whole rows) is what a projector uses by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cl_array

from ..opencl.arrays import upload

#: Lenses added to each side of a span: the kernels compute a voxel's lens coordinate in
#: float32, the host in float64.
SPAN_MARGIN = 1


@dataclass(frozen=True)
class PlaneExtent:
    """A volume's lateral extent per plane, on the host and on the projector's device.

    Attributes
    ----------
    columns
        ``(nz, 2)`` int32: plane ``z``'s voxel columns ``[x0, x1)`` (``x0 == x1``: none).
    spans
        ``(nz, n_columns, 2)`` int32: for aperture column ``i``, the vectors ``[v0, v1)``
        (of the kernels' width) of the rows ``T[(z, i)][y]`` that those columns reach.
    device_columns, device_spans
        The same, on the device.
    """

    columns: np.ndarray
    spans: np.ndarray
    device_columns: cl_array.Array
    device_spans: cl_array.Array

    @classmethod
    def upload(cls, queue, columns: np.ndarray, spans: np.ndarray) -> PlaneExtent:
        """The extent of ``columns`` and ``spans``, copied to ``queue``'s device."""
        columns = np.ascontiguousarray(columns, np.int32)
        spans = np.ascontiguousarray(spans, np.int32)
        return cls(columns, spans, upload(queue, columns), upload(queue, spans))

    @property
    def n_columns(self) -> int:
        """Aperture columns per plane."""
        return int(self.spans.shape[1])


def lens_spans(coef: np.ndarray, columns: np.ndarray, bu: np.ndarray, ny: int, nkx: int,
               vw: int) -> np.ndarray:
    """``(nz, len(bu), 2)`` int: the vectors of ``vw`` lenses that the voxels of each
    plane's ``columns`` reach through each aperture column (``bu``: its offset from the
    aperture's centre), over every voxel row ``0 … ny - 1``.

    On the separable path a voxel ``(ix, iy)`` of plane ``z`` sits at lens column
    ``kx = c0 ix + c1 iy + c6 bu + c4`` (``coef[z]``, kernels/projector.h ``pl_kx``) and
    weighs on ``floor(kx)`` and the next. ``kx`` is affine in ``ix`` and ``iy``, so its
    extremes lie at the band's and the rows' ends; the span holds them and
    :data:`SPAN_MARGIN` lenses more each side, clipped to the array.
    """
    coef = np.asarray(coef, np.float64)
    x = np.asarray(columns, np.int64)
    ix = np.stack([x[:, 0], x[:, 1] - 1], axis=1).astype(np.float64)  # (nz, 2)
    lateral = (coef[:, 0, None, None] * ix[:, :, None]
               + coef[:, 1, None, None] * np.array([0.0, ny - 1.0])[None, None, :])
    lateral = lateral.reshape(len(x), -1)
    shift = coef[:, 6, None] * np.asarray(bu, np.float64)[None, :] + coef[:, 4, None]
    first = np.floor(lateral.min(axis=1)[:, None] + shift) - SPAN_MARGIN
    last = np.floor(lateral.max(axis=1)[:, None] + shift) + 1 + SPAN_MARGIN
    empty = (x[:, 1] <= x[:, 0])[:, None] | (last < 0) | (first > nkx - 1)
    first, last = np.clip(first, 0, nkx - 1), np.clip(last, 0, nkx - 1)
    spans = np.stack([first // vw, last // vw + 1], axis=-1).astype(np.int64)
    spans[empty] = 0
    return spans


def whole_columns(nz: int, nx: int) -> np.ndarray:
    """``(nz, 2)``: every voxel column of every plane."""
    return np.tile(np.array([0, nx], np.int64), (nz, 1))
