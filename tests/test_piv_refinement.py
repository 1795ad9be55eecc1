"""Particle refinement of a correlation field (plenocl/piv/refinement.py): pairing the two
volumes' particles along the predictor, per-window means and their uncertainty."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenocl import Camera, Grid, piv3d
from plenocl.metrics import render_particles
from plenocl.piv import PIVResult
from plenocl.piv.devicemeans import FITTED, ILL_POSED, DeviceWindowMeans
from plenocl.piv.refinement import (
    FITTED_POSITION_SIGMA,
    FOCAL_SYSTEMATIC,
    GRADIENT_PAIRS,
    KEEP_FLOOR,
    ONE_SIGMA,
    POSITION_SIGMA,
    ROBUST_SPREAD,
    WEIGHT_FLOOR,
    FocalZone,
    ParticlePairs,
    depth_interpolation,
    near_median,
    pair_particles,
    predicted,
    refine_with_particles,
    seen_depth,
    window_estimate,
    window_means,
)
from plenocl.reference.refinement import depth_interpolation_reference, window_means_reference

GRID = Grid((48, 40, 56), x=(0, 56), y=(0, 40), z=(0, 48))  # 1 mm = 1 voxel
SHIFT = np.array([1.6, -0.7, 2.2])  # (x, y, z) voxels


def volumes(count: int, seed: int, jitter: float = 0.0, ghosts: int = 0):
    """Particles moved by SHIFT (each position off by ``jitter`` voxels RMS per axis in
    the second volume), and ``ghosts`` unrelated blobs in each volume."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform([3, 3, 3], [53, 37, 45], (count, 3))
    moved = pos + SHIFT + rng.normal(0, jitter, pos.shape)
    extra = [rng.uniform([3, 3, 3], [53, 37, 45], (ghosts, 3)) for _ in range(2)]
    a = render_particles(GRID, np.vstack([pos, extra[0]]) + 0.5, 1.0, sigma_vox=0.8)
    b = render_particles(GRID, np.vstack([moved, extra[1]]) + 0.5, 1.0, sigma_vox=0.8)
    return pos, a, b


@pytest.fixture(scope="module")
def scene():
    pos, a, b = volumes(150, seed=3, jitter=0.15, ghosts=40)
    return pos, a, b, piv3d(a, b, windows=(24, 16))


def test_the_predictor_is_read_between_and_beyond_window_centres(scene):
    field = scene[3]
    pts = np.array([[field.x[1] + 0.3, field.y[1], field.z[0]], [-5.0, 100.0, 60.0]])
    got = predicted(field, pts)
    assert got.shape == (2, 3)
    assert np.allclose(got, SHIFT, atol=0.3)  # a uniform field, inside and clamped beyond


def test_pairs_follow_the_particles_and_leave_ghosts_out(scene):
    pos, a, b, field = scene
    pairs = pair_particles(a, b, field)
    assert 120 <= len(pairs.displacements) <= 150  # most particles, not the 40 ghosts
    err = pairs.displacements - SHIFT
    assert np.median(np.abs(err)) < 0.2
    # the midpoints sit half-way along the motion
    nearest = np.min(np.linalg.norm(pairs.midpoints[:, None] - (pos + SHIFT / 2)[None],
                                    axis=-1), axis=1)
    assert np.median(nearest) < 0.2


def test_window_means_beat_the_correlation_and_their_sigma_covers_the_error(scene):
    """With 0.15 voxel of independent position noise per particle and 20 % ghosts, the
    per-window means of the pairs are closer to the truth than the correlation, and about
    68 % of their errors lie within the reported sigma."""
    _, a, b, field = scene
    refined = refine_with_particles(field, a, b)
    assert refined.refinement["refinement"] == "particles"
    assert refined.refinement["vectors"] >= 0.9 * field.u.size
    assert refined.valid.mean() >= 0.9
    err = {}
    inside = []
    for name, res in (("corr", field), ("pairs", refined)):
        e = np.stack([getattr(res, c) - s for c, s in zip("uvw", SHIFT)])
        err[name] = np.sqrt(np.nanmean(e ** 2))
    for c, s in zip("uvw", SHIFT):
        ok = np.isfinite(refined.sigma_u)
        inside.append(np.abs(getattr(refined, c)[ok] - s) <= getattr(refined, f"sigma_{c}")[ok])
    assert err["pairs"] < err["corr"]
    assert 0.5 <= np.mean(np.concatenate(inside)) <= 0.85


def test_windows_with_too_few_pairs_keep_the_correlation_and_masked_stay_masked():
    _, sa, sb = volumes(4, seed=5)
    res = piv3d(sa, sb, windows=(24, 16))
    res.masked[0, 0, 0] = True
    res.u[0, 0, 0] = np.nan
    refined = refine_with_particles(res, sa, sb, min_pairs=3)
    mean, _, count = window_means(pair_particles(sa, sb, res), res, min_pairs=3)
    keep = (count < 3) & ~refined.outlier  # the refined field is validated again
    assert keep.any()
    np.testing.assert_array_equal(refined.u[keep], res.u[keep])
    assert np.isnan(refined.u[0, 0, 0]) and not refined.valid[0, 0, 0]
    empty = refine_with_particles(res, np.zeros_like(sa), sb)
    same = ~empty.outlier
    np.testing.assert_array_equal(empty.u[same], res.u[same])
    assert empty.refinement["pairs"] == 0 and empty.refinement["vectors"] == 0
    # outliers are replaced, invalid and without sigma
    assert np.all(np.isnan(refined.sigma_u[refined.outlier]))
    assert not refined.valid[refined.outlier].any()


def test_the_one_sigma_quantile_is_the_normal_one():
    from scipy import stats

    assert stats.norm.cdf(1.0) == pytest.approx(ONE_SIGMA)


def test_a_gradient_across_sparse_windows_does_not_bias_their_means(scene):
    """A sheared field sampled by a few pairs per window: moved to each window's centre
    along the fitted local gradient, the pairs' mean is the field at the centre, exactly
    (noise-free), wherever the pairs happen to lie. The uncertainty is then only the
    particles' depth-position term carried through the gradient's depth column."""
    field = scene[3]
    rng = np.random.default_rng(8)
    mid = rng.uniform([0, 0, 0], [56, 40, 48], (300, 3))
    grad = np.array([[0.0, 0.02, -0.03], [0.01, 0.0, 0.0], [0.0, -0.04, 0.0]])
    disp = SHIFT + (mid - 20.0) @ grad.T
    mean, error, count = window_means(ParticlePairs(mid, disp), field)
    zz, yy, xx = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    centres = np.stack([xx, yy, zz], axis=-1)
    truth = np.moveaxis(SHIFT + (centres - 20.0) @ grad.T, -1, 0)
    ok = np.isfinite(mean[0])
    assert ok.mean() > 0.9 and count[ok].min() >= 3
    np.testing.assert_allclose(mean[:, ok], truth[:, ok], atol=1e-9)
    position = np.abs(grad[:, 2]) * POSITION_SIGMA[2]
    np.testing.assert_allclose(error[:, ok], position[:, None] * np.ones(ok.sum()), atol=1e-5)


def test_the_focal_zone_sits_at_z_0_and_spans_the_cameras_depth_resolution():
    from plenocl import Camera

    cam = Camera.paper_16mp()
    grid = Grid((150, 20, 30), x=(-3, 3), y=(-2, 2), z=(-10.0, 10.0))
    zone = FocalZone.of(cam, grid)
    assert zone.plane == pytest.approx(74.5)  # voxel 74.5's centre is z = 0
    assert zone.resolution * grid.spacing[0] == pytest.approx(cam.depth_resolution_mm)
    r = zone.resolution
    got = zone.ambiguity(zone.plane + np.array([0.0, -r, r, 2 * r, -3 * r]))
    np.testing.assert_allclose(got, FOCAL_SYSTEMATIC * r * np.array([1, 0.5, 0.5, 0, 0]),
                               atol=1e-9)


def collapsing_window(rng, true_w: float, n_out: int, n_in: int, zone: FocalZone):
    """A window's pairs: ``n_out`` out of focus measuring ``true_w`` with 1 voxel of
    noise, ``n_in`` at the focal plane whose depth displacement collapsed to 0."""
    d = np.zeros((n_out + n_in, 3))
    d[:n_out, 2] = true_w + rng.normal(0, 1.0, n_out)
    d[n_out:, 2] = rng.normal(0, 0.3, n_in)
    d[:, :2] = rng.normal(0, 0.1, (n_out + n_in, 2))
    depth = np.r_[zone.plane + 2.5 * zone.resolution + np.zeros(n_out),
                  zone.plane + rng.uniform(-1, 1, n_in)]
    return d, depth


def test_the_focal_zones_systematic_term_covers_pairs_that_collapsed():
    """Pairs whose depth displacement (0.6 voxel, about the zone's systematic term at
    the plane) collapsed at the focal plane pull the window's mean towards 0 together,
    which their scatter does not show; with the focal zone the depth uncertainty covers
    that error. The mean and the lateral components are untouched."""
    zone = FocalZone(plane=50.0, resolution=8.0)
    rng = np.random.default_rng(4)
    covered, covered_flat = [], []
    for _ in range(200):
        d, depth = collapsing_window(rng, 0.6, n_out=6, n_in=10, zone=zone)
        mean, sigma = window_estimate(d, depth, np.zeros((3, 3)), zone)
        flat, flat_sigma = window_estimate(d, depth, np.zeros((3, 3)), None)
        np.testing.assert_allclose(mean, d.mean(axis=0))
        np.testing.assert_allclose(flat, mean)
        np.testing.assert_allclose(sigma[:2], flat_sigma[:2])
        covered.append(abs(mean[2] - 0.6) <= sigma[2])
        covered_flat.append(abs(flat[2] - 0.6) <= flat_sigma[2])
    assert np.mean(covered_flat) < 0.5 <= 0.68 <= np.mean(covered)


def test_a_window_inside_the_focal_zone_reports_the_depth_it_cannot_see():
    """All pairs at the focal plane: the depth uncertainty is the zone's ambiguity, not
    the (small) scatter of collapsed pairs."""
    zone = FocalZone(plane=50.0, resolution=8.0)
    d, depth = collapsing_window(np.random.default_rng(5), 0.6, n_out=0, n_in=10, zone=zone)
    _, sigma = window_estimate(d, depth, np.zeros((3, 3)), zone)
    _, flat_sigma = window_estimate(d, depth, np.zeros((3, 3)), None)
    assert flat_sigma[2] < 0.3 < 0.6 < sigma[2]
    assert sigma[2] == pytest.approx(np.mean(zone.ambiguity(depth)), rel=0.05)


def test_fitted_particles_carry_the_smaller_position_term(scene):
    """With a linear gradient and noise-free pairs the uncertainty is the position term
    alone: the fitted particles' depth position (FITTED_POSITION_SIGMA) through it."""
    field = scene[3]
    rng = np.random.default_rng(9)
    mid = rng.uniform([0, 0, 0], [56, 40, 48], (300, 3))
    grad = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, -0.02], [0.0, 0.0, 0.0]])
    disp = SHIFT + (mid - 20.0) @ grad.T
    _, error, _ = window_means(ParticlePairs(mid, disp), field,
                               position_sigma=FITTED_POSITION_SIGMA)
    ok = np.isfinite(error[0])
    expected = np.abs(grad[:, 2]) * FITTED_POSITION_SIGMA[2]
    np.testing.assert_allclose(error[:, ok], expected[:, None] * np.ones(ok.sum()), atol=1e-5)
    assert FITTED_POSITION_SIGMA[2] < POSITION_SIGMA[2]


def grid_field(shape=(5, 6, 7), window=(8, 8, 8), step=4.0) -> PIVResult:
    """A field of ``shape`` window centres ``step`` voxels apart (the correlation's values
    do not enter :func:`window_means`)."""
    z, y, x = (3.5 + step * np.arange(n) for n in shape)
    ones = np.ones(shape, bool)
    zero = np.zeros(shape)
    return PIVResult(x, y, z, zero, zero, zero, ones, np.full(shape, np.nan), ~ones, ~ones,
                     window)


def awkward_pairs(case: str, rng) -> ParticlePairs:
    """Pairs that test the batched window means: sparse windows (many with exactly 3
    pairs), outliers beyond the median band, pairs on one plane or one line (rank-deficient
    gradient fits), midpoints on the windows' faces, none at all."""
    n = {"sparse": 70, "outliers": 600, "plane": 400, "line": 300, "faces": 500, "empty": 0}
    lo, hi = np.zeros(3), np.array([34.0, 30.0, 26.0])  # (x, y, z), a little beyond the grid
    mid = rng.uniform(lo, hi, (n[case], 3))
    if case == "plane":
        mid[:, 2] = 11.5  # every window's pairs share one depth
    if case == "line":
        mid[:, 1:] = [13.5, 11.5]
    if case == "faces":  # integers: |midpoint - centre| is exactly the half-window
        mid = np.round(mid - 0.5) + 0.5
    grad = np.array([[0.0, 0.03, -0.02], [0.02, 0.0, 0.01], [0.0, -0.04, 0.05]])
    disp = SHIFT + (mid - 15.0) @ grad.T + rng.normal(0, [0.1, 0.1, 0.5], mid.shape)
    bad = rng.random(len(mid)) < 0.1
    disp[bad] += rng.choice([-4.0, 4.0], (bad.sum(), 3))
    return ParticlePairs(mid, disp)


@pytest.mark.parametrize("case", ["sparse", "outliers", "plane", "line", "faces", "empty"])
@pytest.mark.parametrize("focus", [None, FocalZone(plane=12.0, resolution=5.0)])
@pytest.mark.parametrize("min_pairs", [2, 3])
@pytest.mark.parametrize("spread, weighted", [(ROBUST_SPREAD, False), (None, False),
                                              (None, True), (ROBUST_SPREAD, True)])
def test_window_means_equal_the_per_window_loop(case, focus, min_pairs, spread, weighted):
    """The batched window means against the per-window loop over local_gradient,
    near_median and window_estimate: the same counts, to float64 rounding the same
    means and uncertainties (rank-deficient fits take lstsq's minimum-norm solution),
    with the robust rule and with the search range alone, each with the pairs alike and
    weighted by uncertainties spread over two orders of magnitude."""
    rng = np.random.default_rng(len(case))
    pairs = awkward_pairs(case, rng)
    if weighted:
        sigma = 10 ** rng.uniform(-2.5, -0.5, pairs.displacements.shape)
        pairs = dataclasses.replace(pairs, sigma=sigma)
    field = grid_field()
    got = window_means(pairs, field, min_pairs, focus=focus, spread=spread)
    want = window_means_reference(pairs, field, min_pairs, focus=focus, spread=spread)
    np.testing.assert_array_equal(got[2], want[2])
    for a, b in zip(got[:2], want[:2]):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    if case == "sparse":  # windows with just enough pairs, and too few
        assert (want[2] == min_pairs).any() and np.isnan(want[0][0]).any()
    if case in ("outliers", "plane", "line"):  # gradient fits and pairs left out
        full = window_means_reference(pairs, field, min_pairs, search=(99.0,) * 3,
                                      spread=None)[2]
        assert (want[2] >= GRADIENT_PAIRS).any() and (want[2] < full).any()
    if case == "empty":
        assert not want[2].any() and np.isnan(want[0]).all()


@pytest.mark.parametrize("case", ["sparse", "outliers", "faces"])
@pytest.mark.parametrize("support", [1.5, 2.0])
def test_window_means_over_a_wider_support_equal_the_per_window_loop(case, support):
    """With a support box wider than the window (one camera's depth, DEPTH_SUPPORT) the
    batched means are the loop's, and each window holds at least the pairs its own box
    holds."""
    rng = np.random.default_rng(len(case) + 7)
    pairs = awkward_pairs(case, rng)
    pairs = dataclasses.replace(pairs, sigma=10 ** rng.uniform(-2.5, -0.5,
                                                               pairs.displacements.shape))
    field, focus = grid_field(), FocalZone(plane=12.0, resolution=5.0)
    got = window_means(pairs, field, 3, focus=focus, support=support)
    want = window_means_reference(pairs, field, 3, focus=focus, support=support)
    np.testing.assert_array_equal(got[2], want[2])
    for a, b in zip(got[:2], want[:2]):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    own = window_means_reference(pairs, field, 3, search=(99.0,) * 3, spread=None)[2]
    wide = window_means_reference(pairs, field, 3, search=(99.0,) * 3, spread=None,
                                  support=support)[2]
    assert (wide >= own).all() and (wide > own).any()


@pytest.mark.parametrize("case", ["sparse", "outliers", "empty"])
@pytest.mark.parametrize("support", [1.0, 2.0])
def test_window_means_of_some_windows_are_theirs_among_all(case, support):
    """``windows`` (the sparse windows' wide means, the seen depth's windows outside the
    blind zone) computes only those windows: each the same as among all of them, to the
    bit, and the others NaN with no pairs counted."""
    rng = np.random.default_rng(len(case) + 11)
    pairs = awkward_pairs(case, rng)
    pairs = dataclasses.replace(pairs, sigma=10 ** rng.uniform(-2.5, -0.5,
                                                               pairs.displacements.shape))
    field, focus = grid_field(), FocalZone(plane=12.0, resolution=5.0)
    wanted = rng.random(field.u.shape) < 0.3
    wanted[0] = True  # a whole plane of windows, and scattered ones
    every = window_means(pairs, field, 3, focus=focus, support=support)
    some = window_means(pairs, field, 3, focus=focus, support=support, windows=wanted)
    for a, b in zip(some, every):
        np.testing.assert_array_equal(a[..., wanted], b[..., wanted])
    assert np.isnan(some[0][:, ~wanted]).all() and not some[2][~wanted].any()
    if case != "empty":
        assert np.isfinite(every[0][:, ~wanted]).any()  # the others had means to leave out


def test_window_means_on_the_device_send_back_only_the_windows_with_pairs(queue):
    """A large field whose pairs fill a corner: the device's window means equal the
    host's, and what comes back is the listed windows' results, less than one double per
    window of the field (the gradients stay on the device; issue 46)."""
    from plenocl.bench.clprofile import OpenCLProfile

    pairs = awkward_pairs("outliers", np.random.default_rng(11))
    field = grid_field(shape=(20, 30, 40))
    device = DeviceWindowMeans(queue)
    want = window_means(pairs, field, 3)
    with OpenCLProfile() as prof:
        got = window_means(pairs, field, 3, device_means=device)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    np.testing.assert_array_equal(got[2], want[2])
    for a, b in zip(got[:2], want[:2]):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert 0 < np.count_nonzero(want[2]) < field.u.size / 10
    assert back < 8 * field.u.size


def test_window_gradients_send_back_one_byte_per_listed_window(queue):
    """The gradients' status crosses as a byte per listed window (the gradients stay on
    the device), and is the same status the host reads either way."""
    from plenocl.bench.clprofile import OpenCLProfile

    pairs = awkward_pairs("outliers", np.random.default_rng(13))
    every = len(pairs.midpoints)
    zero, one, two = (np.full(every, v, int) for v in (0, 1, 2))
    device = DeviceWindowMeans(queue)
    lists, _ = device.box_lists([(zero, two), (zero, one), (zero, one)], (1, 1, 2),
                                np.ones(2, bool))
    dev = device.pairs(pairs.midpoints, pairs.displacements, None, None)
    centres = device.device_centres(([14.0, 16.0], [15.0], [15.0]))
    args = (99.0,) * 3, None, (0.1, 0.1, 0.3), 3, 1e-4
    with OpenCLProfile() as prof:
        status, _ = device.device_gradients(dev, lists, centres, *args)
    assert sum(c.nbytes for c in prof.calls if c.kind == "d2h") == len(lists.win) == 2
    assert set(status) <= {FITTED, ILL_POSED} and FITTED in status


def test_box_lists_of_every_window_send_the_window_mask_once(queue):
    """Box lists asked for every window of the same grid again (each of a pair's
    refinement calls) send the mask of every window (a byte each) once, also after a
    subset's call (which sends its own); the lists are the same either way."""
    from plenocl.bench.clprofile import OpenCLProfile

    rng = np.random.default_rng(14)
    n, shape = 500, (6, 7, 9)
    x0 = rng.integers(0, 9, n)
    ranges = [(x0, x0 + 2), (rng.integers(0, 6, n),) * 2, (rng.integers(0, 5, n),) * 2]
    ranges[1] = (ranges[1][0], ranges[1][0] + 1)
    ranges[2] = (ranges[2][0], ranges[2][0] + 2)
    every, some = np.ones(6 * 7 * 9, bool), rng.random(6 * 7 * 9) < 0.5
    device = DeviceWindowMeans(queue)
    sent, got = [], []
    for wanted in (every, every, some, every):
        with OpenCLProfile() as prof:
            lists, count = device.box_lists(ranges, shape, wanted)
        sent.append(sum(c.nbytes for c in prof.calls if c.kind == "h2d"))
        got.append((lists.win.tolist(), lists.member.get().tolist(), count.tolist()))
    assert sent[1] + every.size == sent[0]
    assert sent[3] == sent[1]  # kept across a subset's call
    assert got[0] == got[1] == got[3]
    assert got[2][2] == np.where(some, got[0][2], 0).tolist()


def test_window_means_on_the_device_upload_the_same_pairs_once(queue):
    """Calls on the same pairs (a refinement's sparse windows after its lateral means)
    send them to the device once, and no per-pair range or window list; other pairs go
    up, and the first again after them; each call's means are the host's."""
    from plenocl.bench.clprofile import OpenCLProfile

    pairs = awkward_pairs("outliers", np.random.default_rng(12))
    fewer = pairs.subset(np.arange(len(pairs.midpoints)) % 3 > 0)
    field, device = grid_field(), DeviceWindowMeans(queue)
    moved = []
    for given in (pairs, pairs, fewer, pairs):
        with OpenCLProfile() as prof:
            got = window_means(given, field, 3, device_means=device)
        moved.append(sum(c.nbytes for c in prof.calls if c.kind == "h2d"))
        want = window_means(given, field, 3)
        np.testing.assert_array_equal(got[2], want[2])
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
    sent = 2 * pairs.midpoints.nbytes  # midpoints and displacements, float64
    assert moved[1] + sent <= moved[0]
    assert moved[3] >= moved[1] + sent
    # the boxes' index ranges and the windows' lists are made on the device (the ranges
    # were 48 bytes a pair, the lists 24 a window): the kept pairs' call sends less than
    # an int per window (the rows' starts, Student's quantiles)
    assert moved[1] < 4 * field.u.size


@pytest.mark.parametrize("case", ["sparse", "outliers", "plane", "line", "faces", "empty"])
@pytest.mark.parametrize("spread, weighted", [(None, True), (ROBUST_SPREAD, False)])
def test_window_means_on_the_device_are_the_hosts(queue, case, spread, weighted):
    """The device's window means (kernels/windowmeans.cl, double precision) against the
    host's batched ones, which equal the per-window loop: the same pairs counted, the
    same windows refined, the means and uncertainties to float64 rounding; with the
    focal zone, over the window and over twice it, and for some windows alone. The
    plane's and the line's gradients are too flat for the normal equations and go back to
    the host's lstsq (solved on the device they would be infinite or NaN)."""
    rng = np.random.default_rng(len(case) + 3)
    pairs = awkward_pairs(case, rng)
    if weighted:
        pairs = dataclasses.replace(pairs, sigma=10 ** rng.uniform(-2.5, -0.5,
                                                                   pairs.displacements.shape))
    field, focus = grid_field(), FocalZone(plane=12.0, resolution=5.0)
    device = DeviceWindowMeans(queue)
    wanted = rng.random(field.u.shape) < 0.5
    for support, windows in [(1.0, None), (2.0, None), (1.0, wanted)]:
        kw = dict(focus=focus, spread=spread, support=support, windows=windows)
        want = window_means(pairs, field, 3, **kw)
        got = window_means(pairs, field, 3, **kw, device_means=device)
        np.testing.assert_array_equal(got[2], want[2])
        for a, b in zip(got[:2], want[:2]):
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    if case in ("plane", "line"):  # all pairs in one window: a flat scatter
        every = len(pairs.midpoints)
        one = (np.zeros(every, int), np.ones(every, int))
        lists, _ = device.box_lists([one, one, one], (1, 1, 1), np.ones(1, bool))
        dev = device.pairs(pairs.midpoints, pairs.displacements, None, None)
        one_window = ([15.0], [15.0], [15.0])  # the axes of a field of one window
        _, status = device.gradients(dev, lists, one_window, (99.0,) * 3,
                                     None, (0.1, 0.1, 0.3), 12, 1e-4)
        assert status[0] == ILL_POSED
        # the host's fit written into the device copy: the estimates read it as they
        # read the same gradient uploaded from the host
        centres = device.device_centres(one_window)
        _, on_device = device.device_gradients(
            dev, lists, centres, (99.0,) * 3, None, (0.1, 0.1, 0.3), 12, 1e-4)
        fitted = rng.normal(scale=0.05, size=(1, 3, 3))
        device.set_gradients(on_device, fitted)
        t = np.array([np.nan] + [2.0] * every)
        est = [device.estimates(dev, lists, c, g, (99.0,) * 3, None, (0.1, 0.1, 0.3), 1,
                                t, 0.1) for c, g in ((centres, on_device),
                                                     (one_window, fitted))]
        for got, want in zip(*est, strict=True):
            np.testing.assert_array_equal(got, want)
        assert np.isfinite(est[0][1]).all()
        zero = device.estimates(dev, lists, centres, np.zeros((1, 3, 3)), (99.0,) * 3,
                                None, (0.1, 0.1, 0.3), 1, t, 0.1)
        assert not np.array_equal(zero[1], est[0][1])  # the gradient moved the mean


def test_window_means_on_the_device_take_the_hosts_scalars_and_zero_spread(queue):
    """A scalar search range or position sigma stands for all three components, and a
    spread of 0 is a reach of the floor (KEEP_FLOOR), on the device as on the host."""
    rng = np.random.default_rng(21)
    pairs, field = awkward_pairs("outliers", rng), grid_field()
    device = DeviceWindowMeans(queue)
    for kw in [dict(search=2.0, position_sigma=0.5), dict(spread=0.0)]:
        want = window_means(pairs, field, 3, **kw)
        got = window_means(pairs, field, 3, **kw, device_means=device)
        np.testing.assert_array_equal(got[2], want[2])
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-12)
    floor = window_means(pairs, field, 3, spread=0.0)[2]
    assert (floor < window_means(pairs, field, 3, spread=None)[2]).any()


def test_window_means_on_the_device_follow_the_field_they_are_given(queue):
    """One device object over fields whose window centres differ (the grid moved, then
    back): each call's means are the host's, not those of the centres it keeps from the
    call before (:meth:`DeviceWindowMeans.device_centres`)."""
    pairs = awkward_pairs("outliers", np.random.default_rng(22))
    device = DeviceWindowMeans(queue)
    field = grid_field()
    for shift in (0.0, 1.5, 0.0):
        moved = dataclasses.replace(field, x=field.x + shift, z=field.z - shift)
        want = window_means(pairs, moved, 3)
        got = window_means(pairs, moved, 3, device_means=device)
        np.testing.assert_array_equal(got[2], want[2])
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
    axes = (np.arange(2.0), np.arange(3.0), np.arange(4.0))
    kept = device.device_centres(axes)
    assert device.device_centres(tuple(a.copy() for a in axes)) is kept
    assert device.device_centres(kept) is kept
    other = device.device_centres(axes[::-1])  # the same numbers, another field
    assert other is not kept and other.count == kept.count == 24
    assert other.axes.size == kept.axes.size == 9  # the axes went up, not 24 x 3 centres


@pytest.mark.parametrize("made", ["host", "device"])
@pytest.mark.parametrize("count, radius", [(0, 1.0), (1, 1.0), (57, 1.0), (400, 2.0)])
def test_box_lists_on_the_device_are_the_k_d_trees(queue, count, radius, made):
    """Each wanted window's pairs from the device's box search (per-axis index ranges,
    given by the host or made on the device from the pairs there, ``box_ranges``; the
    pairs bucketed by row of windows) are the pairs a k-d tree finds within ``radius`` of
    its centre per axis, in pair order; the windows not wanted list none; asked for those
    holding at least 3, those alone, with the same pairs."""
    rng = np.random.default_rng(count)
    field, device = grid_field(), DeviceWindowMeans(queue)
    half = np.asarray(field.window[::-1], float) / 2
    mid = rng.uniform(-2.0, [32.0, 28.0, 24.0], (count, 3))
    if count:  # on a box's face, and just past another's
        mid[0] = np.array([field.x[2], field.y[1], field.z[0]]) + radius * half
        mid[-1] = np.array([field.x[0], field.y[0], field.z[0]]) - radius * half * 1.01
    points = mid / half
    axes = [c / h for c, h in zip((field.x, field.y, field.z), half)]
    ranges = []  # per axis, each point's run of centres within the radius
    for a in range(3):
        near = np.abs(points[:, a, None] - axes[a][None]) <= radius
        first = near.argmax(axis=1)
        ranges.append((first, first + np.count_nonzero(near, axis=1)))
    if made == "device" and count:
        dev = device.pairs(mid, np.zeros_like(mid), None, None)
        centres = device.device_centres((field.x, field.y, field.z))
        on_device = device.box_ranges(dev, half, centres, radius)
        for (lo, hi), (want_lo, want_hi) in zip(on_device, ranges):
            lo, hi, full = lo.get(), hi.get(), want_hi > want_lo
            np.testing.assert_array_equal(hi - lo, want_hi - want_lo)
            np.testing.assert_array_equal(lo[full], want_lo[full])
        ranges = on_device
    wanted = rng.random(field.u.size) < 0.6
    lists, held = device.box_lists(ranges, field.u.shape, wanted)
    z, y, x = np.meshgrid(*axes[::-1], indexing="ij")
    centres = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    truth = (cKDTree(points).query_ball_point(centres, radius, p=np.inf) if count
             else [[] for _ in centres])
    got = dict(zip(lists.win.tolist(), (lists.members(k) for k in range(len(lists.win)))))
    for w, inside in enumerate(truth):
        want = sorted(inside) if wanted[w] else []
        assert held[w] == len(want)
        np.testing.assert_array_equal(got.get(w, []), want)
    assert held[wanted].sum() == lists.stop[-1] if len(lists.win) else not held.any()
    assert lists.largest() == held.max(initial=0)
    busy, none = device.box_lists(ranges, field.u.shape, wanted, least=3, counted=False)
    assert none is None  # the counts not read back
    np.testing.assert_array_equal(busy.win, np.flatnonzero(held >= 3))  # those alone
    np.testing.assert_array_equal(busy.mask.get(), held >= 3)
    for k, w in enumerate(busy.win):
        np.testing.assert_array_equal(busy.members(k), got[w])
    # the busy windows' device mask as the next call's wanted: the host's booleans' lists
    by_mask, _ = device.box_lists(ranges, field.u.shape, busy.mask)
    by_host, _ = device.box_lists(ranges, field.u.shape, held >= 3)
    np.testing.assert_array_equal(by_mask.win, by_host.win)
    for k in range(len(by_host.win)):
        np.testing.assert_array_equal(by_mask.members(k), by_host.members(k))


@pytest.mark.parametrize("wrong", ["transposed", "flat", "integers"])
def test_windows_of_another_shape_or_kind_are_refused_by_name(wrong):
    """A ``windows`` mask that is not one boolean per window of the field's grid is
    refused with the shape it must have (before, a flat mask of the right size passed
    and a transposed one failed inside with a reshape error)."""
    rng = np.random.default_rng(5)
    pairs, field = awkward_pairs("sparse", rng), grid_field()
    mask = np.ones(field.u.shape, bool)
    bad = {"transposed": mask.T, "flat": mask.ravel(), "integers": mask.astype(int)}[wrong]
    with pytest.raises(ValueError, match=r"boolean array of the field's grid shape \(5, 6, 7\)"):
        window_means(pairs, field, 3, windows=bad)


def test_near_median_leaves_out_a_stray_pair_and_keeps_an_honest_spread():
    """One pair 0.4 voxel off among pairs that agree within 0.02 is left out (the search
    range alone keeps it); a pair within the floor of the median is always kept; and
    pairs that scatter widely are kept as a Gaussian's 3 sigma keeps them."""
    rng = np.random.default_rng(3)
    shift = np.array([2.3, -1.4, 1.7])
    d = shift + rng.normal(0, 0.02, (12, 3))
    d[0, 0] += 0.4
    assert not near_median(d, spread=ROBUST_SPREAD)[0]
    assert near_median(d, spread=ROBUST_SPREAD)[1:].all()
    assert near_median(d).all()  # the default: the search range alone
    tight = shift + rng.normal(0, 1e-4, (12, 3))
    tight[0] += 0.9 * np.asarray(KEEP_FLOOR)
    assert near_median(tight, spread=ROBUST_SPREAD).all()
    wide = shift + rng.normal(0, [0.3, 0.3, 0.9], (4000, 3))
    kept = near_median(wide, spread=ROBUST_SPREAD).mean()
    assert 0.98 < kept < 0.997  # 3 sigma per component: 0.9973 ** 3 = 0.992


def one_stray_pair() -> tuple[PIVResult, np.ndarray, np.ndarray]:
    """The field of :func:`grid_field` and ten pairs' midpoints and displacements in its
    window (1, 1, 1), 0.01 voxel about (2.3, -1.4, 1.7), the first 0.5 voxel off in x."""
    rng = np.random.default_rng(4)
    field = grid_field()
    centre = np.array([field.x[1], field.y[1], field.z[1]], float)
    mid = centre + rng.uniform(-1.0, 1.0, (10, 3))
    disp = np.tile([2.3, -1.4, 1.7], (10, 1)) + rng.normal(0, 0.01, (10, 3))
    disp[0, 0] += 0.5
    return field, mid, disp


def test_a_stray_pair_moves_its_window_by_less_than_with_the_search_range_alone():
    """A window of ten pairs at the true shift, one of them 0.5 voxel off laterally: the
    robust mean is the shift, the search range's mean is 0.05 off."""
    field, mid, disp = one_stray_pair()
    pairs = ParticlePairs(mid, disp)
    robust = window_means(pairs, field, 3, spread=ROBUST_SPREAD)[0][:, 1, 1, 1]
    boxed = window_means(pairs, field, 3, spread=None)[0][:, 1, 1, 1]
    assert abs(robust[0] - 2.3) < 0.01 < 0.04 < abs(boxed[0] - 2.3)


def test_a_pair_its_fit_doubts_weighs_less_in_its_window():
    """Ten pairs at the true shift whose fits claim 0.01 voxel, one of them 0.5 voxel
    off laterally with a fit that claims 0.2 (a focal-zone particle's prior): the
    weighted mean is the shift within 0.01 where the pairs alike miss it by 0.05; its
    uncertainty is smaller too. Pairs that all claim the same uncertainty give the
    plain mean and its uncertainty."""
    field, mid, disp = one_stray_pair()
    sigma = np.full((10, 3), 0.01)
    sigma[0] = 0.2
    alike = window_means(ParticlePairs(mid, disp), field, 3)
    weighted = window_means(ParticlePairs(mid, disp, sigma=sigma), field, 3)
    assert abs(weighted[0][0, 1, 1, 1] - 2.3) < 0.01 < 0.04 < abs(alike[0][0, 1, 1, 1] - 2.3)
    assert weighted[1][0, 1, 1, 1] < alike[1][0, 1, 1, 1]
    same = window_means(ParticlePairs(mid, disp, sigma=np.full((10, 3), 0.05)), field, 3)
    for a, b in zip(same[:2], alike[:2]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)


def test_a_flat_scatter_takes_the_minimum_norm_gradient():
    """Pairs on one plane leave the depth gradient undetermined: as lstsq, the batched
    fit shares the offset between the constant and the depth slope (minimum norm)."""
    from plenocl.piv.refinement import _fit_gradients, local_gradient

    rng = np.random.default_rng(2)
    mid = np.column_stack([rng.uniform(0, 20, (40, 2)), np.full(40, 7.0)])
    disp = SHIFT + 0.05 * mid[:, :1] + rng.normal(0, 0.05, (40, 3))
    centre = np.array([10.0, 10.0, 5.0])
    want = local_gradient(ParticlePairs(mid, disp), list(range(40)), centre)
    pos = np.concatenate([mid - centre, disp], axis=1)[None]
    got = _fit_gradients(pos, np.ones((1, 40), bool))[0]
    assert abs(want[0, 2]) > 0.01  # the constant leaks into the depth column
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("spread", [0.0, -1.0, float("nan")])
def test_a_spread_that_keeps_nothing_is_refused_by_name(spread):
    vol = np.zeros((8, 8, 8), np.float32)
    with pytest.raises(ValueError, match="spread=.*positive number of robust"):
        refine_with_particles(grid_field(), vol, vol, spread=spread)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_pairs_their_fits_doubt_do_not_tilt_the_gradient(seed):
    """Thirty pairs fitted to 0.015 voxel and ten placed to 0.25 (focal-zone particles,
    docs/design.md §7.4 item 9) under a linear motion: the gradient weighted as the
    means are errs less than a third as much as the one fitted to all alike, and the
    batched fit gives the per-window fit's."""
    from plenocl.piv.refinement import _fit_gradients, local_gradient

    rng = np.random.default_rng(seed)
    grad = np.array([[0.02, 0.0, -0.01], [0.0, -0.03, 0.01], [0.01, 0.0, 0.02]])
    mid = rng.uniform(0, 16, (40, 3))
    sigma = np.where(np.arange(40) < 30, 0.015, 0.25)[:, None] * np.ones(3)
    disp = SHIFT + (mid - 8.0) @ grad.T + rng.normal(0, 1, (40, 3)) * sigma
    pairs, centre = ParticlePairs(mid, disp, sigma=sigma), np.full(3, 8.0)
    weighted = local_gradient(pairs, list(range(40)), centre, search=(9.0,) * 3)
    alike = local_gradient(pairs.alike(), list(range(40)), centre, search=(9.0,) * 3)
    assert np.abs(weighted - grad).max() < np.abs(alike - grad).max() / 3
    pos = np.concatenate([mid - centre, disp], axis=1)[None]
    weights = 1.0 / (sigma ** 2 + np.asarray(WEIGHT_FLOOR) ** 2)
    got = _fit_gradients(pos, np.ones((1, 40), bool), weights[None])[0]
    np.testing.assert_allclose(got, weighted, rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_depth_interpolation_is_numpys_interp_column_by_column(seed):
    """All columns at once against numpy.interp one column at a time, to the bit:
    awkward shapes, a single depth, columns with no, one, or every finite value, gaps at
    either end, NaN uncertainties (taken as 0), unevenly spaced depths."""
    rng = np.random.default_rng(seed)
    for nz in (1, 2, 5, 9):
        z = np.sort(rng.choice(np.linspace(-4, 4, 40), nz, replace=False))
        w = rng.normal(0.0, 3.0, (nz, 3, 5))
        w[rng.random(w.shape) < rng.uniform(0.1, 0.9)] = np.nan
        w[:, 0, 0], w[:, 0, 1] = np.nan, 2.5  # a column without values, one full
        if nz > 1:
            w[:, 0, 2] = np.nan
            w[nz // 2, 0, 2] = -1.0  # one value: constant
        sigma = rng.uniform(0.0, 1.0, w.shape)
        sigma[rng.random(w.shape) < 0.2] = np.nan
        got, want = depth_interpolation(w, sigma, z), depth_interpolation_reference(w, sigma, z)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
        assert np.isnan(got[0][:, 0, 0]).all() and (got[0][:, 0, 1] == 2.5).all()


def test_a_blind_window_without_a_seeing_one_in_its_column_takes_its_seeing_pairs():
    """One window in depth, centred in the blind zone (a volume hardly deeper than a
    window): nothing to interpolate from, so it takes its seeing pairs' depth motion
    (1.0 here), not all its pairs' (the blind ones at 0.4 drew it below 0.6), and warns
    that a deeper volume measures depth motion."""
    rng = np.random.default_rng(4)
    field, focus = grid_field((1, 3, 3), (16, 8, 8), 8.0), FocalZone(plane=3.5, resolution=1.0)
    seeing = rng.uniform([0, 0, 6.0], [23, 23, 11.0], (300, 3))
    blind = rng.uniform([0, 0, 2.5], [23, 23, 4.5], (300, 3))
    shift = np.array([0.2, -0.1, 0.0])
    disp = np.vstack([np.full((300, 3), shift + [0, 0, 1.0]),
                      np.full((300, 3), shift + [0, 0, 0.4])])
    pairs = ParticlePairs(np.vstack([seeing, blind]), disp + rng.normal(0, 0.02, disp.shape))
    every = window_means(pairs, field, 3, focus=focus)[0][2]
    assert np.all(every < 0.6)  # all pairs' (robust) mean: drawn to the blind ones
    with pytest.warns(UserWarning, match="blind zone .* reconstruct a deeper volume"):
        w, sigma = seen_depth(pairs, field, focus, None, None)
    np.testing.assert_allclose(w, 1.0, atol=0.02)
    assert np.isfinite(sigma).all()


def test_the_focal_zone_along_the_grid_only_for_a_camera_without_pose():
    """A posed camera's focal plane is tilted or moved in the world grid: no depth index
    holds it, so the pair chain, track and a tracking run's binned field get none."""
    from plenocl.camera import Pose
    from plenocl.piv.refinement import FocalZone

    cam = Camera.synthetic_850()
    grid = Grid.for_camera(cam, (-2.0, 2.0))
    assert FocalZone.along_grid(cam, grid) == FocalZone.of(cam, grid)
    moved = cam.with_pose(Pose((0.0, 0.0, 0.0), (0.0, 0.0, 5.0)))
    assert FocalZone.along_grid(moved, grid) is None
