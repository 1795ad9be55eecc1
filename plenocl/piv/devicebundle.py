"""The image fit's ray bundles rendered on the OpenCL device (docs/design.md §7.2).

:class:`DeviceRayBundle` renders what :meth:`plenocl.optics.raybundle.RayBundle.render`
renders, the particles' images on their patches and the derivatives by the image point
and the intensity, with ``kernels/raybundle.cl`` in float32: one work-item per (ray,
particle) traces the rays and their lens choices (a hexagonal array's cells with
``-DPL_HEXAGONAL``: ``ray_spots_hex``), one work-item per patch row (on a GPU) or per
patch (on a CPU) gathers them. The NumPy :class:`RayBundle` stays the fit's
renderer without a queue and the kernel's twin in the tests.
"""

from __future__ import annotations

import threading

import numpy as np
import pyopencl as cl
import pyopencl.cltypes

from ..opencl.arrays import queue_kept
from ..opencl.device import is_cpu
from ..opencl.program import KernelSet
from ..optics.raybundle import Patches, RayBundle

i32, i64, f32 = np.int32, np.int64, np.float32
#: Floats per (particle, ray, lens choice) slot (``PL_SLOT`` of the kernel).
SLOT = 28


#: Above this delta^2 = 1 / (2 sigma^2) the kernel's two-exp form of a ray's pixel edges
#: (``pl_spread``) could overflow float32: each edge takes its own exp.
FAST_SPREAD_MAX = 30.0


def _spread_constants(blur_px: float) -> tuple[np.float32, np.ndarray]:
    """``ray_spots``' ``delta`` = 1 / (sqrt2 sigma) and ``gauss`` (float4): the constants
    ``exp(-k^2 delta^2 / 4)``, k = 1, 3, 5, of its pixel edges, or -1 (an exp per edge)
    where they do not suit (:data:`FAST_SPREAD_MAX`)."""
    delta = 1.0 / (np.sqrt(2.0) * blur_px)
    gauss = cl.cltypes.make_float4(*np.exp(-np.array([1, 9, 25]) * delta**2 / 4), 0)
    if delta**2 > FAST_SPREAD_MAX:
        gauss = cl.cltypes.make_float4(-1, 0, 0, 0)
    return f32(delta), gauss


class DeviceRayBundle:
    """A :class:`RayBundle` on one queue, rendering as :meth:`RayBundle.render`.

    Parameters
    ----------
    bundle
        The camera's rays (aperture samples, lens centres, lattice, blur).
    queue
        The OpenCL queue (the pipeline's projector's).

    Notes
    -----
    One render at a time per object (a lock): :meth:`plenocl.piv.imagefit.ImageFit.
    refine_pair` renders both exposures from two threads. The rays' scratch buffers are
    kept and reused (a fresh buffer's first touch costs page faults on a CPU device), so
    ``queue`` must be in order, as plenocl's queues are.
    """

    def __init__(self, bundle: RayBundle, queue: cl.CommandQueue) -> None:
        self.bundle = bundle
        self.queue = queue
        self._programs: dict[bool, KernelSet] = {}
        self._lock = threading.Lock()
        #: Patch rows per work-item of ``render_rows``: 1 on a GPU (wide ranges), 0 (a
        #: particle's whole patch: its slots' keys scanned once) on a CPU.
        self.rows_per_item = 0 if is_cpu(queue.device) else 1
        self._scratch: tuple | None = None
        cam = bundle.camera
        k = self._kernels(True)
        # the camera's tables go up once per queue, not once per pair's fit
        self._aperture = queue_kept(queue, "raybundle.aperture", bundle.aperture.astype(f32))
        self._lenses = queue_kept(queue, "raybundle.lenses", self._lens_pixels().astype(f32))
        lattice = tuple(f32(v) for v in bundle.to_lattice.ravel())
        spacing = cam.exit_pupil_diameter_mm / 2 * np.sqrt(np.pi / bundle.rays) / cam.ml_pitch_mm
        self._f_px = f32(cam.ml_focal_length_mm / cam.pixel_pitch_mm)
        self._optics = (*lattice, f32(cam.exit_pupil_distance_mm), self._f_px, f32(spacing),
                        *_spread_constants(bundle.blur_px))
        if bundle.cells is not None:
            self._optics += self._hexagonal_cells(k)

    @property
    def _spots(self) -> str:
        """The kernel that traces the rays: ``ray_spots_hex`` on hexagonal cells."""
        return "ray_spots" if self.bundle.cells is None else "ray_spots_hex"

    def _hexagonal_cells(self, k: KernelSet) -> tuple:
        """``ray_spots_hex``'s cell arguments: the metric, the neighbours' steps and their
        table (``kernels/raybundle.cl``)."""
        cells = self.bundle.cells
        gram = cells.gram
        along = cells.steps @ gram  # the metric times each step
        table = np.column_stack([(along * cells.steps).sum(axis=1), along,
                                 -(cells.steps @ cells.model[:2]) / cells.pitch**2])
        return (cl.cltypes.make_float4(gram[0, 0], gram[0, 1], gram[1, 1], 0),
                k.to_device(cells.steps.astype(i32)), k.to_device(table.astype(f32)))

    def _kernels(self, derivatives: bool) -> KernelSet:
        """The program of one variant (``-DPL_DERIVATIVES``), built on first use."""
        if derivatives not in self._programs:
            hexagonal = int(self.bundle.cells is not None)
            self._programs[derivatives] = KernelSet(
                self.queue, "raybundle.cl", (self._spots, "render_rows"),
                [f"-DPL_DERIVATIVES={int(derivatives)}", f"-DPL_HEXAGONAL={hexagonal}"],
                looping=["render_rows"])
        return self._programs[derivatives]

    def _lens_pixels(self) -> np.ndarray:
        """``(rows, cols, 2)`` float64: where a ray along the axis through each lens lands on
        the sensor (``(col, row)`` pixels; NaN for a missing lens)."""
        cam = self.bundle.camera
        return cam.mm_to_px(self.bundle.lenses)

    def render(self, image_points: np.ndarray, intensity: np.ndarray, patches: Patches,
               derivatives: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`RayBundle.render`, on the device.

        Returns the patch elements the light reaches ``(n,)`` (ascending; the rest are
        zero) and their rows ``(5, n)`` float32: value, d/dX', d/dY', d/dd' and d/dI;
        the value row alone ``(1, n)`` without ``derivatives``.
        """
        with self._lock:
            rows = self._render(np.asarray(image_points, f32), np.asarray(intensity, f32),
                                patches, bool(derivatives))
        # d/dI (the unit image) is positive exactly where the light reaches
        elements = np.flatnonzero(rows[-1] if derivatives else rows[0] != 0)
        return elements, rows[:, elements]

    def _render(self, points: np.ndarray, intensity: np.ndarray, patches: Patches,
                derivatives: bool) -> np.ndarray:
        """Both kernels for one set of particles; the rows on the host."""
        total = int(patches.offset[-1])
        if len(points) == 0 or total == 0:
            return np.zeros((5 if derivatives else 1, total), f32)
        k = self._kernels(derivatives)
        out = k.array((5 if derivatives else 1) * total)
        every = [k.to_device(points), k.to_device(intensity), *self.patch_tables(patches)]
        self._launch(k, every, patches.height, 0, out, total)
        return out.get().reshape(-1, total)

    def render_into(self, image_points: np.ndarray, intensity: np.ndarray,
                    patches: Patches, derivatives: bool, out, total: int,
                    chunk: int | None = None, tables: list | None = None
                    ) -> list[cl.Event]:
        """Render into the device array ``out`` and leave the rows there.

        ``out`` holds the rows (5 with ``derivatives``, else 1) of ``total`` elements each;
        ``patches.offset`` places each particle's patch in them. Every element of every
        patch is written. ``chunk``: particles traced at a time (bounds the rays' scratch
        memory; all at once by default); the points, intensities and ``tables`` (the
        patches' :meth:`patch_tables`, made here when ``None``) go up once for all
        chunks. Returns the events of ``ray_spots`` and ``render_rows``, per chunk (none
        without particles), for a profiling queue's timings
        (``benchmarks/raybundle_kernels.py``).
        """
        n = len(image_points)
        if n == 0:
            return []
        with self._lock:
            k = self._kernels(bool(derivatives))
            every = [k.to_device(np.asarray(image_points, f32)),
                     k.to_device(np.asarray(intensity, f32)),
                     *(tables or self.patch_tables(patches))]
            step = n if chunk is None else max(int(chunk), 1)
            return [event for first in range(0, n, step) for event in self._launch(
                k, every, patches.height[first:first + step], first, out, total)]

    def patch_tables(self, patches: Patches) -> list:
        """The patches' offset (long), col0, row0, width and height (int) on the device,
        as :meth:`render_into` and the fit's sums (:mod:`plenocl.piv.fitsums`) read them."""
        k = self._kernels(True)
        return [k.to_device(patches.offset.astype(i64))] + [
            k.to_device(a.astype(i32))
            for a in (patches.col0, patches.row0, patches.width, patches.height)]

    def _launch(self, k: KernelSet, every: list, heights: np.ndarray, first: int, out,
                total: int) -> list[cl.Event]:
        """Enqueue both kernels for the particles from ``first`` (``heights``: their
        patches' heights) of ``every`` (points, intensities and patch tables on the
        device), rows into ``out``; their events."""
        n, rays = len(heights), self.bundle.rays
        slots, keys = self._slots(k, n)
        rows, cols = self.bundle.lenses.shape[:2]
        spots = k.launch(self._spots, (rays, n), every[0], i32(first), self._aperture,
                         i32(rays), self._lenses, i32(rows), i32(cols), *self._optics,
                         slots, keys)
        tallest = max(int(heights.max()), 1)
        band = self.rows_per_item or tallest
        return [spots, k.launch("render_rows", (-(-tallest // band), n), slots, keys,
                                i32(rays), *every, i32(first), i32(band), self._f_px,
                                i64(total), out)]

    def _slots(self, k: KernelSet, n: int) -> tuple:
        """The slots and keys of ``n`` particles' rays: the kept buffers, grown as needed
        (the in-order queue runs the previous launch's kernels before these overwrite
        them)."""
        size = n * self.bundle.rays * 4
        if self._scratch is None or self._scratch[1].size < size:
            self._scratch = (k.array(size * SLOT), k.array(size, i32))
        return self._scratch
