"""The particle pairs' neighbour test (plenocl/piv/pairoutliers.py), the window means'
fill of sparse windows and the predictor's linear extension beyond its centres
(plenocl/piv/refinement.py; docs/design.md §7.4 item 8)."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl.piv import PIVResult
from plenocl.piv.pairoutliers import field_gradient, neighbour_outliers
from plenocl.piv.refinement import ParticlePairs, predicted, sparse_filled, window_means

#: A rotation-like displacement gradient (component u, v, w by x, y, z; voxel per voxel),
#: 1.5 times the error budget's 2 degrees, and an offset (voxels).
GRAD = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.05], [0.0, 0.05, 0.0]])
OFFSET = np.array([1.2, -0.4, 0.8])


def linear_field(shape=(4, 5, 6), step=8.0, grad=GRAD) -> PIVResult:
    """Window centres ``step`` voxels apart holding ``OFFSET + grad @ (x, y, z)``."""
    z, y, x = (4.0 + step * np.arange(n) for n in shape)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([xx, yy, zz], axis=-1)
    uvw = OFFSET + pts @ grad.T
    ones = np.ones(shape, bool)
    return PIVResult(x, y, z, uvw[..., 0], uvw[..., 1], uvw[..., 2], ones,
                     np.full(shape, np.nan), ~ones, ~ones, (8, 8, 8))


def truth_at(mid: np.ndarray, grad=GRAD) -> np.ndarray:
    return OFFSET + mid @ grad.T


def test_a_linear_fields_gradient_is_its_matrix_inside_and_beyond_its_centres():
    field = linear_field()
    pts = np.array([[10.3, 12.1, 7.7], [-6.0, 50.0, 40.0], [44.0, 0.0, 30.5]])
    np.testing.assert_allclose(field_gradient(field, pts), np.broadcast_to(GRAD, (3, 3, 3)),
                               atol=1e-12)
    flat = linear_field(shape=(1, 5, 6))  # one window deep: no gradient along z
    want = GRAD.copy()
    want[:, 2] = 0.0
    np.testing.assert_allclose(field_gradient(flat, pts)[0], want, atol=1e-12)


def test_the_predictor_extends_a_linear_motion_beyond_its_centres_when_asked():
    field = linear_field()
    beyond = np.array([[-4.0, 2.0, 1.0], [50.0, 40.0, 33.0]])  # past every face
    np.testing.assert_allclose(predicted(field, beyond, extrapolate=True), truth_at(beyond),
                               atol=1e-12)
    clamped = np.clip(beyond, [field.x[0], field.y[0], field.z[0]],
                      [field.x[-1], field.y[-1], field.z[-1]])
    np.testing.assert_allclose(predicted(field, beyond), truth_at(clamped), atol=1e-12)


def scattered_pairs(rng, n=400, focal_share=0.2, wrong=12):
    """Pairs in the field's box under ``GRAD`` (about the paper's seeding: 16 neighbours
    within 10 voxels): most fitted to 0.015 voxel, a share known to 0.2 (a focal
    zone's), each off by a normal error of its own sigma; and ``wrong`` confident pairs
    (0.015) that are 0.3 voxel off in y, the component the gradient varies."""
    mid = rng.uniform([0, 0, 0], [44, 36, 28], (n, 3))
    sigma = np.where(rng.random((n, 1)) < focal_share, 0.2, 0.015) * np.ones(3)
    disp = truth_at(mid) + rng.normal(0, sigma)
    bad = rng.choice(np.flatnonzero(sigma[:, 0] < 0.1), wrong, replace=False)
    disp[bad, 1] += 0.3 * np.sign(rng.normal(size=wrong))
    return mid, disp, sigma, bad


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_confident_wrong_pairs_are_left_out_and_honest_ones_kept(seed):
    """Under a strong gradient, with the neighbours moved along it, every confident pair
    0.3 voxel off is found, and under 1.5 % of the honest pairs are left out (the focal
    ones beyond 2.5 of their sigmas); with the neighbours left where they are, their
    spread along the gradient hides most of the wrong pairs."""
    mid, disp, sigma, bad = scattered_pairs(np.random.default_rng(seed))
    out = neighbour_outliers(mid, disp, sigma, linear_field())
    assert out[bad].all()
    honest = np.ones(len(mid), bool)
    honest[bad] = False
    assert out[honest].mean() < 0.015
    still = neighbour_outliers(mid, disp, sigma, linear_field(grad=np.zeros((3, 3))))
    assert still[bad].mean() < 0.5


def test_a_pair_its_fit_doubts_is_judged_by_its_own_uncertainty():
    """The same 0.3-voxel error is an outlier for a pair fitted to 0.015 voxel and not
    for one known to 0.2 (a focal-zone particle's prior)."""
    rng = np.random.default_rng(5)
    mid, disp, sigma, _ = scattered_pairs(rng, wrong=0, focal_share=0.0)
    disp = disp.copy()
    disp[0, 0] += 0.3
    sigma = sigma.copy()
    assert neighbour_outliers(mid, disp, sigma, linear_field())[0]
    sigma[0] = 0.2
    assert not neighbour_outliers(mid, disp, sigma, linear_field())[0]


def test_depth_errors_alone_leave_no_pair_out():
    rng = np.random.default_rng(6)
    mid, disp, sigma, _ = scattered_pairs(rng, wrong=0)
    disp[:, 2] += rng.normal(0, 2.0, len(disp))  # one camera's depth: tested elsewhere
    assert neighbour_outliers(mid, disp, sigma, linear_field()).mean() < 0.01


def test_too_few_pairs_to_judge_leave_none_out_and_bad_settings_are_refused():
    mid = np.arange(30.0).reshape(10, 3)
    assert not neighbour_outliers(mid, mid * 0.0 + np.arange(10)[:, None], None,
                                  linear_field()).any()
    with pytest.raises(ValueError, match="threshold"):
        neighbour_outliers(mid, mid, None, linear_field(), threshold=0.0)
    with pytest.raises(ValueError, match="neighbours"):
        neighbour_outliers(mid, mid, None, linear_field(), neighbours=1)


def test_a_sparse_window_takes_the_pairs_of_twice_its_box():
    """A window with too few pairs of its own gets the mean of the pairs in a box twice
    its size, moved to its centre along their gradient: the linear motion at its centre;
    a window whose depth is unknown stays empty, and filled windows keep theirs."""
    rng = np.random.default_rng(7)
    field = linear_field()
    mid = rng.uniform([0, 0, 0], [44, 36, 28], (1500, 3))
    centre = np.array([field.x[2], field.y[2], field.z[1]])
    far = ~np.all(np.abs(mid - centre) <= 4.5, axis=1)  # nothing in that window's box
    pairs = ParticlePairs(mid[far], truth_at(mid[far]))
    means = window_means(pairs, field)
    assert np.isnan(means[0][0, 1, 2, 2])
    known = np.ones(field.u.shape, bool)
    known[1, 2, 2] = True
    mean, error, count = sparse_filled(means, known, pairs, field)
    np.testing.assert_allclose(mean[:, 1, 2, 2], truth_at(centre[None])[0], atol=1e-9)
    assert count[1, 2, 2] >= 3 and np.isfinite(error[:, 1, 2, 2]).all()
    have = np.isfinite(means[0][0])
    np.testing.assert_array_equal(mean[:, have], means[0][:, have])
    known[1, 2, 2] = False
    assert np.isnan(sparse_filled(window_means(pairs, field), known, pairs, field)[0]
                    [0, 1, 2, 2])
