"""Shared test helpers: the test cameras and the checks many tests make."""

from __future__ import annotations

import numpy as np
import tolerances as tol

from plenocl import Camera

#: The test cameras' optics: M = 1, f/2 main lens (f = 50 mm), 0.125 mm microlenses with
#: f = 0.5 mm (matched to f/2), 7.4 µm pixels: about 17 pixels per microlens.
OPTICS = dict(focal_length_mm=50.0, f_number=2.0, magnification=1.0, ml_pitch_mm=0.125,
              ml_focal_length_mm=0.5, pixel_pitch_mm=0.0074)


def lens_camera(cols: int = 12, rows: int = 10, pixels: tuple[int, int] | None = None,
                **changes) -> Camera:
    """A test camera of ``cols x rows`` microlenses on ``17 cols x 17 rows`` pixels (or
    ``pixels``), with :data:`OPTICS` and any field of :class:`plenocl.Camera` changed by
    keyword (``ml_rotation_deg=2.0``, ``ml_offset_mm=...``, ``pixel_pitch_mm=...``)."""
    fields = {**OPTICS, "ml_count": (cols, rows),
              "pixels": pixels or (17 * cols, 17 * rows), **changes}
    return Camera(**fields)


#: The rotated camera of the projector tests: the 12 x 10 camera's array turned by 2
#: degrees and moved off the axis (general projector path on a sensor-axis grid).
ROTATED = dict(ml_rotation_deg=2.0, ml_offset_mm=(0.01, -0.02))


def assert_close_to_peak(actual, expected, rtol: float, what: object = "") -> None:
    """``max |actual - expected| <= rtol max |expected|``: float32 kernels against float64
    references, relative to the signal's peak."""
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    err, peak = np.abs(actual - expected).max(), np.abs(expected).max()
    assert err <= rtol * peak, f"{what}: max difference {err:.3g} > {rtol:g} x peak {peak:.3g}"


def assert_adjoint(proj, seed: int = 7, rtol: float = tol.ADJOINT) -> None:
    """``<A x, y> = <x, Aᵀ y>`` for random ``x``, ``y``, within ``rtol`` of the sum of the
    absolute terms ``<A |x|, |y|>``."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(proj.grid.shape).astype(np.float32)
    y = rng.standard_normal(proj.image_shape).astype(np.float32)
    lhs = np.dot(proj.forward(x).ravel().astype(np.float64), y.ravel())
    rhs = np.dot(x.ravel().astype(np.float64), proj.back(y).ravel())
    scale = np.dot(np.abs(proj.forward(np.abs(x))).ravel(), np.abs(y).ravel())
    assert abs(lhs - rhs) <= rtol * scale, (lhs, rhs, scale)


def traced_fit_scene(camera, voxel: np.ndarray, count: int, seed: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """An image fit's test scene: ``count`` particles (positions from ``seed``) ray traced
    with 0.8 px blur on a dark level of 20 with unit read noise (image seed ``seed + 2``),
    and start positions off by (0.3, -0.3, 1.5) voxels ``voxel`` (x, y, z mm)."""
    from plenocl.reference.simulate import trace_particles

    rng = np.random.default_rng(seed)
    true = np.column_stack([rng.uniform(-1.5, 1.5, count), rng.uniform(-1.2, 1.2, count),
                            rng.uniform(-8.0, 8.0, count)])
    img = trace_particles(camera, true, 4000.0, 40_000, seed=seed + 2, blur_px=0.8)
    img = img + 20.0 + np.random.default_rng(seed + 2).normal(0.0, 1.0, img.shape)
    return true + np.array([0.3, -0.3, 1.5]) * voxel, img


def vendor_white_image(cam: Camera, queue) -> np.ndarray:
    """A vendor-style white image of ``cam``: at the main lens's own f-number (each
    micro-image a disk filling its lens), photon and read noise, 12-bit, and a 50 %
    vignetting falloff across the sensor (each disk brighter on the side toward the
    centre)."""
    from plenocl.simulate import simulate_white_image

    white = simulate_white_image(cam, stop_f_number=cam.f_number, photon_noise=True,
                                 read_noise=3.0, bit_depth=12, intensity=1e5,
                                 rays_per_lens=50000, seed=18, queue=queue).astype(float)
    rows, cols = np.mgrid[0:white.shape[0], 0:white.shape[1]]
    r2 = (cols - white.shape[1] / 2) ** 2 + (rows - white.shape[0] / 2) ** 2
    return white * (1.0 - 0.5 * r2 / r2.max())
