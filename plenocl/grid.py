"""The reconstruction volume: shape, extents, voxel size and centres (DESIGN §9).

Extents are the outer faces of the volume in millimetres, so a grid with
``shape=(nz, ny, nx)`` and ``x=(x0, x1)`` has voxels ``dx = (x1 - x0) / nx`` wide with
centres at ``x0 + (ix + 0.5) dx``. Volumes are indexed ``vol[iz, iy, ix]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .tomlio import read_toml, write_toml


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
    """

    shape: tuple[int, int, int]
    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]

    def __post_init__(self) -> None:
        shape = tuple(self.shape)
        if len(shape) != 3 or any(int(n) != n or n <= 0 for n in shape):
            raise ValueError(f"grid shape must be three positive integers (nz, ny, nx), "
                             f"got {self.shape!r}")
        object.__setattr__(self, "shape", tuple(int(n) for n in shape))
        for name in "xyz":
            object.__setattr__(self, name, _extent(name, getattr(self, name)))

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
        """All voxel centres ``(N, 3)`` as ``(x, y, z)`` in C order of ``vol[iz, iy, ix]``."""
        zz, yy, xx = np.meshgrid(self.axis_centers("z"), self.axis_centers("y"),
                                 self.axis_centers("x"), indexing="ij")
        return np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])

    def to_index(self, points_xyz) -> np.ndarray:
        """Fractional voxel indices ``(ix, iy, iz)`` of points ``(N, 3)``; centres are integers."""
        pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        dz, dy, dx = self.spacing
        lo = np.array([self.x[0], self.y[0], self.z[0]])
        return (pts - lo) / np.array([dx, dy, dz]) - 0.5

    def contains(self, points_xyz) -> np.ndarray:
        """Whether each point lies inside the volume."""
        pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        inside = np.ones(len(pts), bool)
        for k, name in enumerate("xyz"):
            lo, hi = getattr(self, name)
            inside &= (pts[:, k] >= lo) & (pts[:, k] <= hi)
        return inside

    def to_dict(self) -> dict:
        """The grid as a TOML-ready dictionary."""
        return {"grid": {"shape": list(self.shape), "x_mm": list(self.x),
                         "y_mm": list(self.y), "z_mm": list(self.z)}}

    @classmethod
    def from_toml(cls, path: str | Path) -> Grid:
        """Read a grid file (section ``[grid]`` with ``shape``, ``x_mm``, ``y_mm``, ``z_mm``)."""
        doc = read_toml(path)
        try:
            g = doc["grid"]
            return cls(tuple(g["shape"]), tuple(g["x_mm"]), tuple(g["y_mm"]), tuple(g["z_mm"]))
        except KeyError as exc:
            raise ValueError(f"{path}: the [grid] section needs shape, x_mm, y_mm and z_mm "
                             f"(missing {exc.args[0]!r})") from None

    def to_toml(self, path: str | Path) -> None:
        """Write a grid file atomically."""
        write_toml(path, self.to_dict())

    @classmethod
    def for_camera(cls, camera, z: tuple[float, float], voxel_mm: float | None = None,
                   depth_voxel_mm: float | None = None, fraction: float = 1.0) -> Grid:
        """A grid covering the camera's field of view over depths ``z``.

        The default lateral voxel is one microlens projected into object space (the
        paper's choice, ``p_ml / M``); the default depth voxel is half the camera's depth
        resolution (:attr:`Camera.depth_resolution_mm`), the finest depth sampling the
        optics support. ``fraction`` of the field of view is covered.
        """
        voxel = voxel_mm or camera.ml_pitch_mm / camera.magnification
        dvox = depth_voxel_mm or camera.depth_resolution_mm / 2
        w, h = (n * camera.ml_pitch_mm / camera.magnification * fraction
                for n in camera.ml_count)
        nx, ny = max(1, round(w / voxel)), max(1, round(h / voxel))
        nz = max(1, round((z[1] - z[0]) / dvox))
        return cls((nz, ny, nx), (-nx * voxel / 2, nx * voxel / 2),
                   (-ny * voxel / 2, ny * voxel / 2), tuple(z))
