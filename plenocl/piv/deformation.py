"""The two ways :func:`plenocl.piv3d` deforms volumes: on the host
(:func:`plenocl.piv.interpolate.deform`, SciPy ``map_coordinates``, the reference) or on
an OpenCL device (``kernels/deform.cl``, one work-item per voxel).

Both take a volume once (:meth:`prepare`: zero margin, B-spline filter) and then sample it
at ``p + factor * d(p)`` for a dense predictor ``d`` as often as the passes need.
Deformation is most of a deformed pass's time on a CPU with SciPy (single-threaded); the
kernel spreads it over every core of a CPU and over a GPU.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array

from ..opencl.arrays import inside_zeros
from ..opencl.device import DeviceLike, NoOpenCLError, check_fits, get_queue
from ..opencl.program import KernelSet
from .interpolate import MARGIN, axis_weights, deform, prepare, resample


class HostDeformer:
    """Deformation with SciPy (:func:`plenocl.piv.interpolate.deform`), any order 1, 3, 5."""

    def __init__(self, order: int) -> None:
        self.order = order

    def prepare(self, vol: np.ndarray) -> np.ndarray:
        """The padded (and for orders 3, 5 spline-filtered) volume."""
        return prepare(vol, self.order)

    def field(self, displacement: np.ndarray) -> np.ndarray:
        """A dense predictor ``(3, nz, ny, nx)`` ready for :meth:`__call__` (itself)."""
        return displacement

    def predictor(self, field: np.ndarray, source: tuple[np.ndarray, ...],
                  shape: tuple[int, int, int], kind: str = "cubic") -> np.ndarray:
        """The dense predictor of ``field`` ``(3, *counts)`` (window centres ``source``,
        ``(z, y, x)``) on every voxel of a volume of ``shape``, ready for
        :meth:`__call__`: :func:`plenocl.piv.interpolate.resample` in float32."""
        voxels = tuple(np.arange(n, dtype=float) for n in shape)
        return resample(field, source, voxels, kind, np.float32)

    def __call__(self, prepared: np.ndarray, displacement: np.ndarray,
                 factor: float, keep: bool = False) -> np.ndarray:
        """``vol(p + factor * displacement(p))`` for every voxel, float32 (``keep`` is
        :class:`DeviceDeformer`'s; the host's volume is where it is kept)."""
        return deform(prepared, displacement, factor, self.order)


class DeviceDeformer:
    """Deformation by ``kernels/deform.cl`` on an OpenCL device (orders 1 and 3).

    Parameters
    ----------
    queue
        Device to run on (:func:`plenocl.get_queue` rules).
    order
        1 (trilinear) or 3 (cubic B-spline), as :func:`plenocl.piv.interpolate.deform`.
    """

    def __init__(self, queue: DeviceLike, order: int) -> None:
        if order not in DEVICE_ORDERS:
            raise ValueError(f"device deformation supports deform_order 1 and 3, got {order}; "
                             "use queue=False for the quintic B-spline (host)")
        self.order = order
        self.kernels = KernelSet(get_queue(queue), "deform.cl",
                                 ["deform", "spline_prefilter", "resample_axis"],
                                 options=[f"-DORDER={order}"],
                                 looping=["spline_prefilter", "resample_axis"])

    def prepare(self, vol):
        """The padded, filtered volume (:func:`~plenocl.piv.interpolate.prepare`, the host
        reference) on the device: copied into zeros there, B-spline filtered there
        (``spline_prefilter``, axis by axis as SciPy). ``vol``: a host volume, or a
        float32 device volume on this queue's context (copied there, not uploaded)."""
        if not isinstance(vol, cl_array.Array):
            vol = np.ascontiguousarray(vol, np.float32)
        nz, ny, nx = vol.shape
        shape = (nz + 2 * MARGIN, ny + 2 * MARGIN, nx + 2 * MARGIN)
        check_fits(self.kernels.queue, 4 * (2 * int(np.prod(shape)) + 4 * vol.size),
                   "PIV volume deformation")
        # zeros on the device, the volume copied inside them (np.pad's constant mode)
        coeffs = inside_zeros(self.kernels.queue, vol, shape, (MARGIN,) * 3)
        if self.order == 3:
            self.prefilter(coeffs)
        return coeffs

    def prefilter(self, coeffs) -> None:
        """Turn a padded device volume into its cubic B-spline coefficients in place
        (``scipy.ndimage.spline_filter(mode="mirror")``): z, then y, then x."""
        pz, py, px = coeffs.shape
        plane = py * px
        for n, stride, size, steps in ((pz, plane, (px, py), (1, px)),
                                       (py, px, (px, pz), (1, plane)),
                                       (px, 1, (py, pz), (px, plane))):
            self.kernels.launch("spline_prefilter", size, coeffs, np.int32(n),
                                np.int32(stride), *map(np.int32, steps))

    def field(self, displacement: np.ndarray):
        """A dense predictor ``(3, nz, ny, nx)`` copied to the device once, for both
        volumes of a pass."""
        return self.kernels.to_device(np.asarray(displacement, np.float32))

    def predictor(self, field: np.ndarray, source: tuple[np.ndarray, ...],
                  shape: tuple[int, int, int], kind: str = "cubic"):
        """:meth:`HostDeformer.predictor` made on the device (``resample_axis``, x then y
        then z, as the host's tensor products): only the window-centre field and the
        three weight matrices are uploaded, not the dense predictor."""
        out = self.kernels.to_device(np.ascontiguousarray(field, np.float32))
        for axis in (3, 2, 1):
            weights = axis_weights(kind, source[axis - 1], np.arange(shape[axis - 1],
                                                                     dtype=float))
            ntgt, nsrc = weights.shape
            dims = list(out.shape)
            inner, outer = int(np.prod(dims[axis + 1:])), int(np.prod(dims[:axis]))
            dims[axis] = ntgt
            step = self.kernels.array(tuple(dims))
            self.kernels.launch("resample_axis", (inner, ntgt, outer), out, np.int32(nsrc),
                                self.kernels.to_device(weights.astype(np.float32)), step)
            out = step
        return out

    def __call__(self, prepared, displacement, factor: float, keep: bool = False):
        """``vol(p + factor * displacement(p))`` for every voxel, float32, on the device;
        ``displacement`` from :meth:`field` or :meth:`predictor`. The host's copy, or with
        ``keep`` the device array (for the window sums and correlations on the device)."""
        shape = displacement.shape[1:]
        out = self.kernels.array(shape)
        pz, py, px = prepared.shape
        self.kernels.launch("deform", shape[::-1], prepared, np.int32(pz), np.int32(py),
                            np.int32(px), displacement, np.int32(MARGIN), np.float32(factor), out)
        return out if keep else out.get()


#: B-spline orders ``kernels/deform.cl`` has (the quintic is host-only).
DEVICE_ORDERS = (1, 3)


def make_deformer(order: int, queue: DeviceLike | bool = None):
    """The deformer for ``queue``, chosen as every stage chooses its device: ``None``
    the default device (``PYOPENCL_CTX``, else the preferred one that builds), ``True``
    the same, ``False`` the host (SciPy, the reference), anything else that device. The
    quintic B-spline has no kernel: it is deformed on the host whatever ``queue`` says
    (so ``deform_order = 5`` works in ``process_pair`` and a batch run too)."""
    if queue is False or order not in DEVICE_ORDERS:
        return HostDeformer(order)
    try:
        return DeviceDeformer(None if queue is True else queue, order)
    except NoOpenCLError as exc:
        if queue not in (None, True):
            raise
        raise NoOpenCLError(f"{exc}; or deform the PIV volumes on the host with SciPy "
                            "(piv3d(..., queue=False), several times slower)") from exc
