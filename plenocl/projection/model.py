"""The projector's weighting model as one device-free object: every table the kernels
read and every geometry check, built from a camera and a grid (docs/design.md §5).

:class:`WeightingModel` assembles the pieces of :mod:`.weighting` in the order the
projector needs them: the grid checked against the optics (the depths the camera resolves,
its field of view: :func:`plenocl.optics.depthrange.check_grid`), the aperture samples, the
lens index map and with it the path (separable, or general with a warning), the per-depth
coefficients and the field-of-view check; the lens tables, the pixel offsets and the
race-free lens colouring follow. Nothing here touches a device: :class:`plenocl.Projector`
takes a model and only uploads its tables and launches kernels, and the model can be built
and tested without OpenCL.
"""

from __future__ import annotations

import warnings
from functools import cached_property

import numpy as np

from ..camera import Camera
from ..camera.lattice import DEFAULT_SHEAR_TOL, RectangularLattice
from ..grid import Grid
from ..optics.depthrange import check_grid
from .lenses import lens_reach
from .weighting import (
    DEFAULT_OVERSAMPLE,
    NO_LENS,
    ApertureGrid,
    check_field_of_view,
    colour_stride,
    depth_coefficients,
    lens_index_map,
    lens_tables,
)

__all__ = ["PATHS", "WeightingModel"]
#: The factorised projector's paths: per-axis separable (the lens index map is
#: axis-aligned, or a hexagonal array's triangular map in its rows' frame) or general (a
#: grid across a rotated array's lens rows).
PATHS = ("separable", "general")


class WeightingModel:
    """The weighting model of ``camera`` for ``grid``: tables and checks, no device.

    Parameters
    ----------
    camera
        The camera; its ``microlens_centers`` (calibrated or ideal) are used per lens.
    grid
        The reconstruction volume (its ``rotation_deg`` is the frame's).
    oversample
        Aperture samples per pixel footprint on the aperture, per axis
        (:meth:`ApertureGrid.for_lattice`).
    shear_tol
        Lens-index drift across the array below which the lens index map drops the
        term (axis-aligned, or triangular for a hexagonal lattice:
        :func:`plenocl.projection.weighting.lens_index_map`).
    warn
        Warn when the general (slower) path is taken.

    Raises
    ------
    ValueError
        When the grid reaches beyond the depths the camera resolves or lies outside its
        field of view (:func:`plenocl.optics.depthrange.check_grid`,
        :func:`check_field_of_view`), or ``oversample`` is not a positive number.

    Attributes
    ----------
    aperture : ApertureGrid
        The aperture samples (step 1).
    lens_map : LensIndexMap
        Array-plane mm to fractional lens index (step 2).
    path : str
        ``"separable"`` or ``"general"`` (:data:`PATHS`).
    coef : numpy.ndarray
        ``(nz, 16)`` per-depth coefficients (:func:`depth_coefficients`).
    """

    def __init__(self, camera: Camera, grid: Grid, oversample: float = DEFAULT_OVERSAMPLE,
                 shear_tol: float = DEFAULT_SHEAR_TOL, warn: bool = True) -> None:
        check_grid(camera, grid)
        self.source_camera = camera
        camera = camera.on_lens_lattice()  # a hexagonal array: its axial view (§5)
        self.camera, self.grid = camera, grid
        self.oversample, self.shear_tol = oversample, shear_tol
        self.lens_map = lens_index_map(camera, shear_tol, grid.rotation_deg)
        self.path = "separable" if self.lens_map.triangular else "general"
        self.aperture = ApertureGrid.for_lattice(camera, oversample, grid.rotation_deg,
                                                 *self.lens_map.aperture_lattice())
        if self.path == "general" and warn:
            warn_general_path(camera, grid)
        self.coef = depth_coefficients(camera, grid, self.lens_map, self.aperture)
        check_field_of_view(camera, grid, self.coef, self.aperture)

    @property
    def n_samples(self) -> int:
        """Aperture samples inside the aperture."""
        return int(self.aperture.inside().sum())

    @cached_property
    def colour_stride(self) -> int:
        """Lens stride of the race-free forward scatter (:func:`colour_stride`)."""
        return colour_stride(self.camera, self.aperture)

    @cached_property
    def pixel_offsets(self) -> np.ndarray:
        """``(n_samples, 2)`` float32 pixel offsets of the samples behind a lens
        (:meth:`ApertureGrid.pixel_offsets`)."""
        return self.aperture.pixel_offsets(self.camera)

    @cached_property
    def lens_reach(self) -> int:
        """Half-width (pixels) of the patch a lens's samples touch
        (:func:`plenocl.projection.lenses.lens_reach`)."""
        return lens_reach(float(np.abs(self.pixel_offsets).max()))

    @cached_property
    def lens_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Rounded ``int2`` and remainder ``float2`` centre of every lens
        (:func:`lens_tables`)."""
        return lens_tables(self.camera)

    @cached_property
    def present(self) -> np.ndarray:
        """Bool per lens (flat, row-major): does it have a calibrated centre?"""
        return self.lens_tables[0][:, 0] != NO_LENS


def warn_general_path(camera: Camera, grid: Grid) -> None:
    """Say that a grid across the array's lens rows takes the general path, why (the
    rows' turn against the grid's axes, and for a rectangular array how far its columns
    are off square to its rows) and what makes it fast: never a silent slow-down
    (docs/results.md, Performance: 12.5x at the paper's size for a 0.15° array)."""
    lattice = RectangularLattice.fit(camera.microlens_centers)
    angle = lattice.rotation_deg
    skew = camera.layout.column_note(lattice)
    warnings.warn(
        f"the microlens rows are turned {angle - grid.rotation_deg:+.4f}° against this "
        f"grid's axes{skew}: the projector takes its general path, up to about 12x slower "
        "than a grid along the lens rows. Grid.for_camera (plenocl grid) gives that "
        f"frame; a grid file does with rotation_deg = {angle:.4f} (velocities are written "
        "in object space either way)", stacklevel=4)
