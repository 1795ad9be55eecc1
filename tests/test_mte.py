"""Motion-tracking enhancement (plenocl/pipeline/mte.py): its options, the dense field,
the exchange of the two volumes, and a pair through process_pair with MTE cycles."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol

from plenocl import Projector, process_pair, random_particles
from plenocl.bench.accuracy_section import paper_optics
from plenocl.metrics import render_particles
from plenocl.pipeline import MTESettings
from plenocl.pipeline.mte import combine_volumes, dense_displacement, exchange
from plenocl.piv import PIVResult
from plenocl.reconstruction import ReconstructionSettings
from plenocl.simulate import simulate_image


@pytest.mark.parametrize("kwargs, message", [
    (dict(cycles=-1), "cycles must be"), (dict(cycles=1.5), "cycles must be"),
    (dict(iterations=0), "iterations must be"), (dict(combine="max"), "combine must be"),
    (dict(smooth=float("nan")), "smooth must be"), (dict(smooth=-1.0), "smooth must be"),
])
def test_bad_mte_options_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MTESettings(**kwargs)


def field(shape, u, v, w, nan_at=None) -> PIVResult:
    """A PIV result on a 3 x 3 x 4 grid of window centres over ``shape``."""
    z, y, x = (np.linspace(4, n - 5, k) for n, k in zip(shape, (3, 3, 4)))
    full = [np.full((3, 3, 4), c, np.float64) for c in (u, v, w)]
    if nan_at is not None:
        for c in full:
            c[nan_at] = np.nan
    ones = np.ones((3, 3, 4), bool)
    return PIVResult(x, y, z, *full, ones, np.full((3, 3, 4), np.nan), ~ones, ~ones,
                     (8, 8, 8))


def test_a_uniform_field_stays_uniform_on_every_voxel_smoothed_or_not():
    shape = (20, 16, 24)
    for smooth in (0.0, 1.0):
        d = dense_displacement(field(shape, 1.5, -0.5, 2.0), shape, smooth)
        assert d.shape == (3, *shape) and d.dtype == np.float32
        np.testing.assert_allclose(d[0], 2.0, atol=tol.UNIFORM_FIELD)   # dz from w
        np.testing.assert_allclose(d[2], 1.5, atol=tol.UNIFORM_FIELD)   # dx from u
    masked = dense_displacement(field(shape, 1.0, 1.0, 1.0, nan_at=(1, 1, 1)), shape)
    assert np.isfinite(masked).all()  # a masked (NaN) vector counts as 0, never NaN


@pytest.mark.parametrize("device", [False, True])
def test_the_exchange_moves_each_volume_onto_the_other_time(queue, device):
    """A particle at p in A and p + d in B: B warped back lands on A's particle and A
    warped forward on B's, on the host and on the device."""
    from plenocl import Grid

    grid = Grid((24, 20, 28), x=(0, 28), y=(0, 20), z=(0, 24))
    p = np.array([[12.3, 9.6, 11.2]])
    shift = np.array([2.4, -1.3, 1.8])  # (x, y, z) voxels = mm here
    vol_a = render_particles(grid, p, 1.0, sigma_vox=1.2)
    vol_b = render_particles(grid, p + shift, 1.0, sigma_vox=1.2)
    d = dense_displacement(field(grid.shape, *shift), grid.shape)
    b_at_a, a_at_b = exchange(vol_a, vol_b, d, queue if device else False)
    assert np.corrcoef(b_at_a.ravel(), vol_a.ravel())[0, 1] > 0.99
    assert np.corrcoef(a_at_b.ravel(), vol_b.ravel())[0, 1] > 0.99
    assert b_at_a.min() >= 0 and a_at_b.min() >= 0


def test_the_geometric_combination_keeps_only_what_both_exposures_light():
    a = np.array([0.0, 1.0, 4.0, 2.0], np.float32)
    b = np.array([3.0, 0.0, 1.0, 2.0], np.float32)
    np.testing.assert_allclose(combine_volumes(a, b, "geometric"), [0, 0, 2, 2])
    np.testing.assert_allclose(combine_volumes(a, b, "mean"), [1.5, 0.5, 2.5, 2])
    np.testing.assert_allclose(combine_volumes(a, b, "min"), [0, 0, 1, 2])


@pytest.mark.one_device
def test_process_pair_with_mte_refines_both_volumes_and_the_field(queue):
    """One MTE cycle after the single frame: new volumes from ``mte.iterations`` each,
    a field that still finds the imposed displacement, and its time in ``seconds``;
    ``cycles=0`` is the single frame itself."""
    cam, grid = paper_optics((24, 16))
    proj = Projector(cam, grid, queue)
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    pos, inten = random_particles(box, count=25, seed=5, intensity=2e4)
    shift_mm = np.array([0.25, 0.0, 0.3])
    kw = dict(rays_per_particle=4000, blur_px=0.8, background=20.0, queue=queue)
    raw_a = simulate_image(cam, pos, inten, seed=1, **kw)
    raw_b = simulate_image(cam, pos + shift_mm, inten, seed=2, **kw)
    settings = ReconstructionSettings(iterations=20, supersample=3, coarse_iterations=0)
    single = process_pair(raw_a, raw_b, proj, reconstruction=settings,
                          mte=MTESettings(cycles=0))
    pair = process_pair(raw_a, raw_b, proj, reconstruction=settings,
                        mte=MTESettings(cycles=1, iterations=5))
    assert "mte" in pair.seconds and "mte" not in single.seconds
    assert pair.info_a.iterations == 5 and single.info_a.iterations == 20
    assert not np.array_equal(pair.vol_a, single.vol_a)
    expected = shift_mm / np.array(grid.spacing[::-1])  # (x, y, z) voxels
    for res in (single.piv, pair.piv):
        ok = res.valid
        assert ok.mean() > 0.8
        got = [np.median(c[ok]) for c in (res.u, res.v, res.w)]
        # within half a voxel laterally and 3/4 in depth (a quarter of the depth
        # resolution) on this small, edge-dominated volume
        assert np.all(np.abs(np.array(got) - expected) <= [0.5, 0.5, 0.75]), got
