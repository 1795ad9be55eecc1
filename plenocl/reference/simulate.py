"""NumPy reference of the ray-tracing simulator (``kernels/simulate.cl``).

It uses the same counter-based random words as the kernel, so for one seed both
trace the same rays; only float32 rounding in the kernel can move a ray that lands
within rounding of a pixel or microlens edge.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera

_M1, _M2 = np.uint32(0x7FEB352D), np.uint32(0x846CA68B)


def _hash(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.uint32)
    x = x ^ (x >> np.uint32(16))
    x = x * _M1
    x = x ^ (x >> np.uint32(15))
    x = x * _M2
    return x ^ (x >> np.uint32(16))


def random_words(seed: int, src, ray, k: int) -> np.ndarray:
    """Random word ``k`` of ray ``ray`` of source ``src`` (``kernels/common.h``:
    ``pl_word(pl_ray_key(pl_source_key(seed, src), ray), k)``)."""
    with np.errstate(over="ignore"):
        h = _hash(np.uint32(seed) ^ np.uint32(0x9E3779B9))
        h = _hash(h ^ np.asarray(src, np.uint32))
        h = _hash(h ^ np.asarray(ray, np.uint32))
        return _hash(h ^ np.uint32(k))


def _uniform(word: np.ndarray) -> np.ndarray:
    return (word >> np.uint32(8)).astype(np.float64) / 16777216.0


def _gauss_pair(seed, src, ray) -> tuple[np.ndarray, np.ndarray]:
    """Box-Muller normal pair from random words 3 and 4."""
    r = np.sqrt(-2.0 * np.log(1.0 - _uniform(random_words(seed, src, ray, 3))))
    t = 2 * np.pi * _uniform(random_words(seed, src, ray, 4))
    return r * np.cos(t), r * np.sin(t)


def _lens_lookup(cam: Camera, x: np.ndarray, y: np.ndarray):
    """Microlens ``(kx, ky)`` containing array-plane points, and an inside mask."""
    c, s = np.cos(np.radians(cam.ml_rotation_deg)), np.sin(np.radians(cam.ml_rotation_deg))
    dx, dy = x - cam.ml_offset_mm[0], y - cam.ml_offset_mm[1]
    a, b = c * dx + s * dy, -s * dx + c * dy
    nx, ny = cam.ml_count
    kx, ky = _layout_rules(cam)[0](cam, a, b)
    inside = (kx >= 0) & (ky >= 0) & (kx < nx) & (ky < ny)
    return np.clip(kx, 0, nx - 1), np.clip(ky, 0, ny - 1), inside


def _layout_rules(cam: Camera):
    """The simulate kernel's two layouts (``pl_lens_index`` and ``pl_cell_point`` in
    kernels/common.h and kernels/simulate.cl): which lens holds an array-frame point, and
    a cell's uniform points."""
    if cam.layout.hexagonal:
        return _nearest_hexagonal, _hexagon
    return _rectangular_cell, _rectangle


def _rectangular_cell(cam: Camera, a: np.ndarray, b: np.ndarray):
    """Lens ``(kx, ky)`` of a rectangular array whose pitch-square cell holds ``(a, b)``."""
    nx, ny = cam.ml_count
    return (np.floor(a / cam.ml_pitch_mm + nx / 2).astype(np.int64),
            np.floor(b / cam.ml_pitch_mm + ny / 2).astype(np.int64))


def _nearest_hexagonal(cam: Camera, a: np.ndarray, b: np.ndarray):
    """Lens ``(kx, ky)`` of a hexagonal array whose centre is nearest to array-frame points
    ``(a, b)``: the nearer of the nearest centres in the two rows around each point."""
    nx, ny = cam.ml_count
    fy = b / cam.ml_row_pitch_mm + (ny - 1) / 2

    def nearest_in_row(r):
        fx = a / cam.ml_pitch_mm + (nx - 1) / 2 - cam.odd_row_shift * (r % 2)
        k = np.floor(fx + 0.5)
        return k, ((fx - k) * cam.ml_pitch_mm) ** 2 + ((fy - r) * cam.ml_row_pitch_mm) ** 2

    below, above = np.floor(fy), np.floor(fy) + 1
    (k0, d0), (k1, d1) = nearest_in_row(below), nearest_in_row(above)
    upper = d1 < d0  # ties stay in the lower row, as the kernel's strict comparison does
    return (np.where(upper, k1, k0).astype(np.int64),
            np.where(upper, above, below).astype(np.int64))


def _cell_points(cam: Camera, u1: np.ndarray, u2: np.ndarray):
    """Uniform points of a lens's cell (array frame, from its centre) from uniform numbers:
    the pitch x row rectangle, for a hexagonal array its four corners outside the hexagon
    folded into the tips (``pl_cell_point`` in kernels/simulate.cl)."""
    a, b = (u1 - 0.5) * cam.ml_pitch_mm, (u2 - 0.5) * cam.ml_row_pitch_mm
    return _layout_rules(cam)[1](cam, a, b)


def _rectangle(cam: Camera, a: np.ndarray, b: np.ndarray):
    """A rectangular array's cell is the rectangle itself."""
    return a, b


def _hexagon(cam: Camera, a: np.ndarray, b: np.ndarray):
    """The rectangle's four corners outside the (pointy-top) hexagon folded into its tips."""
    outside = np.abs(b) > (cam.ml_pitch_mm - np.abs(a)) / np.sqrt(3)
    a = np.where(outside, np.copysign(cam.ml_pitch_mm / 2, a) - a, a)
    b = np.where(outside, np.copysign(cam.ml_row_pitch_mm, b) - b, b)
    return a, b


def _deposit(cam: Camera, sx, sy, weight, keep) -> np.ndarray:
    """Sum ``weight`` of the kept rays landing at sensor points into an image."""
    w, h = cam.pixels
    edge_col, edge_row = cam.sensor_edge_px  # the axis from the first pixel's outer edge
    col = np.floor(sx / cam.pixel_pitch_mm + edge_col).astype(np.int64)
    row = np.floor(sy / cam.pixel_pitch_mm + edge_row).astype(np.int64)
    keep = keep & (col >= 0) & (row >= 0) & (col < w) & (row < h)
    image = np.zeros(w * h)
    np.add.at(image, row[keep] * w + col[keep], np.broadcast_to(weight, keep.shape)[keep])
    return image.reshape(h, w)


def _transmitted(seed, src, ray, kx, ky, inside, transmission):
    """Rays surviving the per-lens transmission (rejection with random word 2)."""
    if transmission is None:
        return inside
    t = np.asarray(transmission, float)[ky, kx]
    return inside & ((t >= 1.0) | (_uniform(random_words(seed, src, ray, 2)) < t))


def _centres(cam: Camera, lens_shift_mm) -> np.ndarray:
    """Physical lens centres ``(rows, cols, 2)`` mm: lattice nodes plus any displacement."""
    pos = cam.microlens_positions_mm()
    return pos if lens_shift_mm is None else pos + np.asarray(lens_shift_mm, float)


def trace_particles(cam: Camera, positions, intensities, rays_per_particle: int, seed: int,
                    blur_px: float = 0.0, lens_transmission=None,
                    lens_shift_mm=None) -> np.ndarray:
    """Noise-free raw image of point particles, traced ray by ray (docs/design.md §2, §8).

    Each ray leaves the particle, crosses a uniformly sampled point ``(u, v)`` of the
    circular aperture, passes the image point ``X'`` and meets the array plane at
    ``x = u + (X' - u) d / d'`` (``d``, ``d'``: the array's and the image point's
    distances from the exit pupil, :meth:`plenocl.Camera.image_points`; a thin lens: ``s_i``,
    ``s_i'``); the microlens ``k`` it enters sends it to ``x_k + f_ml (X' - u) / d'`` on
    the sensor. Each ray carries ``I / rays``.
    """
    img_pts = cam.image_points(positions)
    intens = np.broadcast_to(np.asarray(intensities, float), (len(img_pts),))
    src, ray = np.meshgrid(np.arange(len(img_pts)), np.arange(rays_per_particle), indexing="ij")
    radius = cam.exit_pupil_diameter_mm / 2 * np.sqrt(_uniform(random_words(seed, src, ray, 0)))
    theta = 2 * np.pi * _uniform(random_words(seed, src, ray, 1))
    u, v = radius * np.cos(theta), radius * np.sin(theta)
    xp, yp, sip = (img_pts[:, k, None] for k in range(3))
    x = u + (xp - u) * cam.exit_pupil_distance_mm / sip
    y = v + (yp - v) * cam.exit_pupil_distance_mm / sip
    kx, ky, inside = _lens_lookup(cam, x, y)
    keep = _transmitted(seed, src, ray, kx, ky, inside, lens_transmission)
    centres = _centres(cam, lens_shift_mm)[ky, kx]
    sx = centres[..., 0] + cam.ml_focal_length_mm * (xp - u) / sip
    sy = centres[..., 1] + cam.ml_focal_length_mm * (yp - v) / sip
    if blur_px > 0:
        gx, gy = _gauss_pair(seed, src, ray)
        sx, sy = sx + gx * blur_px * cam.pixel_pitch_mm, sy + gy * blur_px * cam.pixel_pitch_mm
    return _deposit(cam, sx, sy, (intens / rays_per_particle)[:, None], keep)


def trace_white(cam: Camera, stop_f_number: float, rays_per_lens: int, seed: int,
                intensity: float = 1.0, blur_px: float = 0.0, lens_transmission=None,
                lens_shift_mm=None) -> np.ndarray:
    """Noise-free white (calibration) image with the aperture stopped down.

    A uniform white field lights every point of each microlens; rays come from a
    uniformly sampled point of the stopped-down aperture (diameter ``f / N_stop``)
    and reach the sensor at ``x_k + f_ml (x - u) / d``. Each lens receives
    ``intensity`` in total (times its transmission).
    """
    nx, ny = cam.ml_count
    src, ray = np.meshgrid(np.arange(nx * ny), np.arange(rays_per_lens), indexing="ij")
    kx, ky = src % nx, src // nx
    centres = _centres(cam, lens_shift_mm)[ky, kx]
    a, b = _cell_points(cam, _uniform(random_words(seed, src, ray, 5)),
                        _uniform(random_words(seed, src, ray, 6)))
    c, s = np.cos(np.radians(cam.ml_rotation_deg)), np.sin(np.radians(cam.ml_rotation_deg))
    x, y = centres[..., 0] + c * a - s * b, centres[..., 1] + s * a + c * b
    radius = cam.exit_pupil_diameter_at(stop_f_number) / 2 * np.sqrt(
        _uniform(random_words(seed, src, ray, 0)))
    theta = 2 * np.pi * _uniform(random_words(seed, src, ray, 1))
    u, v = radius * np.cos(theta), radius * np.sin(theta)
    keep = _transmitted(seed, src, ray, kx, ky, np.ones_like(kx, bool), lens_transmission)
    sx = centres[..., 0] + cam.ml_focal_length_mm * (x - u) / cam.exit_pupil_distance_mm
    sy = centres[..., 1] + cam.ml_focal_length_mm * (y - v) / cam.exit_pupil_distance_mm
    if blur_px > 0:
        gx, gy = _gauss_pair(seed, src, ray)
        sx, sy = sx + gx * blur_px * cam.pixel_pitch_mm, sy + gy * blur_px * cam.pixel_pitch_mm
    return _deposit(cam, sx, sy, intensity / rays_per_lens, keep)
