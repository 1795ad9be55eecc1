"""The raw image smoothed before a reconstruction (``ReconstructionSettings.smooth_px``,
docs/design.md §6.2): the filter's properties, the noise and threshold the preprocessing
takes, and what it is for: the paper's MART on a noisy ray-traced image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenocl import Camera, Grid, Projector, random_particles, reconstruct
from plenocl.metrics import recovery
from plenocl.optics.rawimage import background_and_noise
from plenocl.options import NONE
from plenocl.pipeline.settings import PairSettings
from plenocl.reconstruction import METHODS, SMOOTH_DEFAULTS, ReconstructionSettings
from plenocl.reconstruction.images import gaussian_taps, preprocess, smooth_image, smoothing_gain
from plenocl.simulate import simulate_image


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_the_gain_is_what_the_smoothing_leaves_of_white_noise(sigma):
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 1.0, (600, 500))
    smoothed = smooth_image(noise, sigma)
    assert smoothed[20:-20, 20:-20].std() == pytest.approx(smoothing_gain(sigma), rel=0.03)
    assert gaussian_taps(sigma).sum() == pytest.approx(1.0, abs=1e-12)
    if sigma >= 1.0:  # the continuous Gaussian's 1 / (2 sqrt(pi) sigma)
        assert smoothing_gain(sigma) == pytest.approx(1 / (2 * np.sqrt(np.pi) * sigma),
                                                      rel=0.01)


def test_smoothing_keeps_a_constant_and_a_spots_light_and_centre():
    flat = np.full((31, 47), 7.25)
    assert np.allclose(smooth_image(flat, 1.3), 7.25, rtol=0, atol=1e-12)
    spot = np.zeros((41, 41))
    spot[20, 23] = 5.0
    out = smooth_image(spot, 1.0)
    yy, xx = np.indices(out.shape)
    assert out.sum() == pytest.approx(5.0, rel=1e-12)
    assert (out * yy).sum() / out.sum() == pytest.approx(20.0, abs=1e-9)
    assert (out * xx).sum() / out.sum() == pytest.approx(23.0, abs=1e-9)
    var_x = (out * (xx - 23.0) ** 2).sum() / out.sum()  # the sampled Gaussian's variance
    assert np.sqrt(var_x) == pytest.approx(1.0, rel=0.01)


def test_pixels_without_data_neither_darken_nor_take_light():
    """Normalised over the observed pixels: a constant stays itself beside holes, and the
    holes come out 0."""
    rng = np.random.default_rng(5)
    observed = rng.random((60, 70)) > 0.2
    img = np.where(observed, 3.0, 1e6)  # whatever a pixel without data holds
    out = smooth_image(img, 1.0, observed)
    assert np.allclose(out[observed], 3.0, rtol=1e-12) and np.all(out[~observed] == 0)


def test_preprocessing_keeps_the_raw_noise_and_thresholds_the_smoothed_one(small_camera):
    """The threshold is 4 sigma of the noise the smoothing leaves (the raw noise times
    the gain); the background removed is the raw image's median."""
    rng = np.random.default_rng(8)
    rows, cols = small_camera.pixels[1], small_camera.pixels[0]
    raw = 20.0 + rng.normal(0.0, 3.0, (rows, cols))
    raw[40:43, 60:63] += 400.0
    med, noise = background_and_noise(raw, None)
    img, scale, thr = preprocess(raw, small_camera, smooth_px=1.0)
    plain_img, plain_scale, plain_thr = preprocess(raw, small_camera)
    assert thr * scale == pytest.approx(4.0 * smoothing_gain(1.0) * noise, rel=1e-6)
    assert plain_thr * plain_scale == pytest.approx(4.0 * noise, rel=1e-6)
    expected = np.maximum(smooth_image(raw - med, 1.0), 0.0)
    assert np.allclose(img * scale, expected, rtol=1e-5, atol=1e-4 * scale)


@pytest.mark.parametrize("value", [-1.0, -1e-9, float("nan"), 4.5, True, "1"])
def test_a_smoothing_outside_a_particle_images_size_is_refused(value):
    with pytest.raises(ValueError, match="smooth_px must be a (Gaussian's standard "
                                         "deviation|number or None)"):
        ReconstructionSettings(smooth_px=value)


@pytest.mark.parametrize("method", METHODS)
def test_each_method_smooths_by_its_own_default_and_keeps_what_it_is_given(method):
    """``None`` resolves to the method's default (1 px for the geometric-mean methods,
    none for MLEM), stored resolved: ``replace`` keeps it, a settings document carries
    it, and a value given (0: none) always wins."""
    default = ReconstructionSettings(method)
    assert default.smooth_px == SMOOTH_DEFAULTS[method]
    assert (default.smooth_px == 1.0) == (method in ("smart", "mart"))
    assert dataclasses.replace(default, iterations=3).smooth_px == default.smooth_px
    for given in (0.0, 0.7):
        assert ReconstructionSettings(method, smooth_px=given).smooth_px == given
    doc = PairSettings(reconstruction=default).to_dict(none=NONE)
    assert PairSettings.from_dict(doc).reconstruction.smooth_px == default.smooth_px


def test_no_smoothing_is_none_or_zero_alike(small_camera):
    rng = np.random.default_rng(9)
    rows, cols = small_camera.pixels[1], small_camera.pixels[0]
    raw = (20.0 + rng.normal(0.0, 3.0, (rows, cols))).astype(np.float32)
    for a, b in zip(preprocess(raw, small_camera, smooth_px=0.0), preprocess(raw, small_camera)):
        assert np.array_equal(a, b)


@pytest.mark.one_device
def test_smoothing_lets_the_papers_mart_keep_the_particles_of_a_noisy_image(queue):
    """The paper's MART (15 iterations, mu 0.7, no floor) with lens weights that integrate
    each 3 x 3 sub-voxel's extent: on a noisy ray-traced image (photon noise, dark level
    20, read noise 3) it loses most particles to pixels its 4 sigma threshold calls dark
    unsmoothed (``smooth_px=0``), and keeps nearly all with its defaults: the image
    smoothed by 1 px, and the sub-voxels after MLEM's coarse run (4 coarse MART
    iterations would lose half of them; benchmarks/paper_mart.py measures more scenes);
    what the background removed and the noise are stay the raw image's."""
    grid = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
    cam = Camera.synthetic_850()
    proj = Projector(cam, grid, queue, lens_weights="extent")
    pos, inten = random_particles(((-2.3, 2.3),) * 3, count=20, seed=2100, intensity=1e4)
    img = simulate_image(cam, pos, inten, 20000, seed=2100, blur_px=1.0, photon_noise=True,
                         background=20.0, read_noise=3.0, queue=queue)
    mart = dict(method="mart", iterations=15, relax=0.7, supersample=3, coarse_iterations=0)
    literal = recovery(reconstruct(img, proj, **mart, smooth_px=0), grid, pos).fraction
    vol, info = reconstruct(img, proj, method="mart", return_info=True)
    assert (info.coarse_iterations, info.iterations, info.method) == (4, 15, "mart")
    smoothed = recovery(vol, grid, pos).fraction
    assert literal <= 0.5 and smoothed >= 0.9, (literal, smoothed)
    assert (info.background, info.noise) == pytest.approx(background_and_noise(img, None))
