"""A point particle's raw image and its derivatives, traced ray by ray through the camera
(docs/design.md §7.2): the forward model the image-space particle fit
(:mod:`plenocl.piv.imagefit`) matches to the raw image.

The rays are those of the simulator (docs/design.md §2, §8): from the image point
``X' = (X', Y', d')`` of the particle (``d'``: its distance from the exit pupil,
:meth:`plenocl.Camera.image_points`) through a point ``u`` of the exit pupil to
``x = u + (X' - u) d / d'`` on the microlens array (``d``: the pupil's distance from the
array; a thin lens: ``s_i`` and ``s_i'``), and from the microlens ``k`` that holds ``x``
to ``x_k + f_ml (X' - u) / d'`` on the sensor. The aperture is sampled on
a fixed sunflower pattern instead of at random, each ray lands as a pixel-integrated
Gaussian of the optics' blur, and a ray within a ramp of a cell edge is shared between
the two lenses, so the image is a smooth function of ``X'``: its derivatives are exact
and a Gauss-Newton fit can follow them. The lenses are the camera's calibrated centres
(or its ideal ones) and their cells the affine lattice fitted to them
(:class:`plenocl.camera.lattice.RectangularLattice`), as the projector's; a hexagonal
array's cells are the hexagons around its lenses on the axial lattice fitted to them
(:class:`plenocl.optics.hexcells.HexCells`), where a ray near an edge or a vertex is
shared between two or three lenses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import erf

from ..camera import Camera
from ..camera.lattice import RectangularLattice
from .hexcells import HEX_RAMP_MAX, HexCells

#: Golden angle of the sunflower pattern (radians).
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
#: Narrowest ramp (lattice units) over which a ray is shared between two lenses.
RAMP_FLOOR = 1e-3
#: Pixel offsets around a ray's nearest pixel that receive its blurred light (5 x 5
#: pixels; the shares are normalised over them, so no light is lost).
SPREAD = (-2, -1, 0, 1, 2)


def sunflower(n: int) -> np.ndarray:
    """``n`` points ``(n, 2)`` evenly spread over the unit disk (equal area each)."""
    i = np.arange(n) + 0.5
    r, t = np.sqrt(i / n), i * GOLDEN_ANGLE
    return np.column_stack([r * np.cos(t), r * np.sin(t)])


@dataclass(frozen=True)
class Spots:
    """Where each (particle, ray, lens) lands: ``pid`` (particle), ``col``/``row``
    (pixels), ``weight`` (the ray's share of this lens) and the derivatives with
    respect to the image point ``(X', Y', d')``: ``dweight`` ``(3, M)``, ``dcol_dx``
    (equal to ``drow/dY'``), ``dcol_ds``, ``drow_ds``."""

    pid: np.ndarray
    col: np.ndarray
    row: np.ndarray
    weight: np.ndarray
    dweight: np.ndarray
    dcol_dx: np.ndarray
    dcol_ds: np.ndarray
    drow_ds: np.ndarray


@dataclass(frozen=True)
class Patches:
    """One rectangle of the sensor per particle: rows ``row0``, columns ``col0`` of
    ``width`` and ``height`` pixels, stored one after another from ``offset``."""

    offset: np.ndarray
    col0: np.ndarray
    row0: np.ndarray
    width: np.ndarray
    height: np.ndarray

    def pixels(self, sensor_width: int, elements: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The particle and the sensor's flat pixel index of patch elements (by default
        all of them, in order)."""
        elements = np.arange(self.offset[-1]) if elements is None else elements
        pid = np.searchsorted(self.offset, elements, side="right") - 1
        local = elements - self.offset[pid]
        row = self.row0[pid] + local // self.width[pid]
        return pid, row * sensor_width + self.col0[pid] + local % self.width[pid]


@dataclass(frozen=True)
class RayBundle:
    """The camera's rays for the image-space fit.

    Build it with :meth:`of`; ``aperture`` holds the sampled aperture points (mm),
    ``lenses`` the lens centres on the array plane ``(rows, cols, 2)`` mm and
    ``to_lattice`` the ``(3, 2)`` map ``[x, y, 1] @ to_lattice = (kx, ky)``. For a
    hexagonal array ``cells`` holds its hexagonal cells, and ``lenses`` and ``to_lattice``
    are those of its axial view (:meth:`plenocl.Camera.on_lens_lattice`: indices
    ``(q - q_min, r)``, NaN where the view has no lens); ``None`` for a rectangular one.
    """

    camera: Camera
    aperture: np.ndarray
    lenses: np.ndarray
    to_lattice: np.ndarray
    blur_px: float
    cells: HexCells | None = None

    @classmethod
    def of(cls, camera: Camera, rays: int = 400, blur_px: float = 0.8) -> RayBundle:
        """The bundle of ``camera`` with ``rays`` aperture samples and the optics' blur
        (Gaussian standard deviation in pixels)."""
        if int(rays) != rays or rays < 16:
            raise ValueError(f"rays must be an integer >= 16, got {rays!r}")
        if not (np.isfinite(blur_px) and blur_px > 0):
            raise ValueError(f"blur_px must be a positive number of pixels, got {blur_px!r}")
        lenses, fit, cells = _lens_cells(camera)
        inverse = np.linalg.inv(fit[:2])
        to_lattice = np.vstack([inverse, -fit[2] @ inverse])
        aperture = sunflower(int(rays)) * camera.exit_pupil_diameter_mm / 2
        return cls(camera, aperture, lenses, to_lattice, float(blur_px), cells)

    @property
    def rays(self) -> int:
        """Aperture samples per particle."""
        return len(self.aperture)

    def _ramp(self, s_ip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Half-width (lattice units) over which a ray is shared between two lenses, the
        spacing of the aperture samples on the array plane, per particle; and its
        derivative by ``d'``."""
        cam = self.camera
        spacing = cam.exit_pupil_diameter_mm / 2 * np.sqrt(np.pi / self.rays) / cam.ml_pitch_mm
        rho = cam.exit_pupil_distance_mm / s_ip
        ramp = spacing * np.abs(1 - rho)
        slope = spacing * np.sign(1 - rho) * cam.exit_pupil_distance_mm / s_ip**2
        floor = ramp < RAMP_FLOOR
        return np.where(floor, RAMP_FLOOR, ramp), np.where(floor, 0.0, slope)

    def spots(self, image_points: np.ndarray) -> Spots:
        """Every ray of every particle ``image_points`` ``(P, 3)`` ``(X', Y', d')``
        (:meth:`plenocl.Camera.image_points`) on the sensor."""
        cam = self.camera
        s_ip = image_points[:, 2]
        rho = cam.exit_pupil_distance_mm / s_ip
        e = image_points[:, None, :2] - self.aperture[None]  # (P, N, 2): X' - u
        x = self.aperture[None] + e * rho[:, None, None]
        lat = x @ self.to_lattice[:2] + self.to_lattice[2]
        ramp, dramp = self._ramp(s_ip)
        if self.cells is not None:
            return self._hexagonal_spots(image_points, e, rho, lat, ramp, dramp)
        kx, *share_x = _shares(lat[..., 0], ramp[:, None])
        ky, *share_y = _shares(lat[..., 1], ramp[:, None])
        # lens choices (own, neighbour) per axis: (P, N, 2, 2)
        kx, ky = kx[..., :, None], ky[..., None, :]
        lw = share_x[0][..., :, None] * share_y[0][..., None, :]
        rows, cols = self.lenses.shape[:2]
        keep = (lw > 0) & (kx >= 0) & (ky >= 0) & (kx < cols) & (ky < rows)
        pid, ray, cx, cy = np.nonzero(keep)
        kxk, kyk = kx[pid, ray, cx, 0], ky[pid, ray, 0, cy]
        centre = self.lenses[kyk, kxk]
        ok = np.isfinite(centre).all(axis=1)
        pid, ray, cx, cy, centre = pid[ok], ray[ok], cx[ok], cy[ok], centre[ok]
        return self._landing(image_points, e, rho, pid, ray, centre,
                             [a[pid, ray, cx] for a in share_x],
                             [a[pid, ray, cy] for a in share_y], dramp[pid])

    def _hexagonal_spots(self, image_points: np.ndarray, e: np.ndarray, rho: np.ndarray,
                         lat: np.ndarray, ramp: np.ndarray, dramp: np.ndarray) -> Spots:
        """:meth:`spots` on hexagonal cells: the nearest lens and the neighbours that
        share a ray (:meth:`HexCells.shares`, the ramp cut to :data:`HEX_RAMP_MAX`)."""
        cut = ramp > HEX_RAMP_MAX
        ramp, dramp = np.where(cut, HEX_RAMP_MAX, ramp), np.where(cut, 0.0, dramp)
        index, share, dshare_dx, dshare_dr = self.cells.shares(lat, ramp[:, None])
        q, r = index[..., 0], index[..., 1]
        rows, cols = self.lenses.shape[:2]
        keep = (share > 0) & (q >= 0) & (r >= 0) & (q < cols) & (r < rows)
        pid, ray, k = np.nonzero(keep)
        centre = self.lenses[r[pid, ray, k], q[pid, ray, k]]
        ok = np.isfinite(centre).all(axis=1)
        pid, ray, k, centre = pid[ok], ray[ok], k[ok], centre[ok]
        # the array point x = u + e rho moves by rho per X' and by -e d/d'^2 per d'
        dx = dshare_dx[pid, ray, k]
        dx_ds = -e[pid, ray] * self.camera.exit_pupil_distance_mm / image_points[pid, 2,
                                                                                 None] ** 2
        dweight = np.stack([rho[pid] * dx[:, 0], rho[pid] * dx[:, 1],
                            (dx * dx_ds).sum(axis=1) + dshare_dr[pid, ray, k] * dramp[pid]])
        return self._land(image_points, e, pid, ray, centre, share[pid, ray, k], dweight)

    def _landing(self, image_points, e, rho, pid, ray, centre, share_x, share_y,
                 dramp) -> Spots:
        """The sensor position of the chosen rays and the derivatives of position and
        lens share with respect to the image point."""
        cam = self.camera
        s_ip = image_points[pid, 2]
        ee = e[pid, ray]
        # lattice coordinates move with x = u + e rho: dx/dX' = rho, dx/dd' = -e d/d'^2
        inv = self.to_lattice[:2]
        dlat = [rho[pid, None] * inv[0], rho[pid, None] * inv[1],
                (-ee * cam.exit_pupil_distance_mm / s_ip[:, None] ** 2) @ inv]
        (wx, dwx, rwx), (wy, dwy, rwy) = share_x, share_y
        dweight = np.stack([dwx * wy * d[:, 0] + wx * dwy * d[:, 1] for d in dlat])
        dweight[2] += (rwx * wy + wx * rwy) * dramp  # the ramp widens with defocus
        return self._land(image_points, e, pid, ray, centre, wx * wy, dweight)

    def _land(self, image_points: np.ndarray, e: np.ndarray, pid: np.ndarray,
              ray: np.ndarray, centre: np.ndarray, weight: np.ndarray,
              dweight: np.ndarray) -> Spots:
        """The chosen rays' sensor positions and their derivatives by the image point,
        with their lens shares ``weight`` and its derivatives ``dweight`` ``(3, M)``."""
        cam = self.camera
        pp, f = cam.pixel_pitch_mm, cam.ml_focal_length_mm
        s_ip = image_points[pid, 2]
        ee = e[pid, ray]
        colrow = cam.mm_to_px(centre + f * ee / s_ip[:, None])
        return Spots(pid, colrow[:, 0], colrow[:, 1], weight, dweight, f / (s_ip * pp),
                     -f * ee[:, 0] / (s_ip**2 * pp), -f * ee[:, 1] / (s_ip**2 * pp))

    def patches(self, image_points: np.ndarray, margin: int = 3) -> Patches:
        """A sensor rectangle per particle that holds all its light: its blur circle on
        the array plane grown by a lens and ``margin`` pixels."""
        cam = self.camera
        s_ip = image_points[:, 2]
        rho = cam.exit_pupil_distance_mm / s_ip
        radius = cam.exit_pupil_diameter_mm / 2 * np.abs(1 - rho) + cam.ml_pitch_mm
        centre = image_points[:, :2] * rho[:, None]
        scale = cam.lens_image_scale
        lo = cam.mm_to_px((centre - radius[:, None]) * scale) - margin
        hi = cam.mm_to_px((centre + radius[:, None]) * scale) + margin
        size = np.array(cam.pixels)
        lo = np.clip(np.floor(lo), 0, size).astype(np.int64)
        hi = np.clip(np.ceil(hi) + 1, 0, size).astype(np.int64)
        width, height = np.maximum(hi - lo, 1).T
        offset = np.concatenate([[0], np.cumsum(width * height)])
        return Patches(offset, lo[:, 0], lo[:, 1], width, height)

    def render(self, image_points: np.ndarray, intensity: np.ndarray, patches: Patches,
               derivatives: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The particles' images on their patches and the derivatives.

        Returns the patch elements the light reaches ``(n,)`` (ascending; the rest are
        zero) and their rows ``(5, n)``: value, d/dX', d/dY', d/dd' and d/dI; the
        value row alone ``(1, n)`` without ``derivatives``.
        """
        s = self.spots(image_points)
        scale = (intensity[s.pid] / self.rays)[:, None, None]
        near = np.rint(np.column_stack([s.col, s.row])).astype(np.int64)
        (gx, dx), (gy, dy) = (_spread(near[:, k], (s.col, s.row)[k], self.blur_px)
                              for k in range(2))
        lc = near[:, 0, None] + np.asarray(SPREAD) - patches.col0[s.pid, None]  # (M, 5)
        lr = near[:, 1, None] + np.asarray(SPREAD) - patches.row0[s.pid, None]
        width = patches.width[s.pid, None]
        ok = ((lc >= 0) & (lc < width))[:, :, None] & (
            (lr >= 0) & (lr < patches.height[s.pid, None]))[:, None, :]
        index = (patches.offset[s.pid, None, None] + lr[:, None, :] * width[:, :, None]
                 + lc[:, :, None])[ok]
        g = gx[:, :, None] * gy[:, None, :]  # (M, 5 columns, 5 rows)
        w = s.weight[:, None, None]
        rows = [w * g * scale]
        if derivatives:
            dw = s.dweight[:, :, None, None]
            gxy = (dx[:, :, None] * gy[:, None, :], gx[:, :, None] * dy[:, None, :])
            rows += [(dw[0] * g + w * gxy[0] * s.dcol_dx[:, None, None]) * scale,
                     (dw[1] * g + w * gxy[1] * s.dcol_dx[:, None, None]) * scale,
                     (dw[2] * g + w * (gxy[0] * s.dcol_ds[:, None, None]
                                       + gxy[1] * s.drow_ds[:, None, None])) * scale,
                     w * g / self.rays]
        reached = np.bincount(index, minlength=int(patches.offset[-1])) > 0
        compact = (np.cumsum(reached) - 1)[index]
        elements = np.flatnonzero(reached)
        return elements, np.stack([np.bincount(compact, row[ok], minlength=len(elements))
                                   for row in rows])


def _lens_cells(camera: Camera) -> tuple[np.ndarray, np.ndarray, HexCells | None]:
    """The lens centres on the array plane ``(rows, cols, 2)`` mm (a hexagonal array's
    axial view, NaN where it has no lens), the ``(3, 2)`` lattice fitted to them and a
    hexagonal array's cells (``None`` for a rectangular one). The axial view itself (the
    projector's camera, :meth:`Camera.on_lens_lattice`) is taken as its hexagonal array."""
    centres = camera.on_lens_lattice().microlens_centers
    centres = camera.ideal_microlens_centers() if centres is None else centres
    lenses = camera.px_to_mm(centres) / camera.lens_image_scale
    if camera.layout.hexagonal:
        cells = HexCells.fit(lenses)
        return lenses, cells.model, cells
    return lenses, RectangularLattice.fit(lenses).model, None


def _shares(coord: np.ndarray, ramp: np.ndarray):
    """Per lattice axis: the lens index of the own and the neighbouring cell ``(..., 2)``,
    the ray's share of each, and the shares' derivatives by the coordinate and by the
    ramp. Within ``ramp`` of a cell edge the share falls linearly from 1 to 1/2 at the
    edge (0 beyond ``ramp``)."""
    n = np.rint(coord)
    t = coord - n
    up = np.clip((t - (0.5 - ramp)) / (2 * ramp), 0, 1)
    down = np.clip(((ramp - 0.5) - t) / (2 * ramp), 0, 1)
    side = np.where(up > 0, 1, np.where(down > 0, -1, 0))
    w = np.where(side > 0, up, down)
    inside = (w > 0) & (w < 1)
    dw = np.where(inside, side / (2 * ramp), 0.0)
    dr = np.where(inside, np.where(side > 0, 0.5 - t, t + 0.5) / (2 * ramp**2), 0.0)
    index = np.stack([n, n + side], axis=-1).astype(np.int64)
    return (index, np.stack([1 - w, w], axis=-1), np.stack([-dw, dw], axis=-1),
            np.stack([-dr, dr], axis=-1))


def _spread(nearest: np.ndarray, x: np.ndarray, sigma: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """The share ``(M, 5)`` of a ray at ``x`` that each pixel ``nearest + SPREAD``
    receives, normalised over them, and its derivative by ``x``."""
    g, d = _pixel_gauss(nearest[:, None] + np.asarray(SPREAD), x[:, None], sigma)
    total, dtotal = g.sum(axis=1, keepdims=True), d.sum(axis=1, keepdims=True)
    return g / total, (d - g / total * dtotal) / total


def _pixel_gauss(pixel: np.ndarray, x: np.ndarray, sigma: float):
    """Share of a Gaussian of ``sigma`` centred at ``x`` that falls on ``pixel`` (pixels
    centred at integers), and its derivative by ``x``."""
    s2 = np.sqrt(2.0) * sigma
    hi, lo = (pixel + 0.5 - x) / s2, (pixel - 0.5 - x) / s2
    return (0.5 * (erf(hi) - erf(lo)),
            (np.exp(-lo**2) - np.exp(-hi**2)) / (np.sqrt(np.pi) * s2))
