"""Plenoptic image simulator on OpenCL (docs/design.md §8); NumPy twin in ``reference.simulate``.

Rays are traced exactly through the thin main lens and the microlens each ray
enters. Random numbers are counter-based (a hash of seed, source and ray), so a
seed gives the same rays on every device. Accumulation is in 64-bit fixed point
where the device has 64-bit atomics: the image is then bit-for-bit repeatable.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator

import numpy as np
import pyopencl.array as cl_array

from ..camera import Camera
from ..opencl.device import DeviceLike, device_info, get_queue
from ..opencl.program import KernelSet
from ..optics.depthrange import in_field_of_view
from .sensor import SensorModel

#: Rays one work-item traces; the rest of the parallelism is over sources.
RAYS_PER_ITEM = 128
#: Work-items per launch; bounds device memory and launch size for any particle count.
MAX_ITEMS_PER_LAUNCH = 1 << 22


def _validate_particles(camera: Camera, positions, intensities) -> tuple[np.ndarray, np.ndarray]:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be an (N, 3) array of (x, y, z) mm, got {pos.shape}")
    intens = np.asarray(intensities, dtype=np.float64)
    if intens.ndim > 1 or intens.size not in (1, len(pos)):
        raise ValueError(f"intensities must be one number or one per particle ({len(pos)}), "
                         f"got shape {intens.shape}")
    intens = np.broadcast_to(intens, (len(pos),)).copy()
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(intens))):
        raise ValueError("positions and intensities must be finite (found NaN or Inf)")
    if np.any(intens < 0):
        raise ValueError("intensities must be >= 0 (counts per particle)")
    camera.image_points(pos)  # raises for depths (in the camera's frame) with no real image
    return pos, intens


def _validate_common(seed: int, blur_px: float) -> None:
    if int(seed) != seed or not 0 <= seed < 2**32:
        raise ValueError(f"seed must be an integer in [0, 2**32), got {seed!r}")
    if not (np.isfinite(blur_px) and blur_px >= 0):
        raise ValueError(f"blur_px must be a finite number >= 0 (pixels), got {blur_px!r}")


def _validate_rays(rays: int) -> int:
    if int(rays) != rays or rays < 1 or rays >= 2**31:
        raise ValueError(f"rays must be a positive integer below 2**31, got {rays}")
    return int(rays)


def _lens_shift(camera: Camera, shift) -> np.ndarray:
    """Per-lens displacement ``(rows * cols, 2)`` float32 mm on the array plane, checked."""
    cols, rows = camera.ml_count
    if shift is None:
        return np.zeros((rows * cols, 2), np.float32)
    d = np.asarray(shift, dtype=np.float64)
    if d.shape != (rows, cols, 2) or not np.all(np.isfinite(d)):
        raise ValueError(f"lens_shift_mm must be a finite ({rows}, {cols}, 2) array of (x, y) "
                         "displacements in mm (rows, columns of the microlens array)")
    if np.abs(d).max() > 0.25 * camera.ml_pitch_mm:
        raise ValueError(f"lens_shift_mm moves a lens by {np.abs(d).max():.4g} mm, more than a "
                         f"quarter of the {camera.ml_pitch_mm} mm pitch; the simulator models "
                         "small manufacturing errors only")
    return np.ascontiguousarray(d.reshape(-1, 2), dtype=np.float32)


def _lens_gain(camera: Camera, gain) -> np.ndarray:
    cols, rows = camera.ml_count
    if gain is None:
        return np.ones(rows * cols, np.float32)
    g = np.asarray(gain, dtype=np.float32)
    if g.shape != (rows, cols) or not np.all(np.isfinite(g)) or g.min() < 0 or g.max() > 1:
        raise ValueError(f"lens_transmission must be a ({rows}, {cols}) array of values in "
                         "[0, 1] (rows, columns of the microlens array)")
    return np.ascontiguousarray(g.ravel())


class Simulator:
    """Ray-tracing simulator for one camera on one OpenCL queue.

    Parameters
    ----------
    camera
        The camera; its physical array layout (rotation, offset) is traced.
    queue
        An OpenCL queue, context, device or device-name substring (see
        :func:`plenocl.opencl.device.get_queue`); ``None`` picks one.
    """

    def __init__(self, camera: Camera, queue: DeviceLike = None) -> None:
        self.camera = camera
        self.queue = get_queue(queue)
        self.int64 = device_info(self.queue).int64_atomics
        opts = ["-DPL_INT64_ATOMICS"] if self.int64 else []
        # each work-item traces a block of rays: on a CPU, one item per work-group, or PoCL
        # may run the whole launch as one work-group (one thread)
        kernels = ["trace_particles", "trace_white"]
        self._k = KernelSet(self.queue, "simulate.cl", kernels, opts, looping=kernels)
        self._acc = np.int64 if self.int64 else np.float32

    # ---- shared launch plumbing ---------------------------------------------------------
    def _geometry_args(self) -> list:
        cam = self.camera
        t = math.radians(cam.ml_rotation_deg)
        return [np.float32(cam.ml_pitch_mm), np.float32(math.cos(t)), np.float32(math.sin(t)),
                np.float32(cam.ml_offset_mm[0]), np.float32(cam.ml_offset_mm[1]),
                np.int32(cam.ml_count[0]), np.int32(cam.ml_count[1]),
                np.float32(cam.ml_row_pitch_mm), np.float32(cam.odd_row_shift),
                np.float32(cam.pixel_pitch_mm), *cam.sensor_edge_px.astype(np.float32),
                np.int32(cam.pixels[0]), np.int32(cam.pixels[1])]

    def _quanta(self, per_ray: np.ndarray, total: float) -> tuple[np.ndarray, float]:
        """Per-ray contributions in the accumulator's units, and the scale back to counts."""
        if not self.int64:
            return per_ray.astype(np.float32), 1.0
        scale = 2.0 ** min(40, math.floor(math.log2(2.0**62 / max(total, 1e-30))))
        return np.rint(per_ray * scale).astype(np.int64), scale

    def _new_image(self) -> cl_array.Array:
        w, h = self.camera.pixels
        return cl_array.zeros(self.queue, (h, w), self._acc)

    @staticmethod
    def _read_image(image: cl_array.Array, scale: float) -> np.ndarray:
        return (image.get().astype(np.float64) / scale).astype(np.float32)

    @staticmethod
    def _chunks(n_sources: int, rays: int):
        blocks = -(-rays // RAYS_PER_ITEM)
        per_launch = max(1, MAX_ITEMS_PER_LAUNCH // blocks)
        for start in range(0, n_sources, per_launch):
            yield start, min(per_launch, n_sources - start), blocks

    # ---- public --------------------------------------------------------------------------
    def trace(self, positions, intensities, rays_per_particle: int = 1000, seed: int = 0,
              blur_px: float = 0.0, lens_transmission=None, lens_shift_mm=None) -> np.ndarray:
        """Noise-free image (counts, float32) of point particles; see :func:`simulate_image`."""
        cam = self.camera
        pos, intens = _validate_particles(cam, positions, intensities)
        rays = _validate_rays(rays_per_particle)
        _validate_common(seed, blur_px)
        img_pts = np.zeros((len(pos), 4), np.float32)
        if len(pos):
            img_pts[:, :3] = cam.image_points(pos)
        quanta, scale = self._quanta(intens / rays, float(intens.sum()))
        gain = self._k.to_device(_lens_gain(cam, lens_transmission))
        shift = self._k.to_device(_lens_shift(cam, lens_shift_mm))
        image = self._new_image()
        for start, n, blocks in self._chunks(len(pos), rays):
            pts = self._k.to_device(img_pts[start:start + n])
            q = self._k.to_device(quanta[start:start + n])
            self._k.launch(
                "trace_particles", (blocks, n), pts, q, gain, shift, image,
                np.uint32(seed), np.uint32(start), np.uint32(rays), np.uint32(RAYS_PER_ITEM),
                np.float32(cam.exit_pupil_diameter_mm / 2), np.float32(cam.exit_pupil_distance_mm),
                np.float32(cam.ml_focal_length_mm),
                np.float32(blur_px * cam.pixel_pitch_mm), *self._geometry_args())
        return self._read_image(image, scale)

    def trace_white(self, stop_f_number: float = 16.0, rays_per_lens: int = 2000,
                    intensity: float = 1000.0, seed: int = 0, blur_px: float = 0.8,
                    lens_transmission=None, lens_shift_mm=None) -> np.ndarray:
        """Noise-free white image; see :func:`simulate_white_image`."""
        cam = self.camera
        rays = _validate_rays(rays_per_lens)
        _validate_common(seed, blur_px)
        if not (np.isfinite(intensity) and intensity >= 0):
            raise ValueError(f"intensity must be a finite number >= 0 (counts per lens), "
                             f"got {intensity!r}")
        if not (np.isfinite(stop_f_number) and stop_f_number >= cam.f_number):
            raise ValueError(f"stop_f_number must be >= the lens f-number {cam.f_number:g} "
                             "(the calibration image is taken with the aperture stopped down)")
        n_lens = cam.ml_count[0] * cam.ml_count[1]
        quantum, scale = self._quanta(np.array([intensity / rays]), intensity * n_lens)
        gain = self._k.to_device(_lens_gain(cam, lens_transmission))
        shift = self._k.to_device(_lens_shift(cam, lens_shift_mm))
        image = self._new_image()
        for start, n, blocks in self._chunks(n_lens, rays):
            self._k.launch(
                "trace_white", (blocks, n), gain, shift, image, quantum[0],
                np.uint32(seed), np.uint32(start), np.uint32(rays), np.uint32(RAYS_PER_ITEM),
                np.float32(cam.exit_pupil_diameter_at(stop_f_number) / 2),
                np.float32(cam.exit_pupil_distance_mm), np.float32(cam.ml_focal_length_mm),
                np.float32(blur_px * cam.pixel_pitch_mm), *self._geometry_args())
        return self._read_image(image, scale)


def simulate_image(camera: Camera, positions, intensities, rays_per_particle: int = 1000,
                   seed: int = 0, *, blur_px: float = 0.0, background: float = 0.0,
                   photon_noise: bool = False, read_noise: float = 0.0,
                   electrons_per_count: float = 1.0, bit_depth: int | None = None,
                   saturation: float | None = None, lens_transmission=None,
                   lens_shift_mm=None, queue: DeviceLike = None) -> np.ndarray:
    """Simulate the raw plenoptic image of point particles.

    Parameters
    ----------
    camera
        The camera (its physical microlens layout is traced).
    positions
        ``(N, 3)`` particle positions ``(x, y, z)`` in mm (object space, docs/design.md §1),
        in the world's frame: a posed camera (``camera.pose``) sees each at
        ``pose.to_camera(position)`` (:meth:`plenocl.Camera.image_points`).
    intensities
        Counts each particle sends through the aperture (scalar or ``(N,)``).
    rays_per_particle, seed
        Rays traced per particle, and the seed of the counter-based generator.
    blur_px
        Standard deviation (pixels) of a Gaussian particle-image blur (diffraction).
    background, photon_noise, read_noise, electrons_per_count, bit_depth, saturation
        Sensor model, see :class:`plenocl.sensor.SensorModel`.
    lens_transmission
        Optional ``(rows, cols)`` per-lens transmission in [0, 1] (0: a dead lens).
    lens_shift_mm
        Optional ``(rows, cols, 2)`` displacement of each lens from its lattice node on
        the array plane (mm; manufacturing errors, at most a quarter pitch). A displaced
        lens's image centre moves by ``(1 + f_ml/d)`` times its shift.
    queue
        OpenCL queue, context, device or device-name substring.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` image: float32 counts, or ``uint8``/``uint16`` when ``bit_depth`` is set.
        Without losses the noise-free image sums to the intensity of the rays that land.
    """
    sensor = SensorModel(background, photon_noise, electrons_per_count, read_noise,
                         bit_depth, saturation)
    clean = Simulator(camera, queue).trace(positions, intensities, rays_per_particle, seed,
                                           blur_px, lens_transmission, lens_shift_mm)
    _warn_if_unusable(camera, clean, float(np.sum(intensities)) if np.size(intensities) else 0)
    _warn_if_some_outside(camera, positions, float(clean.max()))
    return recorded(sensor, clean, seed, "image")


#: A recorded image with more than this share of its lit pixels at full scale warns.
SATURATED_WARN = 0.5


def recorded(sensor: SensorModel, clean: np.ndarray, seed: int, what: str) -> np.ndarray:
    """``sensor``'s record of the noise-free ``clean`` image, with a warning where it holds
    nothing (every pixel rounded to zero) or is mostly saturated: light that the chosen
    intensities, background, gain or bit depth lost (plenocl's reconstruction refuses
    such a frame; calibration reads no spot in it)."""
    out = sensor.apply(clean, seed)
    lit = clean > 0
    if not lit.any():
        return out
    saturated = float(np.mean(out[lit] >= sensor.full_scale))  # 0 for a float sensor (inf)
    if not out.any():
        warnings.warn(f"the simulated {what} is blank: every pixel records 0 (the light, "
                      f"peak {float(clean.max()):.3g} counts, rounds to nothing); raise the "
                      "intensities or the gain", stacklevel=3)
    elif saturated > SATURATED_WARN:
        warnings.warn(f"the simulated {what} is saturated: {saturated:.0%} of its lit pixels "
                      f"sit at full scale {sensor.full_scale:g}; lower the intensities or the "
                      "background, or raise the bit depth", stacklevel=3)
    return out


#: The warning :func:`simulate_image` gives when some particles lie outside the field of
#: view (what :func:`seeded_beyond_view` silences).
SOME_OUTSIDE = r"\d+ of the \d+ particles lie outside the camera's field of view"


@contextlib.contextmanager
def seeded_beyond_view() -> Iterator[None]:
    """Inside the block, :func:`simulate_image` does not count the particles outside the
    field of view: for scenes that seed beyond it on purpose (a flow carries particles in
    and out of the view between the exposures, as the demos' do)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=SOME_OUTSIDE)
        yield


def _warn_if_some_outside(camera: Camera, positions, peak: float) -> None:
    """Warn when some particles (not all: :func:`_warn_if_unusable` says that) lie
    outside the field of view at their depths: their light misses the sensor, and a
    truth list that holds them holds particles the image does not."""
    pts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if camera.pose is not None:
        pts = camera.pose.to_camera(pts)
    outside = int(np.count_nonzero(~in_field_of_view(camera, pts)))
    if outside and peak > 0:
        warnings.warn(f"{outside} of the {len(pts)} particles lie outside the camera's field "
                      "of view at their depths: their light misses the sensor (positions "
                      "are x, y, z in mm, z along the optical axis; "
                      "plenocl.optics.depthrange.field_of_view_mm gives the field at a "
                      "depth)", stacklevel=3)


#: A simulated particle image whose brightest pixel stays below this many counts warns:
#: reconstructions of such images lose most particles.
DIM_IMAGE_COUNTS = 50.0


def _warn_if_unusable(camera: Camera, clean: np.ndarray, light: float) -> None:
    """Warn about an image without light (particles outside the field of view) or one
    too dim to reconstruct well."""
    if light <= 0:
        return
    peak = float(clean.max())
    if peak == 0:
        half = (np.array(camera.ml_count) * [camera.ml_pitch_mm, camera.ml_row_pitch_mm]
                / camera.magnification / 2)
        warnings.warn("no light of the particles reached the sensor: they lie outside the "
                      f"field of view (about x in ±{half[0]:.2f}, y in ±{half[1]:.2f} mm at "
                      "z = 0)", stacklevel=3)
    elif peak < DIM_IMAGE_COUNTS:
        warnings.warn(f"the image peaks at {peak:.1f} counts: too dim to reconstruct well "
                      "(most particles are lost below about 50); raise the intensities "
                      "(counts each particle sends through the aperture, e.g. 2e4)",
                      stacklevel=3)


def simulate_white_image(camera: Camera, *, stop_f_number: float = 16.0,
                         rays_per_lens: int = 2000, intensity: float = 1000.0, seed: int = 0,
                         blur_px: float = 0.8, vignetting: float = 0.0, missing=None,
                         background: float = 0.0, photon_noise: bool = False,
                         read_noise: float = 0.0, electrons_per_count: float = 1.0,
                         bit_depth: int | None = None, saturation: float | None = None,
                         lens_shift_mm=None, queue: DeviceLike = None) -> np.ndarray:
    """Simulate a white (calibration) image taken with the main lens stopped down.

    Each microlens images the small stopped-down aperture as a spot centred at
    ``c_k = x_k (1 + f_ml / d)`` (``d``: the exit pupil's distance from the array;
    docs/design.md §2).

    Parameters
    ----------
    stop_f_number
        The f-number the main lens is stopped down to (spot diameter
        ``f_ml m_p (f / N_stop) / d``).
    rays_per_lens, intensity
        Rays traced per microlens and the total counts each lens receives.
    blur_px
        Gaussian spot blur in pixels (diffraction at the stopped-down aperture).
    vignetting
        Relative intensity loss at the array corner, ``1 - vignetting · r² / r_max²``.
    missing
        Optional boolean ``(rows, cols)`` mask of dead or occluded lenses.
    background, photon_noise, read_noise, electrons_per_count, bit_depth, saturation
        Sensor model, see :class:`plenocl.sensor.SensorModel`.
    lens_shift_mm
        Optional per-lens displacement from the lattice, as for :func:`simulate_image`:
        the true image centres are then ``camera.ideal_microlens_centers()`` plus
        :func:`centre_shift_px` of it.
    """
    if not 0.0 <= vignetting < 1.0:
        raise ValueError(f"vignetting must be in [0, 1), got {vignetting}")
    if not (np.isfinite(intensity) and intensity > 0):  # a blank white image: no lens
        raise ValueError(f"intensity must be positive (counts per microlens), got {intensity}")
    pos = camera.microlens_positions_mm()
    r2 = (pos ** 2).sum(-1)
    gain = 1.0 - vignetting * r2 / r2.max() if r2.max() > 0 else np.ones(r2.shape)
    if missing is not None:
        missing = np.asarray(missing, bool)
        if missing.shape != gain.shape:
            raise ValueError(f"missing must be a boolean mask of shape {gain.shape} "
                             "(rows, cols of the microlens array)")
        gain = np.where(missing, 0.0, gain)
    sensor = SensorModel(background, photon_noise, electrons_per_count, read_noise,
                         bit_depth, saturation)
    clean = Simulator(camera, queue).trace_white(stop_f_number, rays_per_lens, intensity, seed,
                                                 blur_px, gain, lens_shift_mm)
    return recorded(sensor, clean, seed, "white image")


def centre_shift_px(camera: Camera, lens_shift_mm) -> np.ndarray:
    """How far (pixels, ``(col, row)``) each microlens image centre moves when its lens
    is displaced by ``lens_shift_mm`` on the array plane: ``(1 + f_ml/d) / p_px`` times."""
    d = np.asarray(lens_shift_mm, dtype=np.float64)
    return d * camera.lens_image_scale / camera.pixel_pitch_mm


def lens_displacements_mm(camera: Camera, *, jitter_px: float = 0.0,
                          distortion_px: float = 0.0, seed: int = 0) -> np.ndarray:
    """Per-lens displacements (``lens_shift_mm`` of :func:`simulate_white_image`) that
    move the microlens image centres off the ideal lattice as a real camera's are.

    Parameters
    ----------
    camera
        The camera (its true layout).
    jitter_px
        RMS (px, per axis) of independent random offsets of the centres (lens placement).
    distortion_px
        A radial distortion of the centres about the optical axis, ``Δc = D (r/r_max)² (c
        - axis)/r_max`` (the main lens's pupil distortion, ``k1 r³``): ``D`` px at the
        lens farthest from the axis, outward for ``D > 0`` (pincushion), inward for ``D < 0``.
    seed
        Seed of the jitter.

    Returns
    -------
    numpy.ndarray
        ``(rows, cols, 2)`` mm on the array plane; the true image centres are
        ``camera.ideal_microlens_centers() + centre_shift_px(camera, shift)``.
    """
    for name, value in (("jitter_px", jitter_px), ("distortion_px", distortion_px)):
        if not np.isfinite(value):
            raise ValueError(f"{name} must be a finite number of pixels, got {value!r}")
    if jitter_px < 0:
        raise ValueError(f"jitter_px must be >= 0 (px RMS), got {jitter_px!r}")
    pos = camera.microlens_positions_mm() * camera.lens_image_scale / camera.pixel_pitch_mm
    r = np.hypot(pos[..., 0], pos[..., 1])
    r_max = max(float(r.max()), 1e-12)
    move = distortion_px * (r / r_max)[..., None] ** 2 * pos / r_max
    move = move + np.random.default_rng(seed).normal(0.0, jitter_px, pos.shape)
    return move * camera.pixel_pitch_mm / camera.lens_image_scale
