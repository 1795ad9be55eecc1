"""Reconstruction metrics on volumes whose answer is known by construction."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl import Grid
from plenocl.metrics import (
    find_particles,
    ghost_fraction,
    match_particles,
    matched_errors,
    quality_q,
    recovered_particles,
    recovery,
    render_particles,
)

GRID = Grid((17, 21, 23), x=(-2.3, 2.3), y=(-2.1, 2.1), z=(-1.7, 1.7))  # 0.2 mm voxels


def _particles(seed=3):
    """12 well-separated particles: a 3 x 2 x 2 lattice (>= 5 voxels apart) with random
    sub-voxel jitter, so peaks never merge."""
    rng = np.random.default_rng(seed)
    ix, iy, iz = np.meshgrid([4, 11, 18], [5, 14], [4, 11], indexing="ij")
    idx = np.column_stack([ix.ravel(), iy.ravel(), iz.ravel()]) + rng.uniform(-0.5, 0.5, (12, 3))
    spacing = np.array(GRID.spacing[::-1])
    return np.array([GRID.x[0], GRID.y[0], GRID.z[0]]) + (idx + 0.5) * spacing


def test_q_is_one_for_identical_and_scale_invariant_zero_for_disjoint():
    truth = render_particles(GRID, _particles())
    assert quality_q(truth, truth) == pytest.approx(1.0)
    assert quality_q(3.0 * truth, truth) == pytest.approx(1.0)
    other = np.zeros_like(truth)
    other[truth == 0] = 1.0
    assert quality_q(other, truth) == 0.0


def test_rendered_particles_conserve_intensity_and_peak_at_the_truth():
    pos = _particles()
    vol = render_particles(GRID, pos, 5.0, sigma_vox=0.8)
    assert vol.sum() == pytest.approx(5.0 * len(pos), rel=1e-4)
    found, _ = find_particles(vol, threshold=0.2)
    pairs = match_particles(found, GRID.to_index(pos), lateral=0.2, depth=0.2)
    assert len(pairs) == len(pos)
    err = np.array([found[f] - GRID.to_index(pos)[t] for t, f in pairs])
    assert np.abs(err).max() < 0.1  # sub-voxel fit of erf-integrated Gaussians


def test_peaks_on_the_faces_are_fitted_as_if_zeros_lay_beyond():
    """A peak in every face and corner voxel of an awkward volume: each sub-voxel offset
    is the three-point fit with 0 beyond the face (parabolic there: a zero neighbour has
    no logarithm), toward the inner neighbour, as a zero-padded volume gives it."""
    rng = np.random.default_rng(7)
    vol = np.zeros((5, 6, 7), np.float32)
    corners = [(z, y, x) for z in (0, 4) for y in (0, 5) for x in (0, 6)]
    for z, y, x in corners:  # each peak with one lit neighbour inside along each axis
        vol[z, y, x] = 10.0
        for inner in ((1 if z == 0 else 3, y, x), (z, 1 if y == 0 else 4, x),
                      (z, y, 1 if x == 0 else 5)):
            vol[inner] = rng.uniform(2.0, 6.0)
    found, values = find_particles(vol, threshold=0.5)
    assert len(found) == 8 and np.all(values == 10.0)
    pad = np.pad(vol, 1)
    for ix, iy, iz in np.rint(found).astype(int):
        c = (iz + 1, iy + 1, ix + 1)
        for k, axis in enumerate((2, 1, 0)):
            minus, plus = list(c), list(c)
            minus[axis] -= 1
            plus[axis] += 1
            m, p = float(pad[tuple(minus)]), float(pad[tuple(plus)])
            want = np.clip((m - p) / (2.0 * (m - 20.0 + p)), -0.5, 0.5)
            got = found[(np.rint(found) == (ix, iy, iz)).all(axis=1)][0, k]
            assert got - (ix, iy, iz)[k] == pytest.approx(want, abs=1e-12)
            assert np.sign(want) == np.sign(p - m)  # towards the lit neighbour inside


def test_a_robust_reference_keeps_the_particles_a_few_bright_voxels_would_hide():
    """Twelve particles and two voxels 40 times brighter (as crossing lines of sight
    make in a dense volume): the maximum as reference keeps only those two; the robust
    level (the brightest 0.5 % of the peaks, at least two, set aside) keeps every
    particle, and with no outlier both references find the same peaks."""
    pos = _particles()
    vol = render_particles(GRID, pos, 5.0, sigma_vox=0.8)
    clean = find_particles(vol, threshold=0.2, reference="robust")[0]
    np.testing.assert_array_equal(clean, find_particles(vol, threshold=0.2)[0])
    vol[0, 0, 0] = vol[16, 20, 22] = 40 * vol.max()
    assert len(find_particles(vol, threshold=0.2)[0]) == 2
    found, _ = find_particles(vol, threshold=0.2, reference="robust")
    assert len(match_particles(found, GRID.to_index(pos), lateral=0.2, depth=0.2)) == len(pos)
    with pytest.raises(ValueError, match="reference must be"):
        find_particles(vol, reference="median")


def test_recovery_counts_tolerances_and_ghosts():
    pos = _particles()
    idx = GRID.to_index(pos)
    shifted = idx + np.array([0.0, 0.0, 1.5])  # within 2 voxels in depth: still recovered
    ghost = np.array([[1.0, 1.0, 1.0]])
    fake = GRID.to_index(np.zeros((0, 3)))
    found = np.vstack([shifted, ghost, fake])
    assert len(match_particles(found, idx)) == len(pos)
    assert len(match_particles(idx + np.array([1.5, 0, 0]), idx)) == 0  # too far laterally
    # compact particles (sigma 0.4 voxel): their own tails stay inside the tolerance
    vol = render_particles(GRID, pos, sigma_vox=0.4) + render_particles(
        GRID, [[1.9, 1.7, 1.3]], 1.0, sigma_vox=0.4)
    rep = recovery(vol, GRID, pos)
    assert rep.recovered == len(pos) and rep.fraction == 1.0
    assert rep.ghost_fraction == pytest.approx(1.0 / (len(pos) + 1), rel=0.05)


def test_matched_errors_are_each_recovered_particle_s_offset():
    """The rendered particles moved by a known sub-voxel step are found that far off,
    lateral and depth separately, one row per recovered particle."""
    pos = _particles()
    step = np.array([0.3, -0.2, 0.5]) * np.array(GRID.spacing[::-1])  # (x, y, z) mm
    vol = render_particles(GRID, pos + step, sigma_vox=0.8)
    d = matched_errors(vol, GRID, pos)
    assert d.shape == (len(pos), 3)
    np.testing.assert_allclose(np.median(d, axis=0), [0.3, -0.2, 0.5], atol=0.05)
    assert matched_errors(np.zeros(GRID.shape, np.float32), GRID, pos).shape == (0, 3)


def test_recovered_particles_names_the_ones_a_peak_matches():
    """Only the rendered particles are marked recovered, the one left out of the volume
    not; their mean is recovery()'s fraction."""
    pos = _particles()
    vol = render_particles(GRID, pos[1:], sigma_vox=0.4)
    hit = recovered_particles(vol, GRID, pos)
    assert hit.dtype == bool and hit.shape == (len(pos),)
    assert not hit[0] and hit[1:].all()
    assert hit.mean() == recovery(vol, GRID, pos).fraction
    assert not recovered_particles(np.zeros(GRID.shape, np.float32), GRID, pos).any()


def test_ghost_fraction_extremes():
    pos = _particles()
    vol = render_particles(GRID, pos, sigma_vox=0.4)
    assert ghost_fraction(vol, GRID.to_index(pos)) < 1e-3
    assert ghost_fraction(vol, np.zeros((0, 3))) == 1.0
    assert ghost_fraction(np.zeros(GRID.shape), GRID.to_index(pos)) == 0.0
