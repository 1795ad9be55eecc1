"""Synthetic flows with known truth, particle displacement and volume-pair rendering.

A *flow* is any callable mapping positions ``(N, 3)`` as ``(x, y, z)`` to velocities
``(N, 3)`` in consistent units (docs/design.md §1, §8). The flows here are steady: uniform,
solid-body rotation, a Lamb-Oseen vortex and a turbulent boundary layer (a Musker mean
profile with a Coles wake plus divergence-free vortical eddies).

:func:`volume_pair` renders two float32 volumes ``vol[iz, iy, ix]`` of Gaussian particles
(each integrated over its voxels with ``erf``) seeded at the mid time and moved by
``-dt/2`` and ``+dt/2`` along the flow, so the reference displacement at a point is
:func:`centred_displacement` (what symmetric-deformation PIV measures).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.special import erf

Flow = Callable[[np.ndarray], np.ndarray]

__all__ = [
    "Flow",
    "LambOseen",
    "SolidBodyRotation",
    "TurbulentBoundaryLayer",
    "Uniform",
    "VolumePair",
    "centred_displacement",
    "displace",
    "musker_profile",
    "render_particles",
    "volume_pair",
]


def _points(positions: np.ndarray) -> np.ndarray:
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must be an (N, 3) array of (x, y, z), got shape {p.shape}")
    return p


def _unit(vector, name: str) -> np.ndarray:
    v = np.asarray(vector, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(v)
    if not np.isfinite(norm) or norm == 0:
        raise ValueError(f"{name} must be a finite non-zero 3-vector (x, y, z), got {vector!r}")
    return v / norm


def _three_finite(name: str, value) -> None:
    """``value`` three finite numbers ``(x, y, z)`` (one number was spread over all three,
    two gave NumPy's broadcasting error)."""
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        v = np.full(0, np.nan)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be three finite numbers (x, y, z), got {value!r}")


@dataclass(frozen=True)
class Uniform:
    """Uniform translation: the same velocity ``(u, v, w)`` everywhere."""

    velocity: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _three_finite("velocity", self.velocity)

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        p = _points(positions)
        return np.broadcast_to(np.asarray(self.velocity, float), p.shape).copy()


@dataclass(frozen=True)
class SolidBodyRotation:
    """Rigid rotation ``u = omega x (p - center)``.

    Parameters
    ----------
    omega
        Angular velocity vector ``(wx, wy, wz)`` in radians per unit time; its direction
        is the rotation axis (right-hand rule).
    center
        A point ``(x, y, z)`` on the rotation axis.
    """

    omega: tuple[float, float, float] = (0.0, 0.0, 1.0)
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _three_finite("omega", self.omega)
        _three_finite("center", self.center)

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        r = _points(positions) - np.asarray(self.center, float)
        return np.cross(np.asarray(self.omega, float), r)


@dataclass(frozen=True)
class LambOseen:
    """Lamb-Oseen vortex: ``u_theta(r) = Gamma / (2 pi r) (1 - exp(-r^2 / rc^2))``.

    Parameters
    ----------
    circulation
        Total circulation ``Gamma`` (length^2 / time); positive turns counter-clockwise
        about ``axis``.
    core_radius
        ``rc``; the swirl velocity peaks at ``r = 1.1209 rc``.
    center, axis
        A point on the vortex axis and the axis direction ``(x, y, z)``.
    """

    circulation: float = 1.0
    core_radius: float = 1.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    #: ``r_max / rc`` and ``u_max 2 pi rc / Gamma`` of the Lamb-Oseen profile.
    R_PEAK = 1.1209178
    U_PEAK = 0.6381863

    @classmethod
    def from_peak_velocity(cls, peak_velocity: float, core_radius: float,
                           center=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0)) -> LambOseen:
        """Vortex whose maximum swirl velocity is ``peak_velocity``."""
        gamma = 2.0 * np.pi * core_radius * peak_velocity / cls.U_PEAK
        return cls(gamma, core_radius, tuple(center), tuple(axis))

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        e = _unit(self.axis, "axis")
        d = _points(positions) - np.asarray(self.center, float)
        radial = d - np.outer(d @ e, e)
        r2 = np.einsum("ij,ij->i", radial, radial)
        rc2 = self.core_radius**2
        # u_theta / r, written to stay finite on the axis (limit Gamma / (2 pi rc^2)).
        small = r2 < 1e-12 * rc2
        safe = np.where(small, 1.0, r2)
        factor = np.where(small, 1.0 / rc2, -np.expm1(-r2 / rc2) / safe)
        return self.circulation / (2.0 * np.pi) * factor[:, None] * np.cross(e, radial)

    def vorticity_on_axis(self) -> float:
        """Axial vorticity at the centre, ``Gamma / (pi rc^2)``."""
        return self.circulation / (np.pi * self.core_radius**2)


def musker_profile(y_plus: np.ndarray) -> np.ndarray:
    """Musker (1979) mean velocity ``u+`` from the wall to the log layer (kappa 0.41, B 5.0).

    The additive constant (published as 3.52) is set to 3.51133 so that ``u+(0) = 0``.
    """
    yp = np.maximum(np.asarray(y_plus, dtype=np.float64), 0.0)
    return (5.424 * np.arctan((2.0 * yp - 8.15) / 16.7)
            + np.log10((yp + 10.6) ** 9.6 / (yp**2 - 8.15 * yp + 86.0) ** 2) - 3.51132976630723)


@dataclass
class TurbulentBoundaryLayer:
    """Zero-pressure-gradient turbulent boundary layer with coherent vortical eddies.

    Streamwise ``x``, wall-normal ``y`` (wall at ``wall_y``, fluid at ``y > wall_y``),
    spanwise ``z``. The mean is Musker's inner profile plus Coles' wake,
    ``u+ = u+_Musker(y+) + (Pi / kappa) 2 sin^2(pi y / 2 delta)``, equal to ``u_inf`` at
    and above ``delta``. The fluctuations are the curl of a vector potential made of
    compact, Gaussian-like vortical eddies (a divergence-free synthetic-eddy method,
    after Poletto, Craft & Revell 2013): three sizes (0.32, 0.16, 0.08 delta) attached to
    the wall, stretched streamwise, damped to zero at the wall (``u' ~ y``,
    ``v' ~ y^2``) and scaled so that the streamwise r.m.s. over ``0.1 < y / delta < 0.5``
    is ``intensity * u_inf``. This gives ``u'+`` about 2, ``v'+`` and ``w'+`` about 1 in
    the log region, decaying through the edge. The field is steady (frozen eddies).

    Parameters
    ----------
    u_inf
        Free-stream velocity.
    delta
        Boundary-layer thickness.
    re_tau
        Friction Reynolds number ``delta u_tau / nu``.
    wall_y
        Wall position along ``y``.
    x_range, z_range
        Streamwise and spanwise extents that the eddies fill (default ``(0, 2 delta)``
        and ``(-delta, delta)``); outside them the fluctuations decay to zero.
    intensity
        Streamwise r.m.s. fluctuation over ``u_inf`` in the log and lower wake region.
    pi_wake
        Coles' wake parameter.
    seed
        Seed of the eddy positions, orientations and signs.
    kappa
        von Karman constant of the wake term (0.41, as in Musker's profile).
    """

    u_inf: float = 1.0
    delta: float = 1.0
    re_tau: float = 1000.0
    wall_y: float = 0.0
    x_range: tuple[float, float] | None = None
    z_range: tuple[float, float] | None = None
    intensity: float = 0.07
    pi_wake: float = 0.45
    seed: int | None = 0
    kappa: float = 0.41
    _eddies: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.delta <= 0 or self.re_tau <= 0:
            raise ValueError("delta and re_tau must be positive")
        d = self.delta
        self.x_range = tuple(self.x_range or (0.0, 2.0 * d))
        self.z_range = tuple(self.z_range or (-d, d))
        self._eddies = self._seed_eddies(np.random.default_rng(self.seed))
        self._calibrate(np.random.default_rng(None if self.seed is None else self.seed + 1))

    @property
    def u_tau(self) -> float:
        """Friction velocity, from ``u_inf = u_tau (u+_Musker(Re_tau) + 2 Pi / kappa)``."""
        edge = musker_profile(self.re_tau) + 2.0 * self.pi_wake / self.kappa
        return self.u_inf / float(edge)

    @property
    def nu(self) -> float:
        """Kinematic viscosity implied by ``re_tau``."""
        return self.delta * self.u_tau / self.re_tau

    def mean_velocity(self, y: np.ndarray) -> np.ndarray:
        """Mean streamwise velocity at wall-normal positions ``y``."""
        eta = np.clip((np.asarray(y, float) - self.wall_y) / self.delta, 0.0, 1.0)
        wake = 2.0 * self.pi_wake / self.kappa * np.sin(0.5 * np.pi * eta) ** 2
        return self.u_tau * (musker_profile(eta * self.re_tau) + wake)

    def fluctuation(self, positions: np.ndarray) -> np.ndarray:
        """Divergence-free velocity fluctuation at ``positions`` ``(N, 3)``."""
        from scipy.spatial import cKDTree

        p = _points(positions)
        psi = np.zeros_like(p)       # vector potential (before wall damping)
        curl = np.zeros_like(p)      # curl of psi
        tree = cKDTree(p / _STRETCH)
        for centres, axes, amps, size in self._eddies:
            _add_eddies(tree, centres, axes, amps, size, psi, curl)
        yd = 0.07 * self.delta
        h = np.maximum(p[:, 1] - self.wall_y, 0.0) / yd
        damp = -np.expm1(-h**2)
        ddamp = 2.0 * h / yd * np.exp(-h**2)
        # curl(f psi) = grad f x psi + f curl psi, with grad f = (0, f', 0)
        grad_f = np.zeros_like(p)
        grad_f[:, 1] = ddamp
        return np.cross(grad_f, psi) + damp[:, None] * curl

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        p = _points(positions)
        out = self.fluctuation(p)
        out[:, 0] += self.mean_velocity(p[:, 1])
        out[p[:, 1] <= self.wall_y] = 0.0
        return out

    def _seed_eddies(self, rng: np.random.Generator) -> list:
        d = self.delta
        eddies = []
        for level, size in enumerate(d * np.array([0.32, 0.16, 0.08])):
            top = min(1.2 * d, 10.0 * size)
            reach = 2.5 * size * _STRETCH
            lo = np.array([self.x_range[0] - reach[0], 0.5 * size, self.z_range[0] - reach[2]])
            hi = np.array([self.x_range[1] + reach[0], top, self.z_range[1] + reach[2]])
            n = max(1, int(0.4 * np.prod(hi - lo) / (size**3 * np.prod(_STRETCH))))
            centres = lo + rng.random((n, 3)) * (hi - lo)
            centres[:, 1] += self.wall_y
            axes = rng.normal(size=(n, 3)) * [0.5, 1.0, 1.0]   # mostly spanwise/normal
            axes /= np.linalg.norm(axes, axis=1, keepdims=True)
            taper = np.clip(1.0 - ((centres[:, 1] - self.wall_y) / (1.2 * d)) ** 2, 0.0, 1.0)
            amps = rng.choice([-1.0, 1.0], n) * size * taper * 0.7**level
            eddies.append((centres, axes, amps, size))
        return eddies

    def _calibrate(self, rng: np.random.Generator) -> None:
        lo = np.array([self.x_range[0], self.wall_y + 0.1 * self.delta, self.z_range[0]])
        hi = np.array([self.x_range[1], self.wall_y + 0.5 * self.delta, self.z_range[1]])
        sample = lo + rng.random((4000, 3)) * (hi - lo)
        rms = float(np.sqrt(np.mean(self.fluctuation(sample)[:, 0] ** 2)))
        scale = self.intensity * self.u_inf / rms if rms > 0 else 0.0
        self._eddies = [(c, a, amps * scale, s) for c, a, amps, s in self._eddies]


#: Eddy elongation ``(x, y, z)``: streamwise-stretched eddies whose axes lean to the
#: spanwise and wall-normal directions make ``u'`` the largest fluctuation (about twice
#: ``v'`` and ``w'``), as in a boundary layer.
_STRETCH = np.array([2.0, 1.0, 1.0])


def _add_eddies(tree, centres: np.ndarray, axes: np.ndarray, amps: np.ndarray,
                size: float, psi: np.ndarray, curl: np.ndarray) -> None:
    """Accumulate ``psi = sum a e phi`` and ``curl psi = sum a grad(phi) x e``.

    ``phi = (1 - q^2)^4`` for ``q = |(p - c) / stretch| / R < 1``, ``R = 2.5 size``
    (Gaussian-like, width about ``size`` times the stretch), has compact support and
    continuous second derivatives, so the velocity and its gradient are continuous where
    an eddy ends. ``tree`` is a ``cKDTree`` of the points divided by the stretch.
    """
    from scipy.spatial import cKDTree

    radius = 2.5 * size
    scaled = centres / _STRETCH
    pairs = tree.sparse_distance_matrix(cKDTree(scaled), radius, output_type="ndarray")
    if pairs.size == 0:
        return
    i, k = pairs["i"], pairs["j"]
    rel = tree.data[i] - scaled[k]
    bump = np.clip(1.0 - (pairs["v"] / radius) ** 2, 0.0, None)
    phi = bump**4 * amps[k]
    grad = (-8.0 / radius**2 * bump**3 * amps[k])[:, None] * (rel / _STRETCH)
    for c in range(3):
        psi[:, c] += np.bincount(i, axes[k, c] * phi, minlength=len(psi))
    cross = np.cross(grad, axes[k])
    for c in range(3):
        curl[:, c] += np.bincount(i, cross[:, c], minlength=len(psi))


def displace(positions: np.ndarray, flow: Flow, dt: float, steps: int = 4) -> np.ndarray:
    """Move points along a steady flow for a time ``dt`` (classical RK4, ``steps`` sub-steps).

    Parameters
    ----------
    positions
        ``(N, 3)`` start points ``(x, y, z)``.
    flow
        Callable ``(N, 3) -> (N, 3)`` velocity.
    dt
        Time interval; negative moves the points backwards.
    steps
        Number of RK4 sub-steps.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` end points.
    """
    p = _points(positions).copy()
    h = float(dt) / max(int(steps), 1)
    for _ in range(max(int(steps), 1)):
        k1 = flow(p)
        k2 = flow(p + 0.5 * h * k1)
        k3 = flow(p + 0.5 * h * k2)
        k4 = flow(p + h * k3)
        p += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return p


def centred_displacement(points: np.ndarray, flow: Flow, dt: float, steps: int = 4) -> np.ndarray:
    """Displacement over ``dt`` of the particle that is at ``points`` at mid-time.

    This is the reference for symmetric (central-difference) PIV:
    ``displace(p, +dt/2) - displace(p, -dt/2)``.
    """
    p = _points(points)
    return displace(p, flow, 0.5 * dt, steps) - displace(p, flow, -0.5 * dt, steps)


def _axis_weights(coord: np.ndarray, n: int, sigma: float, half: int):
    """Per-particle 1-D voxel indices ``(N, K)`` and erf-integrated Gaussian weights."""
    base = np.rint(coord).astype(np.int64)
    idx = base[:, None] + np.arange(-half, half + 1)
    s = np.sqrt(2.0) * sigma
    w = 0.5 * (erf((idx + 0.5 - coord[:, None]) / s) - erf((idx - 0.5 - coord[:, None]) / s))
    inside = (idx >= 0) & (idx < n)
    return np.clip(idx, 0, n - 1), np.where(inside, w, 0.0)


def render_particles(shape: tuple[int, int, int], positions: np.ndarray,
                     intensities: np.ndarray | float = 1.0, sigma: float = 1.0) -> np.ndarray:
    """Render Gaussian particles into a float32 volume ``vol[iz, iy, ix]``.

    Each particle is a 3-D Gaussian of standard deviation ``sigma`` (voxels) integrated
    exactly over every voxel (a product of ``erf`` differences), scaled so that a
    particle's peak density equals its intensity; its integral is
    ``intensity (2 pi sigma^2)^(3/2)``. Positions are voxel-index coordinates ``(x, y, z)``
    (index ``i`` is the centre of voxel ``i``).
    """
    p = _points(positions)
    if sigma <= 0:
        raise ValueError(f"sigma must be positive (voxels), got {sigma}")
    amp = np.broadcast_to(np.asarray(intensities, float), (len(p),)) * (2 * np.pi * sigma**2) ** 1.5
    half = int(np.ceil(4.0 * sigma))
    flat = np.zeros(int(np.prod(shape)), dtype=np.float64)
    nz, ny, nx = shape
    for start in range(0, len(p), 4096):
        sl = slice(start, start + 4096)
        ix, wx = _axis_weights(p[sl, 0], nx, sigma, half)
        iy, wy = _axis_weights(p[sl, 1], ny, sigma, half)
        iz, wz = _axis_weights(p[sl, 2], nz, sigma, half)
        weight = (amp[sl, None, None, None] * wz[:, :, None, None] * wy[:, None, :, None]
                  * wx[:, None, None, :])
        index = (iz[:, :, None, None] * ny + iy[:, None, :, None]) * nx + ix[:, None, None, :]
        flat += np.bincount(index.ravel(), weight.ravel(), minlength=flat.size)
    return flat.reshape(shape).astype(np.float32)


class VolumePair(NamedTuple):
    """Two rendered volumes and the particle positions ``(x, y, z)`` (voxels) in each."""

    vol_a: np.ndarray
    vol_b: np.ndarray
    pos_a: np.ndarray
    pos_b: np.ndarray
    intensities: np.ndarray


def _seed_box(shape, flow: Flow, dt: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Seeding box (voxel units) that also feeds particles flowing in through the faces."""
    nz, ny, nx = shape
    probe = np.stack(np.meshgrid(*(np.linspace(-0.5, n - 0.5, 9) for n in (nx, ny, nz)),
                                 indexing="ij"), axis=-1).reshape(-1, 3)
    reach = float(np.max(np.abs(flow(probe)))) * abs(dt) * 0.75 + 4.0 * sigma + 1.0
    lo = np.full(3, -0.5 - reach)
    hi = np.array([nx, ny, nz], float) - 0.5 + reach
    return lo, hi


def volume_pair(shape: tuple[int, int, int], flow_in_voxels: Flow, density: float = 0.004,
                sigma: float = 1.0, seed: int | None = None, dt: float = 1.0,
                intensity_range: tuple[float, float] = (0.5, 1.0),
                noise: float = 0.0) -> VolumePair:
    """Render a particle volume pair with known displacement.

    Particles are seeded uniformly at mid time (also in a margin around the volume, so
    that particles enter and leave through the faces), moved by ``-dt/2`` and ``+dt/2``
    with :func:`displace`, and rendered with :func:`render_particles`.

    Parameters
    ----------
    shape
        ``(nz, ny, nx)`` of the volumes.
    flow_in_voxels
        Flow callable whose positions and velocities are in voxel-index units
        (``(x, y, z)``, voxels per unit time).
    density
        Particles per voxel.
    sigma
        Particle-image standard deviation in voxels.
    seed
        Random seed (positions, intensities, noise).
    dt
        Time between the two volumes.
    intensity_range
        Particle peak intensities are uniform in this range (identical in both volumes).
    noise
        Standard deviation of additive Gaussian noise (independent per volume).

    Returns
    -------
    VolumePair
        ``(vol_a, vol_b, pos_a, pos_b, intensities)``; volumes are float32
        ``vol[iz, iy, ix]``, positions ``(N, 3)`` as ``(x, y, z)`` in voxel units.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"shape must be three positive integers (nz, ny, nx), got {shape}")
    if density <= 0:
        raise ValueError(f"density must be positive (particles per voxel), got {density}")
    rng = np.random.default_rng(seed)
    lo, hi = _seed_box(shape, flow_in_voxels, dt, sigma)
    count = rng.poisson(density * float(np.prod(hi - lo)))
    mid = lo + rng.random((count, 3)) * (hi - lo)
    intensities = rng.uniform(*intensity_range, size=count)
    pos_a = displace(mid, flow_in_voxels, -0.5 * dt)
    pos_b = displace(mid, flow_in_voxels, 0.5 * dt)
    vols = [render_particles(shape, p, intensities, sigma) for p in (pos_a, pos_b)]
    if noise > 0:
        vols = [(v + rng.normal(0.0, noise, v.shape)).astype(np.float32) for v in vols]
    return VolumePair(vols[0], vols[1], pos_a, pos_b, intensities)
