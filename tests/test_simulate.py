"""The OpenCL ray-tracing simulator against its reference, an independent ray trace,
and the geometry of docs/design.md §2."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol

import plenocl.simulate.raytrace as simmod
from plenocl import Camera, reference
from plenocl.simulate import Simulator, simulate_image, simulate_white_image


def _corr(a, b) -> float:
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def _abcd_trace(cam: Camera, point, rays: int, seed: int) -> np.ndarray:
    """Independent exact trace with paraxial ray-transfer steps (object → lens → MLA →
    microlens → sensor), NumPy's own random numbers, no image-point formulas."""
    rng = np.random.default_rng(seed)
    r = cam.aperture_diameter_mm / 2 * np.sqrt(rng.random(rays))
    t = 2 * np.pi * rng.random(rays)
    ap = np.stack([r * np.cos(t), r * np.sin(t)], -1)
    obj = np.asarray(point[:2], float)
    s_o = cam.object_distance_mm + point[2]
    slope = (ap - obj) / s_o - ap / cam.focal_length_mm  # after the thin main lens
    mla = ap + slope * cam.image_distance_mm
    k = np.floor(mla / cam.ml_pitch_mm + np.array(cam.ml_count) / 2).astype(int)
    ok = np.all((k >= 0) & (k < np.array(cam.ml_count)), axis=1)
    centre = (k - (np.array(cam.ml_count) - 1) / 2) * cam.ml_pitch_mm
    slope2 = slope - (mla - centre) / cam.ml_focal_length_mm  # microlens refraction
    sensor = mla + slope2 * cam.ml_focal_length_mm
    px = np.floor(sensor / cam.pixel_pitch_mm + np.array(cam.pixels) / 2).astype(int)
    ok &= np.all((px >= 0) & (px < np.array(cam.pixels)), axis=1)
    img = np.zeros(cam.pixels[::-1])
    np.add.at(img, (px[ok, 1], px[ok, 0]), 1.0)
    return img


@pytest.mark.parametrize("region", [None, ((51, 17), (119, 136))])
def test_kernel_matches_reference_ray_for_ray(queue, small_camera, region):
    """Ray for ray, on the whole sensor and on a region of it off its centre (the axis
    kept where it crosses the whole sensor)."""
    cam = small_camera if region is None else small_camera.cropped(*region)
    pos = np.array([[0.1, 0.05, 0.0], [-0.3, 0.2, 1.5], [0.2, -0.1, -2.0], [0.6, 0.5, 0.7]])
    inten = np.array([1000.0, 500.0, 2000.0, 750.0])
    a = Simulator(cam, queue).trace(pos, inten, 7001, seed=11, blur_px=0.5)
    b = reference.trace_particles(cam, pos, inten, 7001, seed=11, blur_px=0.5)
    assert b.sum() > 0.3 * reference.trace_particles(small_camera, pos, inten, 7001,
                                                     seed=11, blur_px=0.5).sum()
    assert a.sum() == pytest.approx(b.sum(), rel=tol.SIMULATED_TOTAL)
    assert _corr(a, b) > 0.9999
    # only rays within float32 rounding of an edge may move: a handful of pixels at most
    assert np.count_nonzero(np.abs(a - b) > 1e-3) <= 10


@pytest.mark.parametrize("z", [-3.0, -1.0, 0.0, 1.5, 3.0])
def test_single_particle_agrees_with_exact_ray_trace(queue, z):
    cam = Camera.synthetic_850()
    point = np.array([0.21, -0.13, z])
    rays = 300_000
    img = simulate_image(cam, point[None], 1.0, rays, seed=5, queue=queue)
    ref = _abcd_trace(cam, point, rays, seed=6)
    lit = (img > 0) | (ref > 0)
    assert _corr(img[lit], ref[lit]) >= 0.98


def test_in_focus_particle_lands_only_under_its_microlens(queue, small_camera):
    cam = small_camera
    ky, kx = 4, 7
    xk = cam.microlens_positions_mm()[ky, kx]
    # object point imaged exactly onto the centre of lens (kx, ky): X' = -M x
    point = np.array([[-xk[0] / cam.magnification, -xk[1] / cam.magnification, 0.0]])
    img = simulate_image(cam, point, 1000.0, 20000, seed=1, queue=queue)
    c = cam.microlens_centers[ky, kx]
    half = cam.pixels_per_microlens / 2
    rows, cols = np.nonzero(img)
    assert np.all(np.abs(cols - c[0]) <= half) and np.all(np.abs(rows - c[1]) <= half)
    assert img.sum() == pytest.approx(1000.0, rel=1e-9)


def _lens_sums(cam: Camera, img: np.ndarray) -> np.ndarray:
    """Sum the pixels behind each microlens (nearest ideal image centre)."""
    c00 = cam.microlens_centers[0, 0]
    pitch = cam.microlens_image_pitch_mm / cam.pixel_pitch_mm
    rows, cols = np.indices(img.shape)
    kx = np.clip(np.floor((cols - c00[0]) / pitch + 0.5).astype(int), 0, cam.ml_count[0] - 1)
    ky = np.clip(np.floor((rows - c00[1]) / pitch + 0.5).astype(int), 0, cam.ml_count[1] - 1)
    sums = np.zeros(cam.ml_count[::-1])
    np.add.at(sums, (ky, kx), img)
    return sums


@pytest.mark.parametrize("z", [-4.0, -2.5, 2.5, 4.0])
def test_defocus_disc_grows_as_geometry_predicts(queue, z):
    cam = Camera.synthetic_850()
    img = simulate_image(cam, np.array([[0.0, 0.0, z]]), 1.0, 200_000, seed=2, queue=queue)
    sums = _lens_sums(cam, img)
    xk = cam.microlens_positions_mm()
    var = (sums[..., None] * xk**2).sum((0, 1)) / sums.sum()  # per-axis second moment
    # a uniform disc of radius R has per-axis variance R²/4; lens binning adds p²/12
    radius = 2 * np.sqrt(var.mean() - cam.ml_pitch_mm**2 / 12)
    s_ip = cam.image_distance_at(z)
    expected = cam.aperture_diameter_mm / 2 * abs(s_ip - cam.image_distance_mm) / s_ip
    assert radius == pytest.approx(expected, rel=0.05)


def test_white_spots_sit_on_the_ideal_centres(queue):
    cam = Camera.synthetic_850()
    img = simulate_white_image(cam, rays_per_lens=3000, seed=4, queue=queue)
    centres = cam.ideal_microlens_centers()
    half = int(cam.pixels_per_microlens // 2)
    errors = []
    for ky in range(0, cam.ml_count[1], 7):
        for kx in range(0, cam.ml_count[0], 7):
            c, r = np.rint(centres[ky, kx]).astype(int)
            win = img[r - half:r + half + 1, c - half:c + half + 1]
            rr, cc = np.mgrid[r - half:r + half + 1, c - half:c + half + 1]
            errors.append([(win * cc).sum() / win.sum() - centres[ky, kx, 0],
                           (win * rr).sum() / win.sum() - centres[ky, kx, 1]])
    assert np.abs(errors).max() < 0.15


def test_white_image_matches_reference_and_marks_missing_lenses(queue, small_camera):
    missing = np.zeros((10, 12), bool)
    missing[2, 3] = True
    img = simulate_white_image(small_camera, rays_per_lens=800, seed=3, missing=missing,
                               queue=queue)
    gain = np.where(missing, 0.0, 1.0)
    ref = reference.trace_white(small_camera, 16.0, 800, 3, 1000.0, 0.8, gain)
    assert _corr(img, ref) > 0.9999
    c, r = np.rint(small_camera.microlens_centers[2, 3]).astype(int)
    assert img[r - 3:r + 4, c - 3:c + 4].sum() == 0


def test_image_sums_to_the_light_that_lands(queue, small_camera):
    # one particle near the sensor edge and defocused: part of its light misses
    pos = np.array([[0.7, 0.6, 2.0], [0.0, 0.0, 0.0]])
    img = Simulator(small_camera, queue).trace(pos, [1000.0, 400.0], 5000, seed=9)
    landed = [reference.trace_particles(small_camera, p[None], 1.0, 5000, seed=9).sum()
              for p in pos]
    assert landed[0] < 0.99  # the test case really loses light
    # the reference traces the very same rays (same source ids) in float64
    both = reference.trace_particles(small_camera, pos, [1000.0, 400.0], 5000, seed=9)
    assert img.sum() == pytest.approx(both.sum(), abs=2 * 1000.0 / 5000)


def test_same_seed_same_image_and_chunking_does_not_matter(queue, small_camera, monkeypatch):
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(-0.6, 0.6, 50), rng.uniform(-0.5, 0.5, 50),
                           rng.uniform(-2, 2, 50)])
    sim = Simulator(small_camera, queue)
    a = sim.trace(pos, 100.0, 300, seed=7)
    assert np.array_equal(a, sim.trace(pos, 100.0, 300, seed=7))
    assert not np.array_equal(a, sim.trace(pos, 100.0, 300, seed=8))
    monkeypatch.setattr(simmod, "MAX_ITEMS_PER_LAUNCH", 64)  # many small launches
    b = sim.trace(pos, 100.0, 300, seed=7)
    np.testing.assert_allclose(a, b, atol=tol.SIMULATED_SPLIT)


def test_sensor_model_noise_and_saturation(queue, small_camera):
    pos = np.array([[0.0, 0.0, 0.0]])
    clean = simulate_image(small_camera, pos, 5e4, 20000, seed=1, queue=queue)
    noisy = simulate_image(small_camera, pos, 5e4, 20000, seed=1, photon_noise=True,
                           background=100.0, queue=queue)
    resid = noisy - clean - 100.0
    assert abs(resid.mean()) < 0.5  # Poisson noise is unbiased
    assert resid.var() / (clean + 100.0).mean() == pytest.approx(1.0, rel=0.05)
    digital = simulate_image(small_camera, pos, 5e6, 20000, seed=1, bit_depth=12, queue=queue)
    assert digital.dtype == np.uint16 and digital.max() == 4095  # saturates at full scale


@pytest.mark.parametrize("bad, message", [
    (dict(positions=np.zeros((3, 2))), r"\(N, 3\)"),
    (dict(positions=np.full((1, 3), np.nan)), "finite"),
    (dict(intensities=-1.0), ">= 0"),
    (dict(positions=np.array([[0.0, 0.0, -80.0]])), "no real image"),
    (dict(rays_per_particle=0), "positive integer"),
    (dict(read_noise=-1.0), "read_noise"),
    (dict(bit_depth=20), "bit_depth"),
    (dict(bit_depth=1.5), "bit_depth must be a whole number"),
    # a saturation above the integers' full scale wrapped around (900000 read 48032)
    (dict(bit_depth=16, saturation=1e6), r"above the 16-bit full scale 65535"),
    (dict(photon_noise=True, electrons_per_count=np.inf), "electrons_per_count must be a "
                                                          "finite number"),
])
def test_bad_simulation_input_is_rejected(queue, small_camera, bad, message):
    args = dict(positions=np.zeros((1, 3)), intensities=1.0, rays_per_particle=10)
    args.update(bad)
    with pytest.raises(ValueError, match=message):
        simulate_image(small_camera, queue=queue, **args)


def test_particles_outside_the_field_of_view_are_counted(queue, small_camera):
    """Some particles outside the field of view were dropped in silence (only all of them
    warned): their count is said; particles inside say nothing."""
    import warnings

    inside = np.array([[0.0, 0.0, 0.3]])
    with pytest.warns(UserWarning, match=r"1 of the 2 particles lie outside the camera's "
                                         r"field of view"):
        img = simulate_image(small_camera, np.vstack([inside, [[40.0, 0.0, 0.3]]]), 1e4,
                             200, seed=1, queue=queue)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alone = simulate_image(small_camera, inside, 1e4, 200, seed=1, queue=queue)
    np.testing.assert_allclose(img, alone)  # the outside particle adds no light


def test_a_blank_or_saturated_record_is_said(queue, small_camera):
    """Light the sensor model lost, in silence before: an image rounded to zero, one
    mostly at full scale; a well exposed one says nothing."""
    import warnings

    pos = np.array([[0.0, 0.0, 0.3]])
    with pytest.warns(UserWarning, match=r"simulated image is saturated: 100% of its lit "
                                         r"pixels sit at full scale 255"):
        simulate_image(small_camera, pos, 2e7, 500, seed=1, bit_depth=8, queue=queue)
    with pytest.warns(UserWarning, match="simulated white image is blank"):
        simulate_white_image(small_camera, rays_per_lens=50, intensity=1e-3, bit_depth=16,
                             queue=queue)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        simulate_image(small_camera, pos, 2e4, 500, seed=1, bit_depth=16, queue=queue)


def test_white_image_rejects_open_aperture(queue, small_camera):
    with pytest.raises(ValueError, match="stopped down"):
        simulate_white_image(small_camera, stop_f_number=1.0, queue=queue)


def test_displaced_lenses_move_their_spots_and_images(queue, small_camera):
    """A lens off its lattice node (manufacturing error): the kernel traces the same rays
    as the reference, and the white spot's centroid moves by (1 + f_ml/s_i) times the
    shift, to within the centroid's own noise."""
    from plenocl.simulate import centre_shift_px

    rng = np.random.default_rng(6)
    shift = rng.uniform(-0.002, 0.002, (10, 12, 2))  # mm: about ±0.3 px of image centre
    white = Simulator(small_camera, queue).trace_white(16.0, 4000, 1000.0, 5, 0.8, None, shift)
    ref = reference.trace_white(small_camera, 16.0, 4000, 5, 1000.0, 0.8, None, shift)
    assert _corr(white, ref) > 0.9999
    truth = small_camera.ideal_microlens_centers() + centre_shift_px(small_camera, shift)
    err = []
    for ky in range(1, 9):
        for kx in range(1, 11):
            c, r = np.rint(truth[ky, kx]).astype(int)
            win = white[r - 5:r + 6, c - 5:c + 6]
            rr, cc = np.mgrid[r - 5:r + 6, c - 5:c + 6]
            err.append([(win * cc).sum() / win.sum() - truth[ky, kx, 0],
                        (win * rr).sum() / win.sum() - truth[ky, kx, 1]])
    assert np.sqrt(np.mean(np.square(err))) < 0.03  # the shifts themselves are ~0.15 px RMS
    pos = np.array([[0.1, 0.05, 0.0], [-0.3, 0.2, 1.5]])
    a = Simulator(small_camera, queue).trace(pos, 1000.0, 5001, seed=2, lens_shift_mm=shift)
    b = reference.trace_particles(small_camera, pos, 1000.0, 5001, seed=2, lens_shift_mm=shift)
    assert _corr(a, b) > 0.9999
    with pytest.raises(ValueError, match="quarter"):
        simulate_white_image(small_camera, lens_shift_mm=np.full((10, 12, 2), 0.05),
                             queue=queue)


def test_a_scene_seeded_beyond_the_view_on_purpose_says_nothing(queue, small_camera):
    """The demos seed a margin the flow carries into view: seeded_beyond_view silences the
    count there, and only there."""
    import warnings

    from plenocl.simulate import seeded_beyond_view

    pos = np.array([[0.0, 0.0, 0.3], [40.0, 0.0, 0.3]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with seeded_beyond_view():
            simulate_image(small_camera, pos, 1e4, 200, seed=1, queue=queue)
    with pytest.warns(UserWarning, match="1 of the 2 particles lie outside"):
        simulate_image(small_camera, pos, 1e4, 200, seed=1, queue=queue)
