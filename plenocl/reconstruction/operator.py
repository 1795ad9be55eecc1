"""What a reconstruction needs of a projector: the operator contract.

:class:`ProjectionOperator` states it as a :class:`typing.Protocol`. :class:`plenocl.Projector`
implements it matrix-free on the device; the solver tests implement it with an explicit
weight matrix. The solver depends on this contract only, never on a concrete projector.

Volumes on the device are lists of depth slabs (``pyopencl.array.Array``, float32,
C-contiguous, ``(z1 - z0, ny, nx)`` each); images are one device array ``(H, W)``.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..camera import Camera
from ..grid import Grid

Slabs = list[cl_array.Array]


@runtime_checkable
class ProjectionOperator(Protocol):
    """A linear map ``A`` from voxels to pixels with its exact transpose, on one queue.

    Attributes
    ----------
    queue, camera, grid
        Where it runs and what it maps between.

    Notes
    -----
    ``lenses`` arguments take what :meth:`lens_set` returns (``None``: every lens); an
    operator may ignore them when it always projects onto every lens, since skipping a
    dark lens is exact. ``active`` (bool per depth slice, ``None``: all) marks the slices
    that can be non-zero; the others may be skipped and come out 0 in a back projection.

    A supersampled reconstruction (``supersample > 1``, the default) needs more:
    :class:`RefinableOperator`. An operator without ``refined`` reconstructs with
    ``supersample=1`` (given explicitly) and is refused otherwise.
    """

    queue: cl.CommandQueue
    camera: Camera
    grid: Grid

    def forward_device(self, vol: Slabs, out: cl_array.Array | None = None,
                       active: np.ndarray | None = None, lenses: Any = None
                       ) -> cl_array.Array:
        """``A vol`` into ``out`` (a new image when ``None``)."""

    def back_device(self, image: cl_array.Array, out: Slabs | None = None,
                    active: np.ndarray | None = None, lenses: Any = None,
                    support: Slabs | None = None) -> Slabs:
        """``Aᵀ image`` into ``out`` (new slabs when ``None``); where ``support`` (slabs of
        the grid) is zero the result may be left out as 0: a multiplicative update keeps a
        zero voxel at zero, so only the support's voxels need their back projection (an
        operator may compute them all)."""

    def empty_volume(self) -> Slabs:
        """Uninitialised device slabs of the grid."""

    def volume_to_device(self, vol: np.ndarray) -> Slabs:
        """A checked float32 device copy of a host volume."""

    def volume_to_host(self, slabs: Slabs) -> np.ndarray:
        """The host volume of device slabs."""

    def sensitivity(self) -> Slabs:
        """``Aᵀ 1``, computed once and kept; callers must not write to it."""

    def lit_lenses(self, image: np.ndarray, threshold: float = 0.0) -> np.ndarray:
        """Bool per microlens: could it see a pixel of ``image`` above ``threshold``?
        An operator with a ``queue`` takes the image as a float32 device array on it too
        (:func:`plenocl.reconstruction.images.prepare_image` passes the solver's copy)."""

    def lens_set(self, lit: np.ndarray) -> Any:
        """The lenses flagged in ``lit``, in the form ``lenses`` arguments take."""

    def cropped(self, box: tuple[slice, slice, slice]) -> ProjectionOperator:
        """The same operator restricted to the sub-grid ``vol[box]`` (keeps a computed
        sensitivity, cropped)."""


@runtime_checkable
class RefinableOperator(ProjectionOperator, Protocol):
    """A :class:`ProjectionOperator` that can also refine its grid: what
    :func:`plenocl.reconstruction.reconstruct` uses with ``supersample > 1``
    (:class:`plenocl.Projector` is one)."""

    def refined(self, factor: int) -> ProjectionOperator:
        """The same operator on the grid with ``factor x factor`` lateral sub-voxels per
        voxel (:meth:`plenocl.Grid.refined`; ``factor`` 1: itself), kept per factor. Same
        camera: its :meth:`lit_lenses` are this operator's, which a supersampled
        reconstruction computes once, on this one."""


@runtime_checkable
class FramedOperator(ProjectionOperator, Protocol):
    """A :class:`ProjectionOperator` that may project its grid through another frame's
    operator (:class:`plenocl.Projector` on a grid across a rotated array's lens rows,
    docs/design.md §5.1): a supersampled reconstruction then iterates on ``frame``'s grid
    and resamples once (``None``: no frame, the operator's own grid). Its
    ``back_device`` takes ``reuse_forward=True`` when ``support`` is the volume of its
    last forward projection, unchanged since: the frame's support is then that
    projection's resampled volume (the same zero voxels), not resampled again."""

    frame: ProjectionOperator | None


@runtime_checkable
class PlannedOperator(ProjectionOperator, Protocol):
    """A :class:`ProjectionOperator` that keeps a volume in device slabs by a plan
    (:class:`plenocl.projection.plan.Plan`: ``plan.slabs``, their depth ranges): two
    with the same slabs share volumes."""

    plan: Any

    def volume_box(self, vol: Slabs, box: tuple[slice, slice, slice],
                   into: ProjectionOperator) -> Slabs:
        """``vol[box]`` of this operator's device volume as ``into``'s device volume
        (``into``: this operator :meth:`cropped` to ``box``), copied on the device."""


class SampledOperator(ProjectionOperator, Protocol):
    """A :class:`ProjectionOperator` that can also resample the main-lens aperture: the
    coarse iterations of a coarse-to-fine reconstruction and its first sub-voxel ones run
    on coarser samplings (``coarse_oversample``, ``early_oversample``; docs/design.md
    §6.5; :class:`plenocl.Projector` is one). An operator without it runs them on
    itself."""

    oversample: float

    def sampled(self, oversample: float) -> ProjectionOperator:
        """The same operator with ``oversample`` aperture samples per pixel footprint,
        kept per value (itself at its own value)."""


class WeightedOperator(ProjectionOperator, Protocol):
    """A :class:`ProjectionOperator` that can also change how an aperture sample's light
    is shared between lenses (``lens_weights``: the paper's bilinear weights, or the
    voxel's extent; :class:`plenocl.Projector` is one): a reconstruction whose settings
    name the lens weights runs on :meth:`weighted`."""

    lens_weights: str

    def weighted(self, lens_weights: str) -> ProjectionOperator:
        """The same operator with ``lens_weights``, kept per value (itself at its own)."""
