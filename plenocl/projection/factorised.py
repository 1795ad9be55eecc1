"""The factorised projector's execution path (docs/design.md §5): the kernel launches of
its four stages, for a chunk of aperture columns ``[i0, i1)``: ``volume_to_light`` (``S``)
and ``light_to_image`` (``P``) make the forward projection, ``image_to_light`` (``Pᵀ``) and
``light_to_volume`` (``Sᵀ``) the back projection, and the direct kernels.

:class:`FactorisedStages` is the part of :class:`plenocl.Projector` that launches them;
the projector holds what they read: the weighting model's tables on the device, the
plan (slabs, depth and aperture-column chunks), the kernels and their tuning (vector
width, segments, gather or scatter forms), set up in ``projector.py``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyopencl.array as cl_array

from ..opencl.arrays import fill
from .extent import PlaneExtent
from .lenses import LensSet
from .plan import depth_chunks

i32, f32 = np.int32, np.float32
#: Work-items per group that the element kernels' first dimension is rounded up to.
_ROUND = 16


def _rounded(n: int) -> int:
    """``n`` rounded up to a multiple of :data:`_ROUND` (the kernels skip the extra items)."""
    return -(-n // _ROUND) * _ROUND


class FactorisedStages:
    """The factorised path's kernel launches (module docstring), mixed into
    :class:`plenocl.Projector`, whose attributes they read (``_k``, ``_kernels``, ``_d``,
    ``plan``, ``path``, ``nkxp``, ``seg``, ``nseg``, ``gather_forward``, ``back_mode``,
    ...).
    The light field they return or take is the projector's scratch buffer
    ``L[ky][s - s0][kx]``, reused by the next call."""

    def _lens_args(self) -> tuple:
        """``nkx, nky, nkxp`` as kernel scalars."""
        cols, rows = self.camera.ml_count
        return i32(cols), i32(rows), i32(self.nkxp)

    def _pixel_args(self) -> tuple:
        """Sensor width and height as kernel scalars."""
        width, height = self.camera.pixels
        return i32(width), i32(height)

    @property
    def _ic(self) -> np.float32:
        return f32(self.aperture.center)

    def volume_to_light(self, slabs: Sequence[cl_array.Array], i0: int, i1: int,
                        active: np.ndarray | None = None, lenses: LensSet | None = None,
                        extent: PlaneExtent | None = None) -> cl_array.Array:
        """``L = S vol`` for the samples of aperture columns ``[i0, i1)`` (a chunk of
        :attr:`plan` ``.columns``), the active slices only (at least one), the volume 0
        beyond ``extent`` (the separable path reads only inside it)."""
        active, lenses = self._active(active), self._lenses(lenses)
        extent = self.whole_extent if extent is None else extent
        s0, s1 = self._columns.sample_range(i0, i1)
        nkx, nky, nkxp = self._lens_args()
        light = self._buffer("L", (s1 - s0) * int(nky) * self.nkxp)
        first = True
        for (z0, z1), slab in zip(self.plan.slabs, slabs, strict=True):
            for zc, nzc in depth_chunks(z0, z1, active, self.plan.zchunk):
                zargs = (i32(z0), i32(zc), i32(nzc))
                if self.path == "general":
                    name, size = (("fwd_gen_gather", (int(nkx), int(nky), s1 - s0))
                                  if self.gather_forward else ("fwd_gen", (s1 - s0,)))
                    self._k.launch(name, size, slab, light, self._d["coef"], self._d["ij"],
                                   *self._grid_args(), nkx, nky, nkxp, *zargs, i32(s0),
                                   i32(s1 - s0), self._ic, i32(not first))
                else:
                    self._separable_forward(slab, light, zargs, (i0, i1, s0, s1), first,
                                            lenses, extent)
                first = False
        return light

    def _grid_args(self) -> tuple:
        _, ny, nx = self.shape
        return i32(nx), i32(ny)

    def _separable_forward(self, slab, light, zargs, chunk: tuple[int, int, int, int],
                           first: bool, lenses: LensSet, extent: PlaneExtent) -> None:
        """``fwd_x`` then ``fwd_y`` for one depth chunk and the aperture columns and
        samples ``chunk`` = ``(i0, i1, s0, s1)``: voxel rows onto lens columns, then onto
        lens rows."""
        z0, zc, nzc = zargs
        i0, i1, s0, s1 = chunk
        bounds = self._span_args(extent)
        nkx, nky, nkxp = self._lens_args()
        (nx, ny), nic = self._grid_args(), i1 - i0
        t_buf = self._buffer("T", int(nzc) * nic * int(ny) * self.nkxp)
        xargs = (slab, t_buf, self._d["coef"], nx, ny, nkx, nkxp, z0, zc, i32(i0), i32(nic),
                 self._ic, extent.device_columns, *bounds)
        k = self._kernels(extent)
        if self.gather_forward:
            k.launch("fwd_x", (_rounded(self.nkxp), int(ny), int(nzc) * nic), *xargs)
        else:
            k.launch("fwd_x_row", (int(ny), int(nzc)), *xargs)
        k.launch("fwd_y", (self.nseg, int(nky), nic), t_buf, light, self._d["coef"],
                       self._d["col_lo"], self._d["col_hi"], self._d["col_off"], lenses.rows,
                       ny, nkxp, i32(self.seg), zc, nzc, i32(i0), i32(nic),
                       i32(s0), i32(s1 - s0), self._ic, i32(not first), *bounds)

    def light_to_image(self, light: cl_array.Array, out: cl_array.Array, i0: int, i1: int,
                       lenses: LensSet | None = None) -> None:
        """``image += P L`` for the listed lenses, one race-free colour class at a time."""
        lenses = self._lenses(lenses)
        s0, s1 = self._columns.sample_range(i0, i1)
        nkx, _, nkxp = self._lens_args()
        for a, b in zip(lenses.offsets[:-1], lenses.offsets[1:], strict=True):
            if b > a:
                self._k.launch("fwd_pix", (b - a,), light, out, lenses.ids, i32(a),
                               self._d["rnd"], self._d["frac"], self._d["px"],
                               *self._pixel_args(), nkx, nkxp, i32(s0), i32(s1 - s0),
                               self._scale)

    def image_to_light(self, image: cl_array.Array, i0: int, i1: int,
                       lenses: LensSet | None = None) -> cl_array.Array:
        """``L = Pᵀ image`` for the samples of aperture columns ``[i0, i1)`` (0 at the
        unlisted lenses)."""
        lenses = self._lenses(lenses)
        s0, s1 = self._columns.sample_range(i0, i1)
        nkx, nky, nkxp = self._lens_args()
        n = (s1 - s0) * int(nky) * self.nkxp
        light = self._buffer("L", n)
        fill(light[:n], 0.0)
        if lenses.count:
            sps = (s1 - s0) if self._k.is_cpu else 1  # samples per work-item
            self._k.launch("back_pix", (lenses.count, -(-(s1 - s0) // sps)), image, light,
                           lenses.ids, self._d["rnd"], self._d["frac"], self._d["px"],
                           *self._pixel_args(), nkx, nkxp, i32(s0), i32(s1 - s0), i32(sps),
                           self._scale)
        return light

    def light_to_volume(self, light: cl_array.Array, slab: cl_array.Array, z0: int, z1: int,
                        i0: int, i1: int, accumulate: bool, active: np.ndarray | None = None,
                        lenses: LensSet | None = None,
                        support: cl_array.Array | None = None,
                        extent: PlaneExtent | None = None) -> None:
        """``slab (+)= Sᵀ L`` for the slab ``[z0, z1)`` and aperture columns ``[i0, i1)``,
        active slices only; with ``support`` (a slab like ``slab``), the separable path
        leaves out its zero voxels (0 there, or unchanged when accumulating), and those
        beyond ``extent`` too."""
        active, lenses = self._active(active), self._lenses(lenses)
        extent = self.whole_extent if extent is None else extent
        s0, s1 = self._columns.sample_range(i0, i1)
        nkx, nky, nkxp = self._lens_args()
        acc = i32(accumulate)
        for zc, nzc in depth_chunks(z0, z1, active, self.plan.zchunk):
            zargs = (i32(z0), i32(zc), i32(nzc))
            if self.path == "general":
                self._k.launch("back_gen", (int(self.shape[1]), nzc), light, slab,
                               self._d["coef"], self._d["ij"], *self._grid_args(), nkx, nky,
                               nkxp, zargs[0], zargs[1], i32(s0), i32(s1 - s0), self._ic, acc)
                continue
            t_buf = self._light_to_rows(light, zargs, (i0, i1, s0, s1), lenses, extent)
            (nx, ny), nic = self._grid_args(), i1 - i0
            sup = (i32(0), slab) if support is None else (i32(1), support)
            xargs = (t_buf, slab, self._d["coef"], sup[1], sup[0], nx, ny, nkx, nkxp,
                     *zargs[:2], i32(i0), i32(nic), self._ic, acc, extent.device_columns)
            k = self._kernels(extent)
            if self.gather_forward:
                k.launch("back_x", (_rounded(int(nx)), int(ny), nzc), *xargs)
            else:
                k.launch("back_x_row", (int(ny), nzc), *xargs)

    def _light_to_rows(self, light, zargs, chunk: tuple[int, int, int, int],
                       lenses: LensSet, extent: PlaneExtent) -> cl_array.Array:
        """The separable back projection's lens-row stage for one depth chunk and the
        aperture columns and samples ``chunk`` = ``(i0, i1, s0, s1)``: the intermediate
        ``T[(iz, i)][iy][kx]``, by gather (``back_y``, the extent's spans only; 0 beyond
        them) or atomic scatter (``back_y_scatter``, every row)."""
        _, zc, nzc = zargs
        i0, i1, s0, s1 = chunk
        _, nky, nkxp = self._lens_args()
        ny, nic = self._grid_args()[1], i1 - i0
        t_buf = self._buffer("T", int(nzc) * nic * int(ny) * self.nkxp)
        if self.back_mode == "atomic":
            fill(t_buf[:int(nzc) * nic * int(ny) * self.nkxp], 0.0)
            self._k.launch("back_y_scatter", (self.nseg, int(nky), s1 - s0), light, t_buf,
                           self._d["coef"], self._d["ij"], ny, nkxp, i32(self.seg), zc, nzc,
                           i32(i0), i32(nic), i32(s0), self._ic)
        else:
            columns = 1 if self.back_allcols else nic  # work-items across the columns
            self._kernels(extent).launch("back_y", (self.nseg, int(ny), columns), light, t_buf,
                           self._d["coef"],
                           self._d["col_lo"], self._d["col_hi"], self._d["col_off"],
                           lenses.rows, ny, nky, nkxp, i32(self.seg), zc, nzc, i32(i0), i32(nic),
                           i32(s0), i32(s1 - s0), self._ic, *self._span_args(extent))
        return t_buf

    @staticmethod
    def _span_args(extent: PlaneExtent) -> tuple:
        """The kernels' ``span, ncols`` of ``extent`` (read only by the kernels built with
        ``PL_EXTENT``, :meth:`_kernels`)."""
        return extent.device_spans, i32(extent.n_columns)

    def _direct(self, name: str, src: cl_array.Array, dst: cl_array.Array, z0: int) -> None:
        nkx, nky, _ = self._lens_args()
        depth = (src if name == "fwd_direct" else dst).shape[0]
        self._k.launch(name, (self.shape[2], self.shape[1], depth), src, dst, self._d["coef"],
                       self._d["ij"], self._d["px"], self._d["rnd"], self._d["frac"],
                       *self._grid_args(), nkx, nky, *self._pixel_args(), i32(z0),
                       i32(self.n_samples), self._ic, self._scale)
