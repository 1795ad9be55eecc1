"""The state-space track smoother and the neighbours' velocity prior (docs/design.md
§7.3): against a dense least-squares reference, exact on what they model, honest about
their deviations, and refusing what cannot run."""

import numpy as np
import pytest

from plenocl.ptv import neighbour_velocity, smooth_states
from plenocl.reference.tracking import smooth_states_reference


def _tracks(n=40, frames=9, seed=0, noise=0.05):
    """Tracks of varied spans (some with a gap) moving at constant velocity, their
    measurements with ``noise`` and stated deviations between half and twice it."""
    rng = np.random.default_rng(seed)
    start, velocity = rng.uniform(-5, 5, (n, 1, 3)), rng.uniform(-1, 1, (n, 1, 3))
    truth = start + velocity * np.arange(frames)[None, :, None]
    sigma = noise * rng.uniform(0.5, 2.0, truth.shape)
    measured = truth + sigma * rng.standard_normal(truth.shape)
    for i in range(n):
        lo = rng.integers(0, frames - 2)
        hi = rng.integers(lo + 2, frames + 1)
        measured[i, :lo], measured[i, hi:] = np.nan, np.nan
        if hi - lo > 4 and i % 3 == 0:
            measured[i, lo + 2] = np.nan
    return truth, velocity, measured, sigma


def test_state_smoother_matches_the_dense_reference_with_gaps_and_priors():
    _, velocity, measured, sigma = _tracks()
    rng = np.random.default_rng(1)
    prior = np.where(rng.random(measured.shape) < 0.7, velocity + 0.1, np.nan)
    prior_sigma = rng.uniform(0.05, 0.5, measured.shape)
    q = (0.02, 0.05, 0.1)
    fit = smooth_states(measured, sigma, q, prior, prior_sigma)
    ref = smooth_states_reference(measured, sigma, q, prior, prior_sigma)
    for got, want in zip((fit.positions, fit.velocities, fit.accelerations), ref[:3]):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    for got, want in zip((fit.position_sigma, fit.velocity_sigma, fit.acceleration_sigma),
                         ref[3:]):
        np.testing.assert_allclose(got / fit.birge, want, rtol=1e-8)


def test_state_smoother_is_exact_on_constant_velocity_and_bridges_a_poor_frame():
    truth, velocity, _, _ = _tracks(n=5, frames=7, noise=0.0)
    measured, sigma = truth.copy(), np.full(truth.shape, 0.01)
    measured[:, 3, 2] += 3.0     # one frame's depth far off, and said to be poor
    sigma[:, 3, 2] = 100.0
    fit = smooth_states(measured, sigma, 0.01)
    np.testing.assert_allclose(fit.positions, truth, atol=1e-3)
    np.testing.assert_allclose(fit.velocities, np.broadcast_to(velocity, truth.shape),
                               atol=1e-3)
    np.testing.assert_array_equal(fit.birge, 1.0)  # residuals within the stated noise


def test_a_tight_velocity_prior_sets_the_velocity_and_none_changes_nothing():
    _, _, measured, sigma = _tracks(seed=2)
    plain = smooth_states(measured, sigma, 0.05)
    none = smooth_states(measured, sigma, 0.05, np.full(measured.shape, np.nan),
                         np.full(measured.shape, np.inf))
    np.testing.assert_array_equal(plain.velocities, none.velocities)
    tight = smooth_states(measured, sigma, 0.05, np.full(measured.shape, 0.25),
                          np.full(measured.shape, 1e-6))
    seen = np.isfinite(measured)
    np.testing.assert_allclose(tight.velocities[seen], 0.25, atol=1e-4)


def test_state_smoother_scales_its_deviations_when_the_noise_is_larger_than_stated():
    """Measurements three times noisier than stated: the deviations are scaled by about
    3 (Birge's ratio) and then cover about 68 % of the velocity errors."""
    truth, velocity, measured, sigma = _tracks(n=2000, seed=3)
    noisy = truth + 3 * (measured - truth)
    fit = smooth_states(noisy, sigma, 1e-4)
    assert np.all((fit.birge > 2.6) & (fit.birge < 3.4))
    z = (fit.velocities - velocity) / fit.velocity_sigma
    assert 0.6 < np.mean(np.abs(z[np.isfinite(z)]) < 1) < 0.76


def test_state_smoother_refuses_a_bad_acceleration_noise():
    _, _, measured, sigma = _tracks(n=3)
    for bad in (0.0, -1.0, np.nan, (0.1, 0.0, 0.1)):
        with pytest.raises(ValueError, match="acceleration noise"):
            smooth_states(measured, sigma, bad)


def _field(n=300, frames=2, seed=4):
    """Tracks in a linear velocity field ``v = a + B x`` (voxels of 0.1, 0.2, 0.3 mm)."""
    rng = np.random.default_rng(seed)
    scale = np.array([0.1, 0.2, 0.3])
    positions = rng.uniform(0, 20, (n, frames, 3)) * scale
    a, b = np.array([0.5, -0.2, 0.1]), rng.normal(0, 0.01, (3, 3))
    velocities = a + (positions / scale) @ b.T
    return positions, velocities, scale


def test_neighbours_give_a_linear_field_exactly_without_the_tracks_own_velocity():
    positions, velocities, scale = _field()
    sigma = np.full(velocities.shape, 0.01)
    wrong = velocities.copy()
    wrong[7] += 5.0                     # one track's own velocity far off
    prior, prior_sd = neighbour_velocity(positions, wrong, sigma, scale, 12)
    np.testing.assert_allclose(prior[7], velocities[7], atol=1e-9)
    others = np.arange(len(prior)) != 7
    far = np.linalg.norm(positions / scale - positions[7] / scale, axis=2) > 6
    keep = others[:, None] & far    # fits that did not take track 7 as a neighbour
    np.testing.assert_allclose(prior[keep], velocities[keep], atol=1e-9)
    assert np.median(prior_sd[keep]) < 0.01   # a fit of 12 sharper than one neighbour


def test_neighbours_state_a_wider_prior_where_the_flow_is_not_linear():
    positions, velocities, scale = _field(seed=5)
    sigma = np.full(velocities.shape, 0.01)
    rng = np.random.default_rng(6)
    rough = velocities + rng.normal(0, 0.1, velocities.shape)    # 10 x the stated noise
    prior, prior_sd = neighbour_velocity(positions, rough, sigma, scale, 12)
    z = (prior - rough) / np.hypot(prior_sd, 0.1)
    assert np.median(prior_sd) > 0.02                 # the scatter widened the prior
    assert 0.55 < np.mean(np.abs(z) < 1) < 0.85


def test_neighbours_leave_sparse_frames_without_a_prior_and_refuse_too_few():
    positions, velocities, scale = _field(n=10)
    prior, prior_sd = neighbour_velocity(positions, velocities, np.full(velocities.shape, 0.01),
                                         scale, 12)
    assert np.all(np.isnan(prior)) and np.all(np.isnan(prior_sd))
    for bad in (4, 2, 6.5):
        with pytest.raises(ValueError, match="more than 4 neighbours"):
            neighbour_velocity(positions, velocities, velocities, scale, bad)


def test_smooth_tracks_carries_the_focal_zone_by_the_neighbours_depth_prior_only():
    """Tracks moving uniformly at the paper's optics, each frame's depth within 1 mm of
    the focal plane off by up to 1.5 voxels, varying with depth differently for each
    track (as the fits' errors there, which state about 1.2 voxels), and by 0.1 voxel
    elsewhere: the neighbours' prior brings the focal zone's depth steps within a
    fraction of what the tracks' own frames give; the lateral positions are the same
    either way."""
    from types import SimpleNamespace

    from plenocl.bench.accuracy_section import paper_optics
    from plenocl.pipeline import TrackSettings, smooth_tracks

    cam, grid = paper_optics((24, 16))
    voxel = np.asarray(grid.spacing[::-1])
    rng = np.random.default_rng(7)
    n, frames, step = 300, 8, np.array([1.0, -0.5, 1.2]) * voxel
    start = rng.uniform([grid.x[0], grid.y[0], -6], [grid.x[1], grid.y[1], 6], (n, 3))
    truth = start[:, None] + step * np.arange(frames)[None, :, None]
    focal = np.abs(truth[..., 2]) < 1.0
    noise = np.where(focal[..., None], [0.05, 0.05, 0.5], [0.05, 0.05, 0.1]) * voxel
    sigma = np.where(focal[..., None], [0.05, 0.05, 1.2], [0.05, 0.05, 0.1]) * voxel
    measured = truth + noise * rng.standard_normal(truth.shape)
    phase = rng.uniform(0, 2 * np.pi, (n, 1))
    measured[..., 2] += np.where(focal, 1.5 * voxel[2] * np.sin(truth[..., 2] / (3 * voxel[2])
                                                                  + phase), 0.0)
    proj = SimpleNamespace(camera=cam, grid=grid)
    args = (measured, sigma, np.ones((n, frames)), 1.0, proj)
    with_prior = smooth_tracks(*args, TrackSettings())
    own = smooth_tracks(*args, TrackSettings(neighbours=0))
    zone = focal[:, 1:] & focal[:, :-1]

    def depth_rms(tracks):
        err = np.diff(tracks.positions[..., 2], axis=1) / voxel[2] - step[2] / voxel[2]
        return np.sqrt(np.mean(err[zone] ** 2))

    assert zone.sum() > 50
    assert depth_rms(with_prior) < min(0.15, 0.5 * depth_rms(own))
    np.testing.assert_array_equal(with_prior.positions[..., :2], own.positions[..., :2])


def test_state_smoother_matches_the_reference_on_a_long_series_and_skips_bad_frames():
    """120 frames (the block elimination over the frames against the dense solve), a
    frame whose deviation is infinite counting as missing, a lone particle without
    velocity."""
    _, _, measured, sigma = _tracks(n=6, frames=120, seed=8)
    measured[:, :, :] = np.cumsum(np.random.default_rng(9).normal(0, 0.3, measured.shape),
                                  axis=1)
    sigma[0, 10] = np.inf
    measured[5] = np.nan
    measured[5, 7] = 1.0
    fit = smooth_states(measured, sigma, 0.2)
    cut = measured.copy()
    cut[0, 10] = np.nan
    ref = smooth_states_reference(cut, sigma, 0.2)
    np.testing.assert_allclose(fit.positions[:5], ref[0][:5], atol=1e-8)
    np.testing.assert_allclose(fit.velocities[:5], ref[1][:5], atol=1e-8)
    np.testing.assert_allclose(fit.velocity_sigma[:5] / fit.birge, ref[4][:5], rtol=1e-8)
    np.testing.assert_allclose(fit.acceleration_sigma[:5] / fit.birge, ref[5][:5], rtol=1e-7)
    assert np.all(np.isnan(fit.positions[0, 10])) and np.all(np.isnan(fit.velocities[5]))


def test_neighbours_leave_out_the_track_itself_when_tied_and_refuse_flat_neighbourhoods():
    positions, velocities, scale = _field(n=60, frames=1, seed=10)
    positions[1], velocities[1] = positions[0], velocities[0]   # two tracks at one place
    sigma = np.full(velocities.shape, 0.01)
    wrong = velocities.copy()
    wrong[1] += 5.0                        # the second of the tied pair's own velocity
    prior, _ = neighbour_velocity(positions, wrong, sigma, scale, 12)
    np.testing.assert_allclose(prior[1], velocities[1], atol=1e-9)  # not its own (wrong)
    flat = positions.copy()
    flat[..., 2] = 1.0                     # every track in one depth plane
    prior, prior_sd = neighbour_velocity(flat, velocities, sigma, scale, 12)
    assert np.all(np.isnan(prior)) and np.all(np.isnan(prior_sd))


def test_smooth_tracks_velocities_scale_with_the_frame_interval():
    from types import SimpleNamespace

    from plenocl.bench.accuracy_section import paper_optics
    from plenocl.pipeline import smooth_tracks

    cam, grid = paper_optics((24, 16))
    truth, velocity, measured, sigma = _tracks(n=40, frames=8, seed=12)
    proj = SimpleNamespace(camera=cam, grid=grid)
    args = (measured, sigma, np.ones(measured.shape[:2]))
    one, half = (smooth_tracks(*args, dt, proj) for dt in (1.0, 0.5))
    np.testing.assert_allclose(half.velocities, 2 * one.velocities, rtol=1e-12)
    np.testing.assert_allclose(half.velocity_sigma, 2 * one.velocity_sigma, rtol=1e-12)
    np.testing.assert_array_equal(half.positions, one.positions)


def test_state_smoother_accelerations_follow_a_constantly_accelerating_particle():
    """Precise positions of a particle under constant acceleration: the velocities'
    central differences give it within 5 % away from the track's ends, where the
    one-sided differences of a constant-velocity model fall short, as their larger
    deviations say."""
    t = np.arange(9.0)[:, None]
    a, v0 = np.array([0.2, -0.1, 0.05]), np.array([1.0, 0.3, -0.2])
    measured = (0.5 * a * t**2 + v0 * t)[None]
    fit = smooth_states(measured, np.full(measured.shape, 1e-3), 0.5)
    np.testing.assert_allclose(fit.accelerations[0, 2:-2], np.broadcast_to(a, (5, 3)),
                               rtol=0.05)
    np.testing.assert_allclose(fit.velocities[0, 2:-2], (a * t + v0)[2:-2], atol=0.005)
    assert np.all(fit.acceleration_sigma[0, 0] > fit.acceleration_sigma[0, 4])


def test_particles_seen_twice_merge_into_the_brightest_and_distinct_ones_stay():
    from plenocl.peaks import merge_close

    index = np.array([[10.0, 10.0, 50.0],    # a particle
                      [10.3, 9.8, 54.0],     # seen again 4 voxels deeper: merged
                      [10.2, 10.5, 59.0],    # within the second's reach, not the first's
                      [11.0, 10.0, 50.0],    # one voxel aside: another particle
                      [30.0, 30.0, 20.0]])
    intensity = np.array([5.0, 3.0, 2.0, 4.0, 1.0])
    keep, merged = merge_close(index, intensity, (0.7, 0.7, 6.0))
    np.testing.assert_array_equal(keep, [True, False, True, True, True])
    assert merged[0] == 8.0 and merged[2] == 2.0 and merged[3] == 4.0
    keep, merged = merge_close(index, intensity, (0.7, 0.7, 0.0))
    assert keep.all() and np.array_equal(merged, intensity)


def test_a_prior_formed_in_no_frame_is_said():
    """Fewer tracks in every frame than ``neighbours``: the depth prior cannot be formed
    anywhere (the tracks are smoothed on their own frames, as with ``neighbours=0``), and
    a warning says so with the fix, instead of switching the prior off silently."""
    from types import SimpleNamespace

    from plenocl.bench.accuracy_section import paper_optics
    from plenocl.pipeline import TrackSettings, smooth_tracks

    cam, grid = paper_optics((24, 16))
    rng = np.random.default_rng(3)
    n, frames = 8, 6
    start = rng.uniform([grid.x[0], grid.y[0], 2.0], [grid.x[1], grid.y[1], 6.0], (n, 3))
    measured = start[:, None] + np.array([0.1, 0.0, 0.2]) * np.arange(frames)[None, :, None]
    sigma = np.full(measured.shape, 0.01)
    args = (measured, sigma, np.ones((n, frames)), 1.0, SimpleNamespace(camera=cam, grid=grid))
    with pytest.warns(UserWarning, match=r"prior was formed in no frame: it needs more than "
                                         r"neighbours = 12 .* the most in any frame is 8"):
        alone = smooth_tracks(*args, TrackSettings())
    np.testing.assert_array_equal(alone.positions, smooth_tracks(
        *args, TrackSettings(neighbours=0)).positions)
