"""The model of a PIV result: a 3-D displacement field on the window-centre grid
(:class:`PIVResult`, what :func:`plenocl.piv3d` returns), its derived flow quantities
(velocity, gradient, vorticity, Q-criterion) and the arrays and metadata a file of it
holds (:meth:`PIVResult.arrays`, :meth:`PIVResult.metadata`), including the turn of
vectors on a rotated grid into object space; and the field as a file, written with its
geometry (:func:`save_field`: ``.vti`` for ParaView, ``.npz``, ``.h5``, Tecplot ``.dat``,
``.csv``) and read back (:func:`read_npz`: ``.npz``, ``.h5``). :mod:`plenocl.io.fieldformat`
writes and reads those arrays (and lists them); it knows no PIV algorithm and no
vector-field type.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera.lattice import rotation_matrix
from .io.fieldformat import AXES, FORMAT_VERSION, check_field_path, read_field, write_field
from .options import is_number

__all__ = ["AXES", "FLAGS", "FORMAT_VERSION", "NOTES", "PIVResult", "Size3",
           "displacement_to_velocity", "field_units", "q_criterion", "to_object_space",
           "uncertainty", "velocity_gradient", "vorticity", "voxel_size"]

Size3 = tuple[int, int, int]

#: The boolean flags stored with every field.
FLAGS = ("valid", "outlier", "masked")

#: What a reader of the arrays should know (also in every file's metadata).
NOTES = {"peak_ratio": "primary over secondary correlation peak of the final pass; NaN "
                       "where that pass correlated directly at the lags around zero (the "
                       "default deformed passes), where no second peak is searched; "
                       "piv3d(min_peak_ratio=...) correlates the final pass by FFT"}

@dataclass
class PIVResult:
    """A 3-D displacement field on the window-centre grid.

    Attributes
    ----------
    x, y, z
        1-D window-centre coordinates in voxel-index units.
    u, v, w
        Displacement (voxels) along x, y, z, shaped ``(nz', ny', nx')``; outliers are
        replaced, masked vectors are NaN.
    valid
        ``True`` where the vector came from its own correlation and passed validation.
    peak_ratio
        Primary over secondary correlation peak of the final pass, where that pass
        correlated by FFT; NaN where it correlated directly at the lags around zero
        (``correlation="auto"``, the default, unless ``min_peak_ratio`` is given).
    outlier
        Flagged by the final normalised median test (then replaced).
    masked
        Window excluded by the mask (more than half of it masked).
    window
        Final window size ``(wz, wy, wx)``.
    passes
        Per-pass diagnostics (window, step, vector count, how it correlated and the
        windows it correlated by FFT, outliers, seconds).
    sigma_u, sigma_v, sigma_w
        Standard uncertainty (voxels) of each valid vector's components, from the
        statistics of the final pass's correlation on the deformed volumes
        (:func:`plenocl.piv.direct.correlation_uncertainty`); NaN for invalid, replaced
        or masked vectors and after a single (undeformed) pass. ``None`` in results
        read from files written before it existed.
    refinement
        What refined the field after the correlation (``{}``: nothing): for the particle
        refinement (:func:`plenocl.piv.refinement.refine_with_particles`) the particle
        pairs found, the vectors refined and their median pair count.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    peak_ratio: np.ndarray
    outlier: np.ndarray
    masked: np.ndarray
    window: Size3
    passes: list[dict] = field(default_factory=list)
    sigma_u: np.ndarray | None = None
    sigma_v: np.ndarray | None = None
    sigma_w: np.ndarray | None = None
    refinement: dict = field(default_factory=dict)

    @property
    def shape(self) -> Size3:
        """Vector-grid shape ``(nz', ny', nx')``."""
        return self.u.shape

    @property
    def step(self) -> Size3:
        """Window-centre spacing ``(z, y, x)`` voxels (the window along an axis with a
        single vector)."""
        return tuple(int(round(c[1] - c[0])) if len(c) > 1 else int(w)
                     for c, w in zip((self.z, self.y, self.x), self.window))

    def velocity(self, voxel_size_mm, dt: float):
        """Velocity ``(U, V, W)`` in m/s for a voxel size (mm, scalar or ``(dz, dy, dx)``)."""
        return displacement_to_velocity((self.u, self.v, self.w), voxel_size_mm, dt)

    def velocity_uncertainty(self, voxel_size_mm, dt: float):
        """Standard uncertainty of ``(U, V, W)`` in m/s (NaN where unknown)."""
        sigmas = [np.full(self.shape, np.nan) if s is None else s
                  for s in (self.sigma_u, self.sigma_v, self.sigma_w)]
        return displacement_to_velocity(sigmas, voxel_size_mm, dt)

    def positions_mm(self, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0)):
        """Window centres ``(x, y, z)`` in mm; ``origin_mm = (z0, y0, x0)``: voxel 0 centre."""
        dz, dy, dx = voxel_size(voxel_size_mm)
        z0, y0, x0 = (float(o) for o in origin_mm)
        return x0 + dx * self.x, y0 + dy * self.y, z0 + dz * self.z

    def gradient(self, voxel_size_mm=1.0, dt: float | None = None) -> np.ndarray:
        """Velocity-gradient tensor ``(3, 3, nz', ny', nx')``, see :func:`velocity_gradient`."""
        size = voxel_size(voxel_size_mm)
        if dt is None:  # displacement gradient (mm per mm, i.e. per dt)
            comps = [c * s for c, s in zip((self.u, self.v, self.w), size[::-1])]
        else:           # m/s over m
            comps = list(self.velocity(size, dt))
        scale = 1.0 if dt is None else 1e-3
        x, y, z = self.positions_mm(size)
        return velocity_gradient(*comps, x * scale, y * scale, z * scale)

    def vorticity(self, voxel_size_mm=1.0, dt: float | None = None):
        """Vorticity ``(wx, wy, wz)``: 1/s with ``dt``, else per ``dt`` (dimensionless).

        Derivatives are ``np.gradient`` on the physical vector grid (one-sided at the
        faces); next to masked (NaN) vectors the result is NaN.
        """
        return vorticity(self.gradient(voxel_size_mm, dt))

    def q_criterion(self, voxel_size_mm=1.0, dt: float | None = None) -> np.ndarray:
        """Q-criterion: 1/s^2 with ``dt``, else per ``dt^2``."""
        return q_criterion(self.gradient(voxel_size_mm, dt))

    def arrays(self, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0), dt: float | None = None,
               rotation_deg: float = 0.0) -> dict[str, np.ndarray]:
        """Every array a field file stores, keyed by name (see :mod:`plenocl.io.fieldformat`).

        Parameters
        ----------
        voxel_size_mm
            Scalar or ``(dz, dy, dx)`` in mm.
        origin_mm
            ``(z0, y0, x0)``: the centre of voxel ``(0, 0, 0)`` in mm.
        dt
            Time between the volumes (s); adds ``velocity`` and physical units.
        rotation_deg
            The grid's rotation about the optical axis: ``velocity`` and ``vorticity``
            are given in object space (turned by it).
        """
        size = voxel_size(voxel_size_mm)
        out = self._coordinate_arrays(size, origin_mm)
        out["displacement"] = np.stack([self.u, self.v, self.w])
        out["peak_ratio"] = self.peak_ratio
        out.update({name: np.asarray(getattr(self, name), bool) for name in FLAGS})
        out["displacement_uncertainty"] = uncertainty(self)
        if dt is not None:
            out["velocity"] = to_object_space(self.velocity(size, dt), rotation_deg)
            out["velocity_uncertainty"] = _spread_to_object_space(
                self.velocity_uncertainty(size, dt), rotation_deg)
            out["dt"] = np.asarray(float(dt))
        out["vorticity"] = to_object_space(self.vorticity(size, dt), rotation_deg)
        out["q_criterion"] = self.q_criterion(size, dt)
        out["rotation_deg"] = np.asarray(float(rotation_deg))
        return out

    def _coordinate_arrays(self, size, origin_mm) -> dict[str, np.ndarray]:
        """Window centres (voxel and mm), the voxel and vector grids' geometry, window."""
        x_mm, y_mm, z_mm = self.positions_mm(size, origin_mm)
        out = {"format_version": np.asarray(FORMAT_VERSION), "x": self.x, "y": self.y,
               "z": self.z, "x_mm": x_mm, "y_mm": y_mm, "z_mm": z_mm,
               "voxel_size_mm_xyz": np.asarray(size[::-1]),
               "origin_mm_xyz": np.asarray(origin_mm, float)[::-1].copy(),
               "window_xyz": np.asarray(self.window[::-1])}
        out["vector_origin_mm_xyz"] = np.array([float(c[0]) for c in (x_mm, y_mm, z_mm)])
        # a single vector along an axis gets the voxel size as its spacing
        out["vector_spacing_mm_xyz"] = np.array(
            [float(np.diff(c[:2])[0]) if len(c) > 1 else v
             for c, v in zip((x_mm, y_mm, z_mm), size[::-1])])
        return out

    @staticmethod
    def metadata(dt: float | None = None) -> dict:
        """What a reader of :meth:`arrays` should know: units (velocities in m/s with
        ``dt``, else per ``dt``), axis order and notes; JSON-ready."""
        return {"units": field_units(dt is not None), "axes": AXES, "notes": NOTES}

    @classmethod
    def from_arrays(cls, arrays, source: str = "arrays") -> PIVResult:
        """The field held by :meth:`arrays`' output (per-pass diagnostics are not stored);
        ``source`` names it in the error for arrays that are no vector field."""
        missing = {"x", "y", "z", "displacement", "peak_ratio", *FLAGS} - set(arrays)
        if missing:
            raise ValueError(f"{source} is not a plenocl vector field: missing "
                             f"{sorted(missing)}")
        u, v, w = arrays["displacement"]
        sigma = arrays.get("displacement_uncertainty", (None, None, None))
        return cls(x=arrays["x"], y=arrays["y"], z=arrays["z"], u=u, v=v, w=w,
                   valid=arrays["valid"], peak_ratio=arrays["peak_ratio"],
                   outlier=arrays["outlier"], masked=arrays["masked"],
                   window=_window(arrays),
                   sigma_u=sigma[0], sigma_v=sigma[1], sigma_w=sigma[2])


def _window(arrays) -> Size3:
    """The final window ``(wz, wy, wx)`` of a field's arrays (``window_xyz``; ``window``,
    already (z, y, x), in arrays of the first layout; ``(0, 0, 0)`` where none is stored)."""
    if "window_xyz" in arrays:
        return tuple(int(s) for s in np.asarray(arrays["window_xyz"])[::-1])
    return tuple(int(s) for s in arrays.get("window", (0, 0, 0)))


def _triple(value) -> np.ndarray:
    """``value`` (a scalar or three numbers) as three floats; NaN where it is neither (two
    values, or text), for the caller to refuse by name."""
    try:
        return np.broadcast_to(np.asarray(value, float), (3,))
    except (ValueError, TypeError):
        return np.full(3, np.nan)


def voxel_size(voxel_size_mm) -> tuple[float, float, float]:
    """A voxel size as ``(dz, dy, dx)`` mm from a scalar or a triple, checked positive."""
    size = _triple(voxel_size_mm)
    if not np.all(np.isfinite(size) & (size > 0)):
        raise ValueError(f"voxel_size_mm must be positive, a scalar or (dz, dy, dx) in mm, "
                         f"got {voxel_size_mm!r}")
    return tuple(float(s) for s in size)


def displacement_to_velocity(displacement, voxel_size_mm, dt: float):
    """Convert ``(u, v, w)`` in voxels to m/s: ``d * voxel_size_mm * 1e-3 / dt``.

    Parameters
    ----------
    displacement
        Sequence ``(u, v, w)`` of arrays in voxels along x, y, z.
    voxel_size_mm
        Scalar or ``(dz, dy, dx)`` in mm (array order, as :class:`plenocl.Grid.spacing`).
    dt
        Time between the two volumes (s).
    """
    if not _positive_number(dt):
        raise ValueError(f"dt must be a positive time in seconds (a number, e.g. 175e-6), "
                         f"got {dt!r}")
    if dt > 1.0:
        warnings.warn(f"dt = {dt:g} s between the exposures is unusually long for PIV "
                      "(microseconds to milliseconds): dt is in seconds, e.g. 175 µs is "
                      "175e-6", stacklevel=3)
    dz, dy, dx = voxel_size(voxel_size_mm)
    return tuple(np.asarray(c) * s * 1e-3 / dt for c, s in zip(displacement, (dx, dy, dz)))


def _positive_number(value) -> bool:
    """A positive finite number (NumPy's 0-d arrays too; not text, not a bool)."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    return is_number(value) and bool(np.isfinite(value)) and value > 0


def velocity_gradient(u, v, w, x, y, z) -> np.ndarray:
    """``grad[i, j] = d u_i / d x_j`` (``i, j`` over x, y, z) by ``np.gradient``.

    ``u, v, w`` are shaped ``(nz, ny, nx)``; ``x, y, z`` are the 1-D physical coordinates.
    Axes with a single node contribute zero derivatives.
    """
    grad = np.zeros((3, 3, *np.shape(u)))
    coords = (np.asarray(z, float), np.asarray(y, float), np.asarray(x, float))
    for i, comp in enumerate((u, v, w)):
        for axis, coord in enumerate(coords):
            if len(coord) > 1:
                grad[i, 2 - axis] = np.gradient(np.asarray(comp, float), coord, axis=axis)
    return grad


def vorticity(grad: np.ndarray):
    """Vorticity ``(wx, wy, wz)`` from a velocity-gradient tensor."""
    return grad[2, 1] - grad[1, 2], grad[0, 2] - grad[2, 0], grad[1, 0] - grad[0, 1]


def q_criterion(grad: np.ndarray) -> np.ndarray:
    """``Q = (|Omega|^2 - |S|^2) / 2 = -(1/2) sum_ij A_ij A_ji`` (Hunt, Wray & Moin 1988)."""
    return -0.5 * np.einsum("ij...,ji...->...", grad, grad)


def field_units(with_dt: bool) -> dict[str, str]:
    """Units of each stored array (``with_dt``: velocities in m/s, else per ``dt``)."""
    units = {"x": "voxel", "y": "voxel", "z": "voxel", "x_mm": "mm", "y_mm": "mm",
             "z_mm": "mm", "displacement": "voxel", "peak_ratio": "1",
             "displacement_uncertainty": "voxel",
             "voxel_size_mm_xyz": "mm", "origin_mm_xyz": "mm", "vector_origin_mm_xyz": "mm",
             "vector_spacing_mm_xyz": "mm", "rotation_deg": "degree", "window_xyz": "voxel",
             "format_version": "1"}
    if with_dt:
        units.update(velocity="m s-1", velocity_uncertainty="m s-1", vorticity="s-1",
                     q_criterion="s-2", dt="s")
    else:
        units.update(vorticity="1 (per dt)", q_criterion="1 (per dt^2)")
    return units


def uncertainty(result: PIVResult) -> np.ndarray:
    """``(3, ...)`` standard uncertainty of ``(u, v, w)`` in voxels; all NaN for a result
    without one (read from an older file)."""
    if result.sigma_u is None:
        return np.full((3, *result.shape), np.nan)
    return np.stack([result.sigma_u, result.sigma_v, result.sigma_w])


def _spread_to_object_space(sigmas, rotation_deg: float) -> np.ndarray:
    """Standard uncertainties along a turned grid's axes as object-space ones (the
    components' errors taken as independent)."""
    sx, sy, sz = (np.asarray(c, np.float64) for c in sigmas)
    if rotation_deg:
        r = rotation_matrix(rotation_deg)
        sx, sy = (np.hypot(r[0, 0] * sx, r[0, 1] * sy), np.hypot(r[1, 0] * sx, r[1, 1] * sy))
    return np.stack([sx, sy, sz])


def to_object_space(components, rotation_deg: float) -> np.ndarray:
    """``(x, y, z)`` vector components along a grid turned by ``rotation_deg`` about the
    optical axis, as object-space components ``(3, ...)`` (float64; with
    ``-rotation_deg``, object-space components onto the grid's axes)."""
    cx, cy, cz = (np.asarray(c, np.float64) for c in components)
    if rotation_deg:
        r = rotation_matrix(rotation_deg)
        cx, cy = r[0, 0] * cx + r[0, 1] * cy, r[1, 0] * cx + r[1, 1] * cy
    return np.stack([cx, cy, cz])


# ---- the field as a file ---------------------------------------------------------------
def grid_geometry(grid) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A grid's voxel size ``(dz, dy, dx)`` and voxel-0 centre ``(z0, y0, x0)`` in mm
    (what :meth:`plenocl.PIVResult.arrays` takes)."""
    spacing = tuple(float(s) for s in grid.spacing)
    lows = (grid.z[0], grid.y[0], grid.x[0])
    return spacing, tuple(lo + 0.5 * s for lo, s in zip(lows, spacing))


def _geometry(voxel_size_mm, origin_mm, grid, result: PIVResult | None = None):
    """Voxel size ``(dz, dy, dx)`` and voxel-0 centre ``(z0, y0, x0)`` in mm; with a
    ``grid``, ``result``'s window centres checked to lie on it."""
    if grid is not None:
        if result is not None:
            _check_on_grid(result, grid)
        return grid_geometry(grid)
    origin = _triple(origin_mm)
    if not np.all(np.isfinite(origin)):
        raise ValueError(f"origin_mm must be finite, a scalar or (z0, y0, x0) in mm (the "
                         f"centre of voxel 0), got {origin_mm!r}")
    return voxel_size(voxel_size_mm), tuple(float(o) for o in origin)


def _check_on_grid(result: PIVResult, grid) -> None:
    """Refuse a ``grid`` whose volume does not hold ``result``'s window centres (another
    grid than the volumes'): the vectors would be placed and scaled wrongly."""
    window = (0, 0, 0) if result.window is None else tuple(result.window)
    for axis, centres, n, w in zip("zyx", (result.z, result.y, result.x), grid.shape, window):
        # piv3d's windows lie whole in the volume; a quarter window's slack for fields
        # made otherwise (by hand, another tool), none for a grid smaller than the volume's
        centres, reach = np.asarray(centres, float), (float(w) - 1) / 4 if w else 0.0
        if centres.size and (centres.min() - reach < -0.5 - 1e-6
                             or centres.max() + reach > n - 0.5 + 1e-6):
            raise ValueError(f"this field's windows of {w or 1} voxels lie at voxels "
                             f"{centres.min():g} to {centres.max():g} along {axis}, but the "
                             f"grid has {n} voxels there: give the grid the "
                             "volumes were reconstructed on (grid_used.toml, or the "
                             "volume file's own)")


def field_arrays(result: PIVResult, voxel_size_mm=1.0, origin_mm=(0.0, 0.0, 0.0),
                 dt: float | None = None, rotation_deg: float = 0.0,
                 metadata: dict | None = None) -> dict[str, np.ndarray]:
    """All arrays :func:`save_field` writes to a ``.npz``, keyed by name: the field's own
    (:meth:`plenocl.PIVResult.arrays`) and a JSON ``metadata`` entry, its
    :meth:`~plenocl.PIVResult.metadata` with ``metadata``'s entries; the parameters are
    :func:`save_field`'s."""
    out = result.arrays(voxel_size_mm, origin_mm, dt, rotation_deg)
    out["metadata"] = np.asarray(json.dumps(_metadata(result, dt, metadata)))
    return out


def _metadata(result: PIVResult, dt: float | None, metadata: dict | None) -> dict:
    return {**(metadata or {}), **result.metadata(dt)}


def save_field(path: str | Path, result: PIVResult, voxel_size_mm=None,
               origin_mm=(0.0, 0.0, 0.0), dt: float | None = None, grid=None,
               metadata: dict | None = None) -> Path:
    """Write a PIV result, choosing the format from the extension (.vti, .npz, .h5/.hdf5,
    Tecplot ASCII .dat, .csv; :data:`plenocl.io.fieldformat.FIELD_FORMATS`), atomically.

    Parameters
    ----------
    path
        Output file; its suffix selects the format; its folder must be writable (both
        checked before anything is computed: a ``ValueError`` otherwise).
    result
        Output of :func:`plenocl.piv3d`.
    voxel_size_mm
        Scalar or ``(dz, dy, dx)`` in mm; without it (nor ``grid``) 1 mm, with a warning
        when ``dt`` asks for velocities (m/s from 1 mm voxels are rarely meant).
    origin_mm
        ``(z0, y0, x0)``: the centre of voxel ``(0, 0, 0)`` in mm.
    dt
        Time between the volumes (s); adds velocity in m/s and vorticity in 1/s.
    grid
        Optional :class:`plenocl.Grid` of the volumes; overrides ``voxel_size_mm`` and
        ``origin_mm`` (its extents are the volume's outer faces); on a rotated grid the
        velocity and vorticity are written in object space (:mod:`plenocl.io.fieldformat`).
    metadata
        JSON-ready entries stored with the field (``.npz``, ``.h5``; a batch run records
        each pair's source files here), read back by
        :func:`plenocl.io.fieldformat.field_metadata`.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = check_field_path(path)
    if voxel_size_mm is None:
        if grid is None and dt is not None:
            warnings.warn("save_field with dt but neither grid= nor voxel_size_mm=: the "
                          "velocities (m/s) take 1 mm voxels; give the volumes' grid (or "
                          "their voxel size in mm)", stacklevel=2)
        voxel_size_mm = 1.0
    size, origin = _geometry(voxel_size_mm, origin_mm, grid, result)
    rotation = 0.0 if grid is None else grid.rotation_deg
    return write_field(path, result.arrays(size, origin, dt, rotation),
                       _metadata(result, dt, metadata))


def read_npz(path) -> tuple[PIVResult, dict[str, np.ndarray]]:
    """Read a field written by :func:`save_field` to a ``.npz`` or ``.h5`` (a file of the
    first layout comes back in the current one, :func:`plenocl.io.fieldformat.read_field`).

    Returns
    -------
    result : PIVResult
        The displacement field and flags (per-pass diagnostics are not stored).
    arrays : dict
        Every stored array, including ``voxel_size_mm_xyz``, ``origin_mm_xyz`` (both
        (x, y, z)) and, if written, ``dt`` and ``velocity``.
    """
    arrays = read_field(path)
    return PIVResult.from_arrays(arrays, source=str(path)), arrays
