"""Image-space particle fit (plenocl/optics/raybundle.py, plenocl/piv/imagefit.py): the
deterministic ray bundle against the reference ray tracer, its derivatives against
finite differences, and the fit's recovery of particles from ray-traced images."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tolerances as tol

from plenocl.bench.accuracy_section import paper_optics
from plenocl.optics.raybundle import RayBundle, sunflower
from plenocl.optics.sightline import line_of_sight, sight_frames
from plenocl.piv.imagefit import (
    MAX_STEP_VOXELS,
    PRIOR_VOXELS,
    ImageFit,
    ImageFitSettings,
    posterior_covariance,
    sight_steps,
)
from plenocl.reference.simulate import trace_particles

CAM, GRID = paper_optics((32, 24))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm


def rendered(bundle: RayBundle, positions: np.ndarray, intensity: float,
             shift=None) -> tuple[np.ndarray, np.ndarray]:
    """The bundle's image of particles on the whole sensor (flat) and all its rows
    (value and derivatives) on the whole sensor."""
    pts = CAM.image_points(positions)
    if shift is not None:
        pts = pts + shift
    patches = bundle.patches(CAM.image_points(positions))
    elements, rows = bundle.render(pts, np.full(len(pts), intensity), patches)
    _, pixel = patches.pixels(CAM.pixels[0], elements)
    full = np.zeros((len(rows), CAM.pixels[0] * CAM.pixels[1]))
    for k, row in enumerate(rows):
        np.add.at(full[k], pixel, row)
    return full[0], full


def test_sunflower_spreads_equal_areas():
    pts = sunflower(4000)
    r = np.hypot(*pts.T)
    assert r.max() < 1.0
    assert abs(np.mean(r < 0.5) - 0.25) < 0.005  # a quarter of the area inside r = 1/2
    assert np.abs(pts.mean(axis=0)).max() < 0.01


@pytest.mark.parametrize("z", [-6.5, 4.0])
def test_bundle_matches_the_reference_tracer(z):
    """Same rays, deterministic instead of random: the images agree to the tracer's own
    Monte-Carlo noise, the light is conserved and the centroid agrees."""
    pos = np.array([[0.31, -0.22, z]])
    ref = trace_particles(CAM, pos, 1000.0, 200_000, seed=5, blur_px=0.8).ravel()
    image, _ = rendered(RayBundle.of(CAM, rays=3000, blur_px=0.8), pos, 1000.0)
    assert image.sum() == pytest.approx(ref.sum(), rel=2e-3)
    assert np.linalg.norm(image - ref) / np.linalg.norm(ref) < 0.08
    cols = np.arange(ref.size) % CAM.pixels[0]
    rows = np.arange(ref.size) // CAM.pixels[0]
    for coord in (cols, rows):
        assert (coord * image).sum() / image.sum() == pytest.approx(
            (coord * ref).sum() / ref.sum(), abs=0.05)


@pytest.mark.parametrize("axis, step", [(0, 2e-4), (1, 2e-4), (2, 2e-3)])
def test_derivatives_match_finite_differences(axis, step):
    bundle = RayBundle.of(CAM, rays=500, blur_px=0.8)
    pos = np.array([[0.12, 0.4, -5.0], [-0.5, 0.1, 7.0]])
    shift = np.zeros(3)
    shift[axis] = step
    _, rows = rendered(bundle, pos, 50.0)
    _, plus = rendered(bundle, pos, 50.0, shift)
    _, minus = rendered(bundle, pos, 50.0, -shift)
    numeric = (plus[0] - minus[0]) / (2 * step)
    assert np.linalg.norm(rows[1 + axis] - numeric) < 0.03 * np.linalg.norm(numeric)
    assert np.allclose(rows[4] * 50.0, rows[0])  # d/dI is the unit image


def noisy_image(positions: np.ndarray, seed: int) -> np.ndarray:
    """A ray-traced raw image: 0.8 px blur, a dark level of 20 counts and read noise."""
    img = trace_particles(CAM, positions, 4000.0, 40_000, seed=seed, blur_px=0.8)
    return img + 20.0 + np.random.default_rng(seed).normal(0.0, 1.0, img.shape)


def test_fit_recovers_out_of_focus_particles():
    """Started 1.5 voxels off in depth (0.3 laterally), the fit comes back within a few
    tenths of a voxel, far better than the start; its sigma shrinks below the prior."""
    rng = np.random.default_rng(1)
    true = np.column_stack([rng.uniform(-1.5, 1.5, 6), rng.uniform(-1.2, 1.2, 6),
                            [-8.0, -6.0, -4.0, 4.0, 6.0, 8.0]])
    start = true + np.array([0.3, -0.3, 1.5]) * VOXEL
    fit = ImageFit(CAM, GRID, [noisy_image(true, 3)], ImageFitSettings(rays=400))
    out = fit.fit(0, start)
    err = np.abs(out.positions - true) / VOXEL
    assert err[:, 2].max() < 0.4, err
    assert err[:, :2].max() < 0.15, err
    assert np.all(out.sigma[:, 2] / VOXEL[2] < 0.5)
    assert out.intensities == pytest.approx(4000.0, rel=0.1)


def test_in_focus_particle_keeps_its_prior():
    """A particle in the focal plane lights one lens: its depth is not in the image, so
    the fit reports the prior's depth uncertainty and stays near its start."""
    true = np.array([[0.2, 0.1, 0.0]])
    start = true + np.array([0.0, 0.0, 1.0]) * VOXEL
    fit = ImageFit(CAM, GRID, [noisy_image(true, 4)])
    out = fit.fit(0, start)
    assert out.sigma[0, 2] / VOXEL[2] > 0.8
    assert abs(out.positions[0, 2] - start[0, 2]) / VOXEL[2] < 1.5


def test_dark_image_leaves_peaks_in_place():
    fit = ImageFit(CAM, GRID, [np.full((CAM.pixels[1], CAM.pixels[0]), 20.0)])
    peaks = np.array([[10.2, 8.7, 40.1], [30.0, 20.5, 120.3]])
    assert np.allclose(fit.refine(0, peaks), peaks, atol=1e-6)
    assert fit.refine(0, np.zeros((0, 3))).shape == (0, 3)
    still = ImageFit(CAM, GRID, [noisy_image(GRID.from_index(peaks), 2)],
                     ImageFitSettings(iterations=0))
    assert np.allclose(still.refine(0, peaks), peaks)  # no iterations: the peaks as given


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="shape"):
        ImageFit(CAM, GRID, [np.zeros((5, 5))])
    with pytest.raises(ValueError, match="rays"):
        RayBundle.of(CAM, rays=3)
    with pytest.raises(ValueError, match="blur_px"):
        RayBundle.of(CAM, blur_px=float("nan"))
    with pytest.raises(ValueError, match="iterations"):
        ImageFitSettings(iterations=-1)
    with pytest.raises(ValueError, match="damping"):
        ImageFitSettings(damping=0.0)


def test_a_known_background_gives_the_fits_own_images():
    """The median and noise a reconstruction removed (``ReconstructionInfo``), given to
    the fit, give exactly the images and noise it computes itself; bad ones are named."""
    from plenocl.reconstruction.images import prepare_image
    from plenocl.reconstruction.settings import ReconstructionSettings

    class Optics:  # the camera alone: prepare_image asks nothing else without skip_dark
        camera = CAM

    raws = [noisy_image(np.array([[0.1, 0.2, z]]), seed) for z, seed in ((-5.0, 6), (3.0, 7))]
    known = []
    for raw in raws:
        prepared = prepare_image(raw, Optics, ReconstructionSettings(skip_dark=False))
        known.append((prepared.background, prepared.noise))
    assert all(med > 0 and noise > 0 for med, noise in known)  # a dark level and noise
    own = ImageFit(CAM, GRID, raws)
    given = ImageFit(CAM, GRID, raws, backgrounds=known)
    for (img, noise), (img_k, noise_k) in zip(own.images, given.images, strict=True):
        assert np.array_equal(img.values, img_k.values) and img.scale == img_k.scale
        assert noise == noise_k
    with pytest.raises(ValueError, match="2 images"):
        ImageFit(CAM, GRID, raws, backgrounds=known[:1])
    with pytest.raises(ValueError, match="finite"):
        ImageFit(CAM, GRID, raws, backgrounds=[(float("nan"), 1.0), known[1]])


@pytest.mark.parametrize("kind", ["float", "integer", "dark-subtracted"])
def test_a_reconstructions_background_free_image_is_the_fits_own(kind):
    """The image a reconstruction's solver reads, as it hands it to the fit
    (``PreparedImage.fit_image``, ``ReconstructionInfo.background_free``), is the one
    the fit makes from the raw image and the same background, bit for bit (a camera's
    integers, floats, a dark frame subtracted: background 0): values and scale, and the
    image they stand for within float32 rounding of ``max(I - median, 0)``; none where
    the reconstruction smoothed the image or masked pixels, or removed no background;
    wrong ones are refused by name."""
    import dataclasses

    from plenocl.reconstruction.images import prepare_image
    from plenocl.reconstruction.settings import ReconstructionSettings

    class Optics:  # the camera alone: prepare_image asks nothing else without skip_dark
        camera = CAM

    raw = noisy_image(np.array([[0.1, 0.2, -2.0]]), 8)
    if kind == "integer":
        raw = np.round(raw).astype(np.uint16)
    elif kind == "dark-subtracted":
        raw = raw - np.float32(np.median(raw))  # pixels below zero: background 0
    rec = ReconstructionSettings(skip_dark=False)
    prepared = prepare_image(raw, Optics, rec)
    known = (prepared.background, prepared.noise)
    assert (known[0] == 0.0) == (kind == "dark-subtracted")
    own = ImageFit(CAM, GRID, [raw], backgrounds=[known])
    free = prepared.fit_image()
    given = ImageFit(CAM, GRID, [raw], backgrounds=[known], background_free=[free])
    assert free.values is prepared.image and free.on_device is None
    for img in (own.images[0][0], given.images[0][0]):
        assert np.array_equal(img.values, free.values) and img.scale == free.scale
    assert own.images[0][1] == given.images[0][1]
    exact = np.maximum(raw.astype(np.float64) - known[0], 0.0)
    np.testing.assert_allclose(free.image(), exact, rtol=2 * tol.ROUNDING,
                               atol=2 * tol.ROUNDING * exact.max())
    for other in (dataclasses.replace(rec, smooth_px=1.0), dataclasses.replace(
            rec, background=None) if kind != "dark-subtracted" else None):
        if other is not None:
            assert prepare_image(raw, Optics, other).fit_image() is None
    seen = np.ones(raw.shape, bool)
    assert prepare_image(raw, Optics, rec, seen).fit_image() is None
    for bad, known_bad in ((free.replace(values=free.values.astype(np.float64)), known),
                           (free.replace(values=free.values[1:]), known),
                           (free.replace(scale=0.0), known), (free.values, known),
                           (free.replace(on_device=free.values[1:]), known),
                           (free.replace(on_device=free.values.astype(np.float64)), known),
                           (free, None)):
        with pytest.raises(ValueError, match="background_free"):
            ImageFit(CAM, GRID, [raw], backgrounds=[known_bad], background_free=[bad])
    for known_bad in ((known[0], float("nan")), (known[0], -1.0), (float("nan"), known[1])):
        with pytest.raises(ValueError, match="finite median and a finite non-negative noise"):
            ImageFit(CAM, GRID, [raw], backgrounds=[known_bad], background_free=[free])


def test_per_particle_peaks_match_the_unsorted_form():
    """The residual noise's per-particle peak by runs of the sorted particle ids equals
    ``np.maximum.at`` (sorted, unsorted, a particle without elements, none at all)."""
    from plenocl.piv.imagefit import _peaks

    rng = np.random.default_rng(5)
    for n in (1, 7, 40):
        pid = np.sort(rng.integers(0, n, 500))
        pid = pid[pid != n // 2] if n > 1 else pid
        value = rng.random(len(pid))
        for ids in (pid, rng.permutation(pid)):
            want = np.zeros(n)
            np.maximum.at(want, ids, value)
            np.testing.assert_array_equal(_peaks(value, ids, n), want)
    assert not _peaks(np.zeros(0), np.zeros(0, int), 3).any()


def test_refined_peaks_carry_the_fits_uncertainty_in_voxels():
    """``refine_pair`` returns each fit's posterior standard deviation on the grid (mm
    over the voxel size), and it says what the window means weigh by: a particle in the
    focal plane, whose image is one lens, is placed laterally several times less surely
    than one out of focus, whose image spans lenses (about 0.13 against 0.004 voxel)."""
    true = np.array([[0.2, 0.1, 0.0], [-0.4, 0.3, -6.0]])
    fit = ImageFit(CAM, GRID, [noisy_image(true, 6)] * 2, ImageFitSettings(rays=400))
    peaks = GRID.to_index(true + np.array([0.2, -0.2, 0.5]) * VOXEL)
    first, second = fit.refine_pair(peaks, peaks)
    want = fit.fit(0, GRID.from_index(peaks))
    np.testing.assert_allclose(first.sigma, want.sigma / VOXEL, rtol=1e-9)
    np.testing.assert_allclose(first.positions, GRID.to_index(want.positions), rtol=1e-9)
    np.testing.assert_allclose(second.sigma, first.sigma, rtol=1e-9)  # the same image
    assert np.all(first.sigma[0, :2] > 10 * first.sigma[1, :2]), first.sigma


def test_a_pairs_second_fit_runs_on_one_kept_thread_and_ends_before_it_returns(
        monkeypatch):
    """``refine_pair`` fits the second exposure on a helper thread the calling thread
    keeps from pair to pair (its kernels fetched once), and returns or raises only when
    that fit has ended: an error in the first fit waits for the second."""
    import threading
    import time

    from plenocl.piv import imagefit

    monkeypatch.setattr(imagefit, "thread_count", lambda: 2)
    threads, ended = [], []

    def fitted(fit, grid, index, peaks):
        if index == 1:
            threads.append(threading.current_thread())
            time.sleep(0.2)
            ended.append(index)
        elif peaks is None:
            raise RuntimeError("the first fit failed")
        return index

    monkeypatch.setattr(imagefit, "refined_peaks", fitted)
    fit = object.__new__(ImageFit)
    fit.grid = GRID
    assert ImageFit.refine_pair(fit, np.zeros((0, 3)), np.zeros((0, 3))) == (0, 1)
    assert ImageFit.refine_pair(fit, np.zeros((0, 3)), np.zeros((0, 3))) == (0, 1)
    assert threads[0] is threads[1] is not threading.current_thread()
    ended.clear()
    with pytest.raises(RuntimeError, match="first fit failed"):
        ImageFit.refine_pair(fit, None, np.zeros((0, 3)))
    assert ended == [1]  # the second fit had ended when the error came out


def test_the_posterior_covariance_leans_with_the_line_of_sight():
    """Off the axis one camera places a particle worst along its line of sight, which
    leans by ``r / s_o``: the fit's posterior covariance has its long axis on that line
    (within a third of the lean, where the z axis is the whole lean off), about 16 times
    the short ones; ``sigma`` is its diagonal's root, and ``refine_pair`` gives it in
    voxels²."""
    true = np.array([[2.4, 0.3, -6.0], [-2.4, -0.5, -6.0], [2.4, 0.3, 6.0]])
    fit = ImageFit(CAM, GRID, [noisy_image(true, 7)] * 2, ImageFitSettings(rays=400))
    start = true + np.array([0.2, -0.2, 0.5]) * VOXEL
    out = fit.fit(0, start)
    cov = out.covariance
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2))
    np.testing.assert_allclose(out.sigma, np.sqrt(np.diagonal(cov, axis1=1, axis2=2)))
    values, vectors = np.linalg.eigh(cov)
    assert np.all(values > 0) and np.all(values[:, 2] > 100 * values[:, 1]), values
    lines = line_of_sight(CAM, true)
    off_line = np.arccos(np.abs(np.einsum("ni,ni->n", vectors[:, :, 2], lines)))
    lean = np.arccos(np.abs(lines[:, 2]))
    assert np.all(lean > np.radians(1.0)) and np.all(off_line < lean / 3), (off_line, lean)
    first, _ = fit.refine_pair(GRID.to_index(start), GRID.to_index(start))
    np.testing.assert_allclose(first.covariance, cov / np.outer(VOXEL, VOXEL), rtol=1e-9)


def scaled_normals(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Normal matrices ``D M D`` ``(n, 4, 4)`` of well-conditioned ``M`` and diagonal
    ``D`` of powers of two from 2^-20 to 2^20 (a fit's axes in millimetres and counts
    differ so; the scaling is exact in floating point), and the exact position blocks of
    their inverses, ``D^-1 M^-1 D^-1``."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 12, 4))
    m = np.einsum("nki,nkj->nij", a, a)
    d = 2.0 ** rng.integers(-20, 21, size=(n, 4))
    outer = d[:, :, None] * d[:, None, :]
    return (m * outer), (np.linalg.inv(m) / outer)[:, :3, :3]


def test_the_posterior_covariance_is_the_inverse_across_axes_of_any_scale():
    """Axes 2^40 apart (condition numbers to 1e24): the covariance is the exact inverse's
    position block to float64 rounding, where the pseudo-inverse drops the small
    singular values (errors of order one); exactly symmetric."""
    normal, want = scaled_normals(64, 3)
    got = posterior_covariance(normal)
    scale = np.abs(want).max(axis=(1, 2), keepdims=True)
    np.testing.assert_array_less(np.abs(got - want) / scale, 1e-12)
    np.testing.assert_array_equal(got, np.swapaxes(got, 1, 2))
    pinv = np.linalg.pinv(normal)[:, :3, :3]
    assert np.max(np.abs(pinv - want) / scale) > 1e-3  # what it replaced could not


def test_a_particle_lighting_no_pixel_keeps_its_positions_prior():
    """A matrix whose intensity row and column are zero (the particle lights no pixel)
    takes the pseudo-inverse beside the others: its position block is the inverse of
    the position block, the others' their own; a NaN diagonal still raises (the
    pseudo-inverse's ``LinAlgError``), and negative or subnormal diagonals give no
    warning."""
    normal, want = scaled_normals(5, 4)
    blind = normal.copy()
    blind[2, 3, :] = blind[2, :, 3] = 0.0
    got = posterior_covariance(blind)
    scale = np.abs(want).max(axis=(1, 2), keepdims=True)
    keep = [0, 1, 3, 4]
    np.testing.assert_array_less(np.abs(got[keep] - want[keep]) / scale[keep], 1e-12)
    # the pseudo-inverse's float64 accuracy at axes 2^40 apart
    np.testing.assert_allclose(got[2], np.linalg.inv(blind[2, :3, :3]), rtol=1e-6)
    singular = normal[:2].copy()
    singular[1] = np.outer([1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0])
    got = posterior_covariance(singular)  # the stack refused: all by the pseudo-inverse
    np.testing.assert_allclose(got[1], np.linalg.pinv(singular[1])[:3, :3], rtol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        posterior_covariance(np.full((1, 4, 4), np.nan))
    odd = normal[:2].copy()
    odd[0, 3, 3], odd[1, 3, 3] = -1.0, 1e-320
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = posterior_covariance(odd)
    np.testing.assert_allclose(got, np.linalg.pinv(odd)[:, :3, :3], rtol=1e-6)


def leaning_equations(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal equations ``(n, 4, 4)``, right-hand sides ``(n, 4)`` and offsets ``(n, 3)``
    mm of particles on the axis: one camera's, the depth (third unknown) known about 16
    times worse than the lateral position."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(n, 40, 4)) * np.array([30.0, 30.0, 2.0, 1.0])
    normal = np.einsum("nki,nkj->nij", jac, jac)
    rhs = np.einsum("nki,nk->ni", jac, rng.normal(size=(n, 40)))
    return normal, rhs, rng.normal(size=(n, 3)) * 0.01


def test_the_fit_steps_alike_in_every_line_of_sight_frame():
    """The damped step of a particle whose line of sight leans is the step of the same
    equations on the axis, turned onto its line, and so is its posterior covariance: the
    prior, the Levenberg-Marquardt damping and the step bound hold in the line's frame,
    so off the axis the fit converges along its line as fast as on it. (Damping by the
    grid's own diagonal, the rule before, fails this: its steps along lines leaning
    0.13-0.3 rad were 0.16-0.5 of the turned ones.) On the axis the step is the damped
    solve with the prior."""
    n = 7
    normal, rhs, offset = leaning_equations(n, 3)
    prior = np.asarray(PRIOR_VOXELS) * VOXEL
    axis = np.broadcast_to(np.eye(3), (n, 3, 3))
    steps, intensity, cov = sight_steps(normal, rhs, offset, prior, axis, 0.1, 3)
    weights = 1.0 / prior ** 2
    posterior = normal.copy()
    posterior[:, [0, 1, 2], [0, 1, 2]] += weights
    damped = posterior + 0.1 * np.einsum("ni,ij->nij",
                                          np.diagonal(posterior, axis1=1, axis2=2), np.eye(4))
    plain = np.linalg.solve(damped, (rhs - np.pad(weights * offset, ((0, 0), (0, 1))))[..., None])
    bound = np.asarray(MAX_STEP_VOXELS) * VOXEL
    np.testing.assert_allclose(steps, np.clip(plain[:, :3, 0], -bound, bound), rtol=1e-9)
    np.testing.assert_allclose(intensity, plain[:, 3, 0], rtol=1e-9)
    np.testing.assert_allclose(cov, np.linalg.inv(posterior)[:, :3, :3], rtol=1e-7)
    lean = np.linspace(0.05, 0.3, n)
    lines = np.stack([np.sin(lean) * np.cos(3 * lean), np.sin(lean) * np.sin(3 * lean),
                      np.cos(lean)], axis=1)
    frames = sight_frames(lines)
    turn = np.zeros((n, 4, 4))
    turn[:, :3, :3], turn[:, 3, 3] = frames, 1.0
    turned = sight_steps(np.einsum("nij,njk,nlk->nil", turn, normal, turn),
                         np.einsum("nij,nj->ni", turn, rhs),
                         np.einsum("nij,nj->ni", frames, offset), prior, frames, 0.1, 3)
    np.testing.assert_allclose(turned[0], np.einsum("nij,nj->ni", frames, steps),
                               atol=1e-9 * np.abs(steps).max())
    np.testing.assert_allclose(turned[1], intensity, rtol=1e-7)
    np.testing.assert_allclose(turned[2], np.einsum("nij,njk,nlk->nil", frames, cov, frames),
                               atol=1e-9 * np.abs(cov).max())


def test_each_particles_step_and_covariance_are_its_own_whatever_it_is_solved_with():
    """The damping's floor was the stack's largest diagonal and one singular matrix sent
    its whole stack to the pseudo-inverse, so a particle's step depended on the others
    solved with it (a batch's field moved 0.22 voxel with the fit's particles per launch):
    solved one at a time, in chunks of 3, or all at once, the same bits."""
    rng = np.random.default_rng(3)
    n = 12
    a = rng.normal(size=(n, 4, 4))
    normal = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(4)
    scales = np.array([1e6, 1e6, 1e5, 1e-4])   # mm and counts: many decades apart
    normal *= np.sqrt(scales)[:, None] * np.sqrt(scales)[None, :]
    normal[4] *= 1e9                          # one much larger particle (the stack's max)
    normal[7] = np.diag([1e6, 1e6, 1e5, 0.0])  # an unseen intensity: singular
    rhs = rng.normal(size=(n, 4))
    offset = rng.normal(size=(n, 3)) * 0.01
    frames = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    runs = [sight_steps(normal, rhs, offset, (0.02, 0.02, 0.2), frames, 0.01, chunk)
            for chunk in (1, 3, n)]
    for got in runs[1:]:
        for x, y in zip(got, runs[0]):
            np.testing.assert_array_equal(x, y)
    alone = np.concatenate([posterior_covariance(normal[k:k + 1]) for k in range(n)])
    np.testing.assert_array_equal(posterior_covariance(normal), alone)
