"""The image fit's per-particle sums on the OpenCL device (docs/design.md §7.2).

:class:`DeviceFitSums` renders every particle's patch rows with a
:class:`plenocl.piv.devicebundle.DeviceRayBundle` into one device buffer and reduces them
there with ``kernels/imagefit.cl``: the model image of all particles, each particle's
Gauss-Newton normal equations and residual scatter, and the start intensity's sums. Only
16 floats per particle come back to the host, which solves the 4 x 4 systems
(:class:`plenocl.piv.imagefit.ImageFit`). The host's NumPy sums stay the path without a
queue; ``plenocl.reference.imagefit`` holds the kernels' twins.
"""

from __future__ import annotations

import threading

import numpy as np
import pyopencl.array as cl_array

from ..opencl.device import is_cpu
from ..opencl.program import KernelSet, group_size
from ..opencl.rowlists import DeviceRowLists
from ..optics.raybundle import Patches
from .devicebundle import SLOT, DeviceRayBundle

i32, i64, f32 = np.int32, np.int64, np.float32
_KERNELS = ("patch_model", "normal_sums", "unit_sums")
#: Sensor columns per work-item of the model image: one on a GPU, a run on a CPU.
MODEL_BLOCK = {False: 1, True: 256}
#: Particles rendered at once on a CPU device and on the host (a CPU's caches).
HOST_CHUNK = 128
#: The rays' scratch a GPU's rendering may take at once: its default chunk (2,892
#: particles at 200 rays: the paper pair's 2,789 in one launch, not 22 of 128).
GPU_SCRATCH_BYTES = 256 * 2**20
#: The kept rows buffer, too small, is made this much larger than asked (within the
#: device's largest buffer): a fit's patches change a little at every step as its
#: particles move (the 116 x 78 pair's rows 32.13 → 32.97 million floats over eight
#: steps), and a buffer made exactly to size was made again at most steps, each a fresh
#: buffer's page faults. The model image keeps the sensor's size: made to size.
KEPT_HEADROOM = 1.25


def fit_chunk(renderer: DeviceRayBundle, chunk: int | None = None) -> int:
    """Particles ``renderer`` renders at once: ``chunk`` when given; else
    :data:`HOST_CHUNK` on a CPU device, and on a GPU as many as
    :data:`GPU_SCRATCH_BYTES` of ray slots and keys hold, within the device's largest
    buffer (each launch costs the host its uploads and index tables, so fewer is faster
    there). The rows are the same for any chunk: each particle's are written alone."""
    if chunk is not None:
        return int(chunk)
    device = renderer.queue.device
    if is_cpu(device):
        return HOST_CHUNK
    per_particle = renderer.bundle.rays * 4 * (SLOT + 1) * 4
    budget = min(GPU_SCRATCH_BYTES, int(device.max_mem_alloc_size))
    return max(HOST_CHUNK, budget // per_particle)


class DeviceFitSums:
    """The fit's sums on ``renderer``'s queue.

    Parameters
    ----------
    renderer
        The device ray bundle that renders the particles' rows.
    chunk
        Particles rendered at once (bounds the rays' scratch memory); ``None``:
        :func:`fit_chunk`'s.
    group
        Work-items per particle of the sums (a power of two); ``None``: 1 on a CPU,
        :data:`plenocl.opencl.program.GPU_GROUP` elsewhere.

    Notes
    -----
    One computation at a time per object (a lock): both exposures' fits may run on two
    threads (:meth:`plenocl.piv.imagefit.ImageFit.refine_pair`). The rendered rows and the
    model image live in buffers kept from one computation to the next (grown as needed):
    on a CPU device a fresh buffer costs a page fault per 4 KiB at its first touch, which
    on a paper-size fit took longer than the rendering itself.
    """

    def __init__(self, renderer: DeviceRayBundle, chunk: int | None = None,
                 group: int | None = None) -> None:
        self.renderer = renderer
        self.chunk = fit_chunk(renderer, chunk)
        cpu = is_cpu(renderer.queue.device)
        self.group = group_size(renderer.queue, group)
        self._k = KernelSet(renderer.queue, "imagefit.cl", _KERNELS,
                            [f"-DPL_GROUP={self.group}"], looping=["patch_model"])
        self._block = MODEL_BLOCK[cpu]
        self._lock = threading.Lock()
        self._kept: dict[str, cl_array.Array] = {}
        self._lists = DeviceRowLists(renderer.queue)

    def upload(self, image: np.ndarray) -> cl_array.Array:
        """A device copy (float32) of a sensor-shaped ``(rows, cols)`` image."""
        return self._k.to_device(np.asarray(image, f32))

    def fits(self, patches: Patches) -> bool:
        """Whether the rows of ``patches`` (with derivatives) fit one device buffer."""
        return 5 * 4 * int(patches.offset[-1]) <= self.renderer.queue.device.max_mem_alloc_size

    def unit_sums(self, data: cl_array.Array, image_points: np.ndarray,
                  patches: Patches, data_scale: float = 1.0) -> np.ndarray:
        """Per particle ``(n, 2)``: ``sum(unit * image)`` and ``sum(unit^2)`` of its image
        at unit intensity, over its patch; the image is ``data * data_scale`` (``data``
        from :meth:`upload` and 1, or a device image in other units: a reconstruction's,
        divided by its maximum, and that maximum)."""
        n = len(image_points)
        if n == 0:
            return np.zeros((0, 2))
        with self._lock:
            geometry = self._geometry(patches)  # once for both kernels
            unit = self._render(image_points, np.ones(n), patches, geometry, False)
            return self._reduce_units(unit, data, geometry, data_scale)

    def normal_sums(self, data: cl_array.Array, image_points: np.ndarray,
                    intensity: np.ndarray, patches: Patches, jac: np.ndarray,
                    data_scale: float = 1.0) -> np.ndarray:
        """Per particle ``(n, 16)``: ``J^T J`` (upper triangle, row by row), ``J^T r``,
        the lit elements and their summed squared residuals
        (:func:`plenocl.reference.imagefit.normal_sums`), against the model image of all
        ``n`` particles; ``jac`` ``(n, 3, 3)``: ``d (X', Y', d') / d (x, y, z)``; the
        image is ``data * data_scale`` (:meth:`unit_sums`)."""
        n = len(image_points)
        if n == 0:
            return np.zeros((0, 16))
        with self._lock:
            geometry = self._geometry(patches)  # once for the three kernels
            rows = self._render(image_points, intensity, patches, geometry, True)
            model = self._model(rows, patches, geometry, data.shape)
            return self._reduce_normals(rows, data, model, geometry, jac, data_scale)

    def reduce_units(self, unit: cl_array.Array, data: cl_array.Array,
                     patches: Patches, data_scale: float = 1.0) -> np.ndarray:
        """The ``unit_sums`` kernel on rendered value rows ``unit`` (device, float32) and
        the image ``data * data_scale``: :func:`plenocl.reference.imagefit.unit_sums`,
        ``(n, 2)`` float64."""
        return self._reduce_units(unit, data, self._geometry(patches), data_scale)

    def _reduce_units(self, unit: cl_array.Array, data: cl_array.Array,
                      geometry: list[cl_array.Array], data_scale: float) -> np.ndarray:
        """:meth:`reduce_units` with the patches' :meth:`_geometry` on the device."""
        n = geometry[1].size
        out = self._k.array(2 * n)
        self._k.launch("unit_sums", (n * self.group,), unit, data, f32(data_scale),
                       *geometry, *_sensor(data), out, local_size=(self.group,))
        return out.get().reshape(n, 2).astype(np.float64)

    def reduce_normals(self, rows: cl_array.Array, data: cl_array.Array,
                       model: cl_array.Array, patches: Patches, jac: np.ndarray,
                       data_scale: float = 1.0) -> np.ndarray:
        """The ``normal_sums`` kernel on rendered ``rows`` (device, 5 rows of the patches'
        elements) and the image ``data * data_scale``:
        :func:`plenocl.reference.imagefit.normal_sums`, ``(n, 16)`` float64."""
        return self._reduce_normals(rows, data, model, self._geometry(patches), jac,
                                    data_scale)

    def _reduce_normals(self, rows: cl_array.Array, data: cl_array.Array,
                        model: cl_array.Array, geometry: list[cl_array.Array],
                        jac: np.ndarray, data_scale: float) -> np.ndarray:
        """:meth:`reduce_normals` with the patches' :meth:`_geometry` on the device."""
        n = len(jac)
        out = self._k.array(16 * n)
        self._k.launch("normal_sums", (n * self.group,), rows, i64(rows.size // 5), data,
                       f32(data_scale), model, *geometry, *_sensor(data),
                       self._k.to_device(np.asarray(jac, f32)), out, local_size=(self.group,))
        return out.get().reshape(n, 16).astype(np.float64)

    def _render(self, image_points: np.ndarray, intensity: np.ndarray, patches: Patches,
                geometry: list[cl_array.Array], derivatives: bool) -> cl_array.Array:
        """Every particle's rows into one device buffer, ``chunk`` particles at a time
        (the points and ``geometry`` uploaded once for all)."""
        total = int(patches.offset[-1])
        rows = self._kept_array("rows", (5 if derivatives else 1) * total, KEPT_HEADROOM)
        self.renderer.render_into(image_points, intensity, patches, derivatives, rows,
                                  total, chunk=self.chunk, tables=geometry)
        return rows

    def model(self, values: cl_array.Array, patches: Patches,
              shape: tuple[int, int]) -> cl_array.Array:
        """The sum of every particle's value patch (the first row of ``values``) on the
        sensor ``shape`` ``(rows, cols)``: the ``patch_model`` kernel,
        :func:`plenocl.reference.imagefit.patch_model`."""
        return self._model(values, patches, self._geometry(patches), shape)

    def _model(self, values: cl_array.Array, patches: Patches,
               geometry: list[cl_array.Array], shape: tuple[int, int]) -> cl_array.Array:
        """:meth:`model` with the patches' :meth:`_geometry` on the device; each sensor
        row's particles listed there (:class:`plenocl.opencl.rowlists.DeviceRowLists`:
        only the patches' rows cross, not the lists)."""
        lists = self._lists.rows(patches.row0, patches.row0 + patches.height, shape[0])
        model = self._kept_array("model", shape[0] * shape[1]).reshape(shape)
        blocks = -(-shape[1] // self._block)
        self._k.launch("patch_model", (blocks, shape[0]), values, *geometry[:4],
                       lists.start_device, lists.items, i32(shape[1]), i32(self._block),
                       model)
        return model

    def _kept_array(self, name: str, size: int, headroom: float = 1.0) -> cl_array.Array:
        """The first ``size`` floats of the kept buffer ``name``, grown to hold them
        (:func:`kept_size` with ``headroom``; the in-order queue finishes the previous
        computation's kernels before new ones)."""
        kept = self._kept.get(name)
        if kept is None or kept.size < size:
            largest = self.renderer.queue.device.max_mem_alloc_size // 4
            kept = self._kept[name] = self._k.array(kept_size(size, largest, headroom))
        return kept[:size]

    def _geometry(self, patches: Patches) -> list[cl_array.Array]:
        """The patches' offset (long), col0, row0, width and height (int) on the device
        (:meth:`plenocl.piv.devicebundle.DeviceRayBundle.patch_tables`)."""
        return self.renderer.patch_tables(patches)


def kept_size(size: int, largest: int, headroom: float) -> int:
    """Floats to make a kept buffer that must hold ``size``: ``headroom`` times it, but
    no more than ``largest`` (the device's largest buffer), never less than ``size``
    (a buffer beyond ``largest`` is the driver's to refuse) and at least one."""
    return max(min(int(size * headroom), largest), size, 1)


def _sensor(image: cl_array.Array) -> tuple[np.int32, np.int32]:
    """``(cols, rows)`` of a sensor-shaped device image, as kernel arguments."""
    return i32(image.shape[1]), i32(image.shape[0])
