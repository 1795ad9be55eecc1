"""Full-aperture calibration follows each lens (issue 44, deliverable 3): white images
at the main lens's own f-number whose lenses sit off the lattice (0.2 px RMS jitter and
a radial distortion of the main lens) are calibrated to each lens's own centre
``c_k`` (docs/design.md §3), against the simulator's truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import OPTICS, lens_camera
from scipy import ndimage, special

from plenocl import Camera, get_queue
from plenocl.calibration import find_centers
from plenocl.calibration.lenscentres import fit_disks
from plenocl.simulate import centre_shift_px, lens_displacements_mm, simulate_white_image

TARGET_RMS_PX = 0.05
JITTER_PX = 0.2
DISTORTION_PX = 1.5
#: A camera's exposure: ~2000 of 4096 counts in a disk, photon and read noise.
EXPOSURE = dict(photon_noise=True, read_noise=3.0, bit_depth=12, intensity=4e5,
                rays_per_lens=100_000)


def _camera(layout: str, cols: int = 14, rows: int = 12) -> Camera:
    """~17 px per lens, rotated 0.3°; the sensor cut to the array."""
    row_px = 16.98 * (3**0.5 / 2 if layout == "hexagonal" else 1.0)
    return lens_camera(cols, rows, (int(cols * 16.98) + 1, int(rows * row_px) + 1),
                       ml_layout=layout, ml_rotation_deg=0.3)


def _nominal(cam: Camera) -> Camera:
    return dataclasses.replace(cam, ml_rotation_deg=0.0)


def _shifted(cam: Camera, jitter: float = JITTER_PX, distortion: float = DISTORTION_PX):
    """Lens displacements (mm), the true centres, and the jitter's part of them (px)."""
    shift = lens_displacements_mm(cam, jitter_px=jitter, distortion_px=distortion, seed=4)
    smooth = lens_displacements_mm(cam, distortion_px=distortion)
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    return shift, truth, centre_shift_px(cam, shift - smooth)


def _rms(centres: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(((centres - truth) ** 2).sum(-1))))


@pytest.fixture(scope="module", params=[
    pytest.param(("rectangular", 0.0), id="rect"),
    pytest.param(("rectangular", 0.5), id="rect-vignetted", marks=pytest.mark.slow),
    pytest.param(("hexagonal", 0.0), id="hex", marks=pytest.mark.slow),
    pytest.param(("hexagonal", 0.5), id="hex-vignetted")])
def jittered(request):
    """The camera, the true centres, the jitter's part of them, and the calibration
    (default and lattice-only) of its white image. Calibration is host code: the image
    is simulated once, on the default device."""
    layout, vignetting = request.param
    cam = _camera(layout)
    shift, truth, jitter = _shifted(cam)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, vignetting=vignetting,
                                 lens_shift_mm=shift, seed=7, queue=get_queue(), **EXPOSURE)
    return (cam, truth, jitter, find_centers(white, _nominal(cam)),
            find_centers(white, _nominal(cam), method="fit"))


def test_each_lens_is_found_within_the_target(jittered):
    """≤ 0.05 px RMS (2-D) on every found lens, where the lattice alone (``method="fit"``)
    is off by the lenses' jitter and the distortion."""
    cam, truth, _, fit, lattice = jittered
    assert fit.aperture == "full" and fit.method == "combined"
    assert fit.found.mean() >= 0.97
    assert _rms(fit.centers, truth) <= TARGET_RMS_PX
    assert _rms(lattice.centers, truth) > 4 * _rms(fit.centers, truth)


def test_the_estimate_follows_the_jitter(jittered):
    """Each centre's offset from the smooth model is the lens's own: it correlates with
    the true jitter (the distortion is the model's), and the lenses' scatter about the
    lattice is measured as the simulated 0.2 px."""
    cam, truth, jitter, fit, _ = jittered
    own = (fit.centers - fit.model)[fit.found]
    true = (truth - fit.model)[fit.found]
    assert np.corrcoef(own.ravel(), true.ravel())[0, 1] > 0.97
    assert np.corrcoef(own.ravel(), jitter[fit.found].ravel())[0, 1] > 0.9
    assert fit.lattice_scatter_px == pytest.approx(JITTER_PX, rel=0.25)
    assert fit.degree == 3  # the radial distortion is found: cubic in the lens position


def test_the_estimated_uncertainty_is_the_actual_one(jittered):
    """The per-lens deviations (``noise_px``) the fit reports match the per-lens
    estimates' actual errors (per axis), so the weighting against the lattice is right."""
    _, truth, _, fit, _ = jittered
    actual = _rms(fit.centroids, truth) / np.sqrt(2)
    assert float(np.nanmedian(fit.noise_px)) == pytest.approx(actual, rel=0.4)


def test_lenses_cut_by_the_sensor_edge_fall_back_to_the_prior():
    """A disk mostly beyond the sensor's edge is not fitted (``NaN``, infinite deviation,
    so calibration keeps the model's centre for it); its neighbours, which see it in
    their windows, stay within the target."""
    cam = _camera("rectangular")
    shift, truth, _ = _shifted(cam)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, lens_shift_mm=shift,
                                 seed=7, queue=get_queue(), **EXPOSURE).astype(float)
    pitch = cam.pixels_per_microlens
    cut = white[:, : int(truth[:, -1, 0].min()) - 5]  # the last column: centres 5 px off
    disks = fit_disks(cut, truth, pitch)
    assert np.isnan(disks.centres[:, -1]).all() and np.isinf(disks.sigma[:, -1]).all()
    assert _rms(disks.centres[:, -2], truth[:, -2]) <= TARGET_RMS_PX
    assert _rms(disks.centres[:, :-1], truth[:, :-1]) <= TARGET_RMS_PX


def test_a_noisy_image_leans_on_the_lattice():
    """A dim image (a tenth of the light, 8 bits): each lens's own fit is noisier, and the
    combination, weighing it against the lattice by both uncertainties, is better than
    either alone."""
    cam = _camera("hexagonal")
    shift, truth, _ = _shifted(cam, jitter=0.05)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, lens_shift_mm=shift,
                                 photon_noise=True, read_noise=2.0, bit_depth=8,
                                 intensity=4e4, rays_per_lens=20_000, seed=9, queue=get_queue())
    fit = find_centers(white, _nominal(cam))
    own, model = _rms(fit.centroids, truth), _rms(fit.model[fit.found], truth[fit.found])
    assert _rms(fit.centers, truth) < min(own, model)


def test_the_lens_displacements_are_what_they_say():
    """``distortion_px`` moves the lens farthest from the axis that far outward, radially;
    ``jitter_px`` is the RMS per axis of the rest."""
    cam = lens_camera(30, 20)
    ideal = cam.ideal_microlens_centers()
    axis = np.array(cam.pixels) / 2 - 0.5
    move = centre_shift_px(cam, lens_displacements_mm(cam, distortion_px=2.0))
    radius = np.hypot(*(ideal - axis).transpose(2, 0, 1))
    far = np.unravel_index(np.argmax(radius), radius.shape)
    np.testing.assert_allclose(move[far], 2.0 * (ideal[far] - axis) / radius[far], atol=1e-9)
    outward = ((ideal - axis) * move).sum(-1)
    assert (outward >= -1e-12).all()
    jitter = centre_shift_px(cam, lens_displacements_mm(cam, jitter_px=0.2, seed=1))
    assert float(np.sqrt(np.mean(jitter**2))) == pytest.approx(0.2, rel=0.05)


def _hexagonal_046(cols: int = 11, rows: int = 12) -> Camera:
    """Issue 44 finding 3's array: 65 px per lens, hexagonal, rotated 0.3°, the sensor
    cut to the array (the odd rows' offset is the lenses' displacement, :func:`_odd_rows`)."""
    pixel = OPTICS["pixel_pitch_mm"] * lens_camera().pixels_per_microlens / 65.0
    return lens_camera(cols, rows, (int((cols + 0.5) * 65) + 1, int(rows * 65 * 3**0.5 / 2) + 1),
                       ml_layout="hexagonal", ml_rotation_deg=0.3, pixel_pitch_mm=pixel)


def _odd_rows(cam: Camera, pitches: float) -> np.ndarray:
    """Lens displacements (mm) moving the odd rows by ``pitches`` along the rows."""
    turn = np.radians(cam.ml_rotation_deg)
    shift = np.zeros((cam.ml_count[1], cam.ml_count[0], 2))
    shift[1::2] = pitches * cam.ml_pitch_mm * np.array([np.cos(turn), np.sin(turn)])
    return shift


def test_odd_rows_offset_by_046_pitch_are_followed():
    """Issue 44 finding 3 as quoted: a hexagonal array of 65 px disks whose odd rows sit
    0.46 pitch from the even ones, not the camera file's 0.5 (plus 0.2 px jitter). Each
    lens is found within the target; the grid model fits the odd rows' offset (2.6 px),
    so the lenses' scatter about it is their jitter and the model alone is off by the
    jitter only. The lattice alone (the disks' centroids, which take in part of their
    neighbours' offsets) is off alternately by row."""
    cam = _hexagonal_046()
    shift = _odd_rows(cam, -0.04) + lens_displacements_mm(cam, jitter_px=JITTER_PX, seed=4)
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, lens_shift_mm=shift,
                                 seed=7, queue=get_queue(), **dict(
                                     EXPOSURE, intensity=6e6, rays_per_lens=200_000))
    fit = find_centers(white, _nominal(cam))
    lattice = find_centers(white, _nominal(cam), method="fit")
    assert fit.found.all() and fit.method == "combined"
    assert _rms(fit.centers, truth) <= TARGET_RMS_PX
    assert fit.lattice_scatter_px == pytest.approx(JITTER_PX, rel=0.25)
    assert _rms(fit.model, truth) <= 1.25 * np.sqrt(2) * JITTER_PX
    error = (lattice.centers - truth)[..., 0]
    assert error[0::2].mean() * error[1::2].mean() < 0  # alternating by row
    assert _rms(lattice.centers, truth) > 4 * _rms(fit.centers, truth)


def test_odd_rows_offset_by_046_pitch_stopped_down():
    """The same offset stopped down (17 px lenses, f/16 spots, 0.1 px jitter): the grid
    model alone (``method="fit"``) follows the odd rows, off by the jitter only, and the
    lenses' scatter about it is measured as the jitter."""
    jitter = 0.1
    cam = _camera("hexagonal", cols=16, rows=18)
    shift = _odd_rows(cam, -0.04) + lens_displacements_mm(cam, jitter_px=jitter, seed=4)
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    white = simulate_white_image(cam, lens_shift_mm=shift, seed=3, queue=get_queue(),
                                 photon_noise=True, intensity=1e4, rays_per_lens=20_000)
    lattice = find_centers(white, _nominal(cam), method="fit")
    assert lattice.aperture == "stopped" and lattice.found.all()
    assert _rms(lattice.centers, truth) <= 1.25 * np.sqrt(2) * jitter
    assert lattice.lattice_scatter_px == pytest.approx(jitter, rel=0.25)


def test_correlated_noise_is_counted():
    """A white image whose noise is correlated between neighbouring pixels (the dim
    image of :func:`test_a_noisy_image_leans_on_the_lattice` blurred by 0.7 px, as a
    resampled image is; lenses on the lattice): each fit's reported deviation is its
    actual error, not the fraction the residuals' independent pixels would say, so the
    combination leans on the lattice instead of following the noise."""
    cam = _camera("hexagonal")
    truth = cam.ideal_microlens_centers()
    white = simulate_white_image(cam, stop_f_number=cam.f_number, photon_noise=True,
                                 read_noise=2.0, bit_depth=8, intensity=4e4,
                                 rays_per_lens=20_000, seed=9, queue=get_queue())
    fit = find_centers(ndimage.gaussian_filter(white.astype(float), 0.7), _nominal(cam))
    actual = _rms(fit.centroids, truth) / np.sqrt(2)
    assert float(np.nanmedian(fit.noise_px)) == pytest.approx(actual, rel=0.3)
    assert _rms(fit.centers, truth) <= 0.5 * _rms(fit.centroids, truth)


def _soft_disks(cam: Camera, centres: np.ndarray, seed: int) -> np.ndarray:
    """A white image like plenopticam's synthetic hexagonal one: disks of 0.3 pitch
    radius (not touching), a wide soft edge (0.06 pitch), a domed top and Gaussian noise
    (σ 10 counts on a 150-count disk over a 50-count floor)."""
    pitch = cam.pixels_per_microlens
    w, h = cam.pixels
    y, x = np.mgrid[:h, :w]
    img = np.zeros((h, w))
    for cx, cy in centres.reshape(-1, 2):
        r = np.hypot(x - cx, y - cy) / (0.3 * pitch)
        img += 0.5 * special.erfc((r - 1) / 0.2) * np.clip(1 - 0.5 * r**2, 0, None)
    return 50 + 150 * img + np.random.default_rng(seed).normal(0, 10, img.shape)


def test_lenses_on_the_lattice_keep_the_lattice():
    """An exact lattice of soft, noisy disks (plenopticam's published white image, whose
    per-lens disk fits scatter far beyond their stated uncertainties): the image shows no
    lens off the lattice, so the default is no worse than the lattice alone
    (``method="fit"``) instead of following the fits' noise."""
    pitch = 40.0
    cam = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (15, 17), 0.125 / pitch,
                 (int(15 * pitch) + 1, int(17 * pitch * 0.866) + 1),
                 ml_layout="hexagonal", ml_odd_row_shift=0.5)
    truth = cam.ideal_microlens_centers()
    white = _soft_disks(cam, truth, seed=2)
    fit = find_centers(white, cam, aperture="full")
    lattice = find_centers(white, cam, method="fit", aperture="full")
    assert fit.method == "combined" and fit.found.mean() >= 0.9
    assert _rms(fit.centers, truth) <= _rms(lattice.centers, truth) + 0.005
