"""The reconstruction volume: shape, extents, voxel size and centres (docs/design.md §9).

Extents are the outer faces of the volume in millimetres, so a grid with
``shape=(nz, ny, nx)`` and ``x=(x0, x1)`` has voxels ``dx = (x1 - x0) / nx`` wide with
centres at ``x0 + (ix + 0.5) dx``. Volumes are indexed ``vol[iz, iy, ix]``.

A grid may be rotated about the optical axis (``rotation_deg``): its ``x``/``y`` extents
and axes are then those of a frame turned counter-clockwise by that angle, and a point's
object-space coordinates are ``(x, y) = R (x_g, y_g)``. A frame that follows the
microlens rows makes the projector separable for a rotated array
(:meth:`Grid.for_camera`). Methods that take or return points (:meth:`centers`,
:meth:`to_index`, :meth:`contains`) use object-space coordinates; :meth:`to_world`
turns grid-frame vectors (a velocity field) into object-space ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera.lattice import DEFAULT_SHEAR_TOL, rotation_matrix, separable_rotation_deg
from .camera.pose import require_world_frame
from .io.tomlfile import read_toml, write_toml
from .optics.depthrange import check_grid


def _extent(name: str, value) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo, hi = math.nan, math.nan
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        raise ValueError(f"grid extent {name} must be two finite numbers (lo, hi) with lo < hi "
                         f"in mm, got {tuple(value)!r}")
    return lo, hi


@dataclass(frozen=True)
class Grid:
    """A regular voxel grid in object space (mm).

    Parameters
    ----------
    shape
        ``(nz, ny, nx)`` voxel counts.
    x, y, z
        ``(lo, hi)`` extents of the volume's outer faces in mm; +z points away from the
        camera, the origin is on the optical axis at the nominal focal plane.
    rotation_deg
        Rotation of the grid's lateral axes about the optical axis (counter-clockwise,
        degrees); ``x`` and ``y`` are extents along the rotated axes.
    """

    shape: tuple[int, int, int]
    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]
    rotation_deg: float = 0.0

    def __post_init__(self) -> None:
        shape = tuple(self.shape)
        if len(shape) != 3 or any(int(n) != n or n <= 0 for n in shape):
            raise ValueError(f"grid shape must be three positive integers (nz, ny, nx), "
                             f"got {self.shape!r}")
        object.__setattr__(self, "shape", tuple(int(n) for n in shape))
        for name in "xyz":
            object.__setattr__(self, name, _extent(name, getattr(self, name)))
        rot = self.rotation_deg
        if not (isinstance(rot, (int, float)) and math.isfinite(rot) and abs(rot) <= 45):
            raise ValueError(f"grid rotation_deg must be a finite angle within ±45 degrees, "
                             f"got {rot!r}")
        object.__setattr__(self, "rotation_deg", float(rot))

    def to_world(self, vx, vy) -> tuple[np.ndarray, np.ndarray]:
        """Object-space ``x``, ``y`` components of vectors given along the grid's axes
        (``R (vx, vy)``; unchanged for an unrotated grid)."""
        vx, vy = np.asarray(vx, dtype=np.float64), np.asarray(vy, dtype=np.float64)
        if not self.rotation_deg:
            return vx, vy
        r = rotation_matrix(self.rotation_deg)
        return r[0, 0] * vx + r[0, 1] * vy, r[1, 0] * vx + r[1, 1] * vy

    def to_frame(self, points_xyz) -> np.ndarray:
        """Points ``(N, 3)`` from object space into the grid's frame (``Rᵀ (x, y)``, z)."""
        pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        if not self.rotation_deg:
            return pts
        out = pts.copy()
        out[:, :2] = pts[:, :2] @ rotation_matrix(self.rotation_deg)
        return out

    def refined(self, factor: int) -> Grid:
        """The same volume with ``factor x factor`` lateral sub-voxels per voxel: shape
        ``(nz, ny * factor, nx * factor)``, same extents, depth planes and rotation."""
        if int(factor) != factor or factor < 1:
            raise ValueError(f"refinement factor must be a positive integer, got {factor!r}")
        nz, ny, nx = self.shape
        return Grid((nz, ny * int(factor), nx * int(factor)), self.x, self.y, self.z,
                    self.rotation_deg)

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Voxel size ``(dz, dy, dx)`` in mm, in array order."""
        nz, ny, nx = self.shape
        return ((self.z[1] - self.z[0]) / nz, (self.y[1] - self.y[0]) / ny,
                (self.x[1] - self.x[0]) / nx)

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        """Bytes of one float32 volume."""
        return 4 * self.size

    def axis_centers(self, axis: str) -> np.ndarray:
        """Voxel-centre coordinates (mm) along ``"x"``, ``"y"`` or ``"z"``."""
        n = self.shape[{"z": 0, "y": 1, "x": 2}[axis]]
        lo, hi = getattr(self, axis)
        return lo + (np.arange(n) + 0.5) * (hi - lo) / n

    def centers(self) -> np.ndarray:
        """All voxel centres ``(N, 3)`` as object-space ``(x, y, z)`` in C order of
        ``vol[iz, iy, ix]``."""
        zz, yy, xx = np.meshgrid(self.axis_centers("z"), self.axis_centers("y"),
                                 self.axis_centers("x"), indexing="ij")
        wx, wy = self.to_world(xx.ravel(), yy.ravel())
        return np.column_stack([wx, wy, zz.ravel()])

    def to_index(self, points_xyz) -> np.ndarray:
        """Fractional voxel indices ``(ix, iy, iz)`` of object-space points ``(N, 3)``;
        centres are integers."""
        pts = self.to_frame(points_xyz)
        dz, dy, dx = self.spacing
        lo = np.array([self.x[0], self.y[0], self.z[0]])
        return (pts - lo) / np.array([dx, dy, dz]) - 0.5

    def index_jacobian(self) -> np.ndarray:
        """``(3, 3)`` ``d (ix, iy, iz) / d (x, y, z)``: an object-space offset (mm) as a
        fractional voxel-index offset (:meth:`to_index` is affine)."""
        dz, dy, dx = self.spacing
        return (self.to_frame(np.eye(3)) / np.array([dx, dy, dz])).T

    def from_index(self, index_xyz) -> np.ndarray:
        """Object-space points ``(N, 3)`` of fractional voxel indices ``(ix, iy, iz)``
        (the inverse of :meth:`to_index`)."""
        idx = np.asarray(index_xyz, dtype=np.float64).reshape(-1, 3)
        dz, dy, dx = self.spacing
        lo = np.array([self.x[0], self.y[0], self.z[0]])
        pts = (idx + 0.5) * np.array([dx, dy, dz]) + lo
        wx, wy = self.to_world(pts[:, 0], pts[:, 1])
        return np.column_stack([wx, wy, pts[:, 2]])

    def corners(self, margin: float = 0.0) -> np.ndarray:
        """The eight corners ``(8, 3)`` (mm) of the volume's outer faces, moved out by
        ``margin`` voxels on every side."""
        lo, hi = -0.5 - margin, np.array(self.shape[::-1], float) - 0.5 + margin
        pick = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], bool)
        return self.from_index(np.where(pick, hi, lo))

    def contains(self, points_xyz) -> np.ndarray:
        """Whether each object-space point lies inside the volume."""
        pts = self.to_frame(points_xyz)
        inside = np.ones(len(pts), bool)
        for k, name in enumerate("xyz"):
            lo, hi = getattr(self, name)
            inside &= (pts[:, k] >= lo) & (pts[:, k] <= hi)
        return inside

    def to_dict(self) -> dict:
        """The grid as a TOML-ready dictionary."""
        grid = {"shape": list(self.shape), "x_mm": list(self.x), "y_mm": list(self.y),
                "z_mm": list(self.z)}
        if self.rotation_deg:
            grid["rotation_deg"] = self.rotation_deg
        return {"grid": grid}

    @classmethod
    def from_toml(cls, path: str | Path) -> Grid:
        """Read a grid file (section ``[grid]`` with ``shape``, ``x_mm``, ``y_mm``, ``z_mm``
        and optionally ``rotation_deg``)."""
        doc = read_toml(path)
        g = doc.get("grid")
        if not isinstance(g, dict):
            raise ValueError(f"{path}: a grid file needs a [grid] section with shape, x_mm, "
                             "y_mm and z_mm")
        unknown = sorted(set(g) - set(GRID_KEYS))
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {unknown} in [grid]; it takes "
                             f"{list(GRID_KEYS)}")
        missing = [key for key in GRID_KEYS[:4] if key not in g]
        if missing:
            raise ValueError(f"{path}: the [grid] section needs shape, x_mm, y_mm and z_mm "
                             f"(missing {missing[0]!r})")
        lists = [key for key, n in zip(GRID_KEYS[:4], (3, 2, 2, 2))
                 if not (isinstance(g[key], list) and len(g[key]) == n)]
        if lists:
            raise ValueError(f"{path}: [grid] {lists[0]} must be a list of "
                             f"{3 if lists[0] == 'shape' else 2} numbers "
                             f"({'[nz, ny, nx]' if lists[0] == 'shape' else '[low, high] mm'}), "
                             f"got {g[lists[0]]!r}")
        try:
            return cls(tuple(g["shape"]), tuple(g["x_mm"]), tuple(g["y_mm"]), tuple(g["z_mm"]),
                       g.get("rotation_deg", 0.0))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{path}: {exc}") from None

    def to_toml(self, path: str | Path) -> None:
        """Write a grid file atomically."""
        write_toml(path, self.to_dict())

    @classmethod
    def for_camera(cls, camera, z: tuple[float, float], voxel_mm: float | None = None,
                   depth_voxel_mm: float | None = None, fraction: float = 1.0,
                   rotation_deg: float | None = None) -> Grid:
        """A grid covering the camera's field of view over depths ``z``, centred on what
        the sensor's (a region of interest's) centre sees at the nominal focal plane.

        The default lateral voxel is one microlens projected into object space (the
        paper's choice, ``p_ml / M``); the default depth voxel is half the camera's depth
        resolution (:attr:`Camera.depth_resolution_mm`), the finest depth sampling the
        optics support. ``fraction`` of the field of view is covered. By default
        (``rotation_deg=None``) the grid's lateral axes follow the microlens rows and
        columns of the (calibrated) array, so that a rotated array projects on the fast
        separable path; an array aligned with the sensor to within 0.001 lens across it
        keeps the sensor's axes. A hexagonal array's field is its columns' pitch by its
        rows' (``pitch·√3/2``), and its axes follow its rows.
        """
        require_world_frame(camera, "Grid.for_camera")
        z = _extent("z", z)
        voxel = _size(voxel_mm, "voxel_mm", camera.ml_pitch_mm / camera.magnification)
        dvox = _size(depth_voxel_mm, "depth_voxel_mm", camera.depth_resolution_mm / 2)
        if _real(fraction) is None or not 0 < fraction <= 1:
            raise ValueError(f"fraction is the share of the field of view the grid covers, "
                             f"0 < fraction <= 1, got {fraction!r}")
        w, h = (n * step / camera.magnification * fraction for n, step in
                zip(camera.ml_count, (camera.ml_pitch_mm, camera.ml_row_pitch_mm)))
        if voxel_mm is not None:  # a default larger than its span: one voxel, as before
            _fits(voxel, "voxel_mm", min(w, h), "the field of view covered")
        if depth_voxel_mm is not None:
            _fits(dvox, "depth_voxel_mm", z[1] - z[0], f"the depth range {z}")
        nx, ny = max(1, round(w / voxel)), max(1, round(h / voxel))
        nz = max(1, round((z[1] - z[0]) / dvox))
        if nx * ny * nz > MAX_VOXELS:
            raise ValueError(f"a grid of {nz} x {ny} x {nx} voxels (z, y, x) is more than "
                             f"any device holds ({MAX_VOXELS:.2g}): voxel_mm {voxel:g} and "
                             f"depth_voxel_mm {dvox:g} are in millimetres (the defaults: "
                             f"{camera.ml_pitch_mm / camera.magnification:.3g} and "
                             f"{camera.depth_resolution_mm / 2:.3g})")
        if rotation_deg is None:
            rotation_deg = separable_rotation_deg(camera.on_lens_lattice().microlens_centers,
                                                  DEFAULT_SHEAR_TOL)
        cx, cy = camera.field_centre_mm() @ rotation_matrix(rotation_deg)  # grid frame
        grid = cls((nz, ny, nx), (cx - nx * voxel / 2, cx + nx * voxel / 2),
                   (cy - ny * voxel / 2, cy + ny * voxel / 2), tuple(z), rotation_deg)
        check_grid(camera, grid)
        return grid


#: The keys of a grid file's ``[grid]`` section (the first four required).
GRID_KEYS = ("shape", "x_mm", "y_mm", "z_mm", "rotation_deg")
#: The most voxels :meth:`Grid.for_camera` makes: 2^31 float32 voxels are 8 GiB, and
#: the kernels index a volume with 32-bit integers.
MAX_VOXELS = 2**31 - 1


def _size(value, name: str, default: float) -> float:
    """A voxel size in mm: ``value``, a positive finite number, or ``default`` for None."""
    if value is None:
        return float(default)
    size = _real(value)
    if size is None or not (np.isfinite(size) and size > 0):
        raise ValueError(f"{name} must be a positive size in mm, or None for the default "
                         f"({default:.3g} mm), got {value!r}")
    return size


def _real(value) -> float | None:
    """``value`` as a float when it is one real number (a NumPy scalar or 0-d array, a
    fraction), else ``None`` (text, a bool, several numbers)."""
    if isinstance(value, (bool, np.bool_, str, bytes)) or np.ndim(value) \
            or np.iscomplexobj(value):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _fits(size: float, name: str, span: float, what: str) -> None:
    """A voxel no larger than the span it divides (a size in µm given as mm, say)."""
    if size > span:
        raise ValueError(f"{name} = {size:g} mm is larger than {what} ({span:.3g} mm): "
                         "sizes are in millimetres")
