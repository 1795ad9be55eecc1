"""What the figures draw: a vector field on its grid in physical units
(:class:`VectorData`), read from a field file or a batch's store through
:mod:`plenocl.io`'s readers."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

#: The axes of a field, in the order of its vector components.
AXES = ("x", "y", "z")
#: The components a figure can colour by.
COMPONENTS = ("u", "v", "w", "speed")


@dataclass(frozen=True)
class VectorData:
    """A vector field ready to draw.

    Attributes
    ----------
    x, y, z
        1-D coordinates of the vector grid (mm), each monotonic.
    velocity
        ``(3, nz, ny, nx)`` components along x, y, z in ``unit``; NaN where unknown.
    valid
        ``(nz, ny, nx)``: the vectors to draw (valid and finite).
    unit
        ``"m/s"``, or ``"mm"`` for a displacement field written without ``dt`` (``"voxel"``
        where it holds no voxel size).
    axis_labels
        Label of each axis, x y z (e.g. ``"y streamwise (mm)"``).
    component_labels
        Name of each component, u v w.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    velocity: np.ndarray
    valid: np.ndarray
    unit: str = "m/s"
    axis_labels: tuple[str, str, str] = ("x (mm)", "y (mm)", "z (mm)")
    component_labels: tuple[str, str, str] = ("u", "v", "w")
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        shape = (len(self.z), len(self.y), len(self.x))
        if self.velocity.shape != (3, *shape) or self.valid.shape != shape:
            raise ValueError(f"velocity {self.velocity.shape} and valid {self.valid.shape} do "
                             f"not match the grid's {shape} (z, y, x) vectors")

    @property
    def shape(self) -> tuple[int, int, int]:
        """Vector-grid shape ``(nz, ny, nx)``."""
        return self.valid.shape

    def coordinate(self, axis: str) -> np.ndarray:
        """The 1-D coordinates (mm) along ``axis`` (``"x"``, ``"y"`` or ``"z"``)."""
        return {"x": self.x, "y": self.y, "z": self.z}[check_axis(axis)]

    def label(self, name: str) -> str:
        """Label of an axis (``"x"``...) or a component (``"u"``... ``"speed"``) with units."""
        if name in AXES:
            return self.axis_labels[AXES.index(name)]
        comp = "speed |V|" if name == "speed" else self.component_labels[COMPONENTS.index(name)]
        return f"{comp} ({self.unit})"

    def component(self, name: str) -> np.ndarray:
        """``(nz, ny, nx)`` values of a component (or the speed), NaN where not valid."""
        name = check_component(name)
        vel = np.where(self.valid, self.velocity, np.nan)
        if name == "speed":
            return np.sqrt(np.sum(vel**2, axis=0))
        return vel[COMPONENTS.index(name)]

    def with_velocity(self, velocity: np.ndarray, valid: np.ndarray | None = None) -> VectorData:
        """The same grid and labels with other vectors (e.g. fluctuations, the truth)."""
        return replace(self, velocity=np.asarray(velocity, float),
                       valid=self.valid if valid is None else valid)


def check_axis(axis: str) -> str:
    """``axis`` if it is one of x, y, z, else a ``ValueError`` naming them."""
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    return axis


def check_component(name: str) -> str:
    """``name`` if it is one of u, v, w, speed, else a ``ValueError`` naming them."""
    if name not in COMPONENTS:
        raise ValueError(f"component must be one of {COMPONENTS}, got {name!r}")
    return name


def read_vector_field(path: str | Path) -> VectorData:
    """A field written by :func:`plenocl.vectorfield.save_field` (``.npz``): velocities in
    m/s where it was written with ``dt``, else displacements in mm (voxels times their
    size along each axis: on voxels of unequal sizes, arrows in voxels on axes in mm
    point the wrong way)."""
    from ..vectorfield import read_npz

    res, arrays = read_npz(path)
    missing = [f"{a}_mm" for a in AXES if f"{a}_mm" not in arrays]
    if missing:
        raise ValueError(f"{path} holds no vector positions ({', '.join(missing)}): a field "
                         "plenocl.vectorfield.save_field writes has them; save the field "
                         "with its grid (save_field(path, result, grid=...))")
    coords = [np.asarray(arrays[f"{a}_mm"], float) for a in AXES]
    rotation = float(arrays.get("rotation_deg", 0.0))
    if "velocity" in arrays:
        vel, unit = grid_frame(np.asarray(arrays["velocity"], float), rotation), "m/s"
    else:
        size = np.asarray(arrays.get("voxel_size_mm_xyz", (1.0, 1.0, 1.0)), float)
        vel = np.stack([res.u, res.v, res.w]).astype(float) * size.reshape(3, 1, 1, 1)
        unit = "mm" if "voxel_size_mm_xyz" in arrays else "voxel"
    valid = np.asarray(res.valid, bool) & np.all(np.isfinite(vel), axis=0)
    try:
        return VectorData(*coords, velocity=vel, valid=valid, unit=unit,
                          **turned_labels(rotation))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def turned_labels(rotation_deg: float) -> dict:
    """The axis and component labels of a grid turned by ``rotation_deg`` about the
    optical axis (its vectors drawn on its own axes; none for an unturned grid)."""
    if not rotation_deg:
        return {}
    turn = f"grid turned {rotation_deg:g}°"
    return {"axis_labels": (f"x along the grid (mm; {turn})", "y along the grid (mm)",
                            "z (mm)"),
            "component_labels": ("u along the grid's x", "v along the grid's y", "w")}


def grid_frame(velocity: np.ndarray, rotation_deg: float) -> np.ndarray:
    """Object-space velocity ``(3, ...)`` (a stored field's) turned onto the axes of a
    grid turned by ``rotation_deg``, the axes its coordinates are on: what a figure draws
    and differentiates against them (``Rᵀ v``; as it is on an unrotated grid)."""
    from ..vectorfield import to_object_space

    return to_object_space(velocity, -rotation_deg) if rotation_deg else velocity


def store_field(arrays: dict[str, np.ndarray], prefix: str = "mean",
                rotation_deg: float = 0.0) -> VectorData:
    """A batch store's ensemble field (``u_mean``... or ``u_ensemble``... by ``prefix``),
    valid where it has a value, on its grid's axes (the store's ``rotation_deg``)."""
    vel = grid_frame(np.stack([np.asarray(arrays[f"{c}_{prefix}"], float) for c in "uvw"]),
                     rotation_deg)
    valid = np.all(np.isfinite(vel), axis=0)
    return VectorData(*(np.asarray(arrays[a], float) for a in AXES), velocity=vel,
                      valid=valid, unit="m/s", **turned_labels(rotation_deg))
