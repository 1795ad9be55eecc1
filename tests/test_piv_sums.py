"""The direct correlation's window sums on a device (``kernels/windowsums.cl``,
:class:`plenocl.piv.devicesums.DeviceSums`) against the host's matrix products
(:class:`plenocl.piv.direct.HostSums`), on awkward shapes with windows whose weights
reach past the volume's faces."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array
import pytest
import tolerances as tol

from plenocl import flows
from plenocl.piv.correlation import window_grid
from plenocl.piv.deformation import DeviceDeformer, HostDeformer
from plenocl.piv.devicesums import DeviceSums, sums_for
from plenocl.piv.direct import (
    LAGS,
    HostSums,
    correlate_direct,
    correlated_factors,
    correlation_uncertainty,
    fit_direct,
    margin,
)

#: (shape, window, overlap, weighting): odd sizes, a volume thinner than the x taps, a
#: step of 1, top-hat windows, weights reaching far past every face and a volume no
#: deeper than the depth lags.
CASES = [((13, 17, 22), (8, 9, 10), 0.5, 0.35),
         ((5, 13, 17), (5, 8, 9), 0.5, 0.6),
         ((11, 25, 9), (9, 8, 8), 0.75, 0.8),
         ((20, 21, 23), (10, 12, 8), 0.5, 0.5),
         ((12, 10, 31), (9, 9, 11), 0.9, 0.35),
         ((11, 25, 9), (9, 8, 8), 0.75, None)]


def _pair(shape):
    rng = np.random.default_rng(sum(shape))
    return tuple(rng.random(shape).astype(np.float32) for _ in range(2))


def _close(got, want):
    """Equal to float32 rounding of sums whose terms are of the peak's order."""
    assert got.shape == want.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=tol.PIV_TWIN * float(np.abs(want).max()))


@pytest.fixture(scope="module")
def device_sums(queue):
    return DeviceSums(queue)


@pytest.mark.parametrize("shape,size,overlap,weighting", CASES)
def test_correlation_sums_match_the_host(device_sums, shape, size, overlap, weighting):
    a, b = _pair(shape)
    grid = window_grid(shape, size, overlap)
    if weighting is not None:  # the weights reach past a face: the zeros there count
        assert any(margin(w, weighting) > o for w, o in zip(size, grid.offset))
    got = device_sums.correlation_sums(a, b, grid, weighting)
    want = HostSums().correlation_sums(a, b, grid, weighting)
    for g, w in zip(got, want):
        assert g.shape == (len(LAGS), *grid.count)
        _close(g, w)
    s_a, s_b, raw_a, raw_b, products = got
    assert np.all(raw_a > 0) and np.all(raw_b > 0) and np.all(products > 0)


@pytest.mark.parametrize("shape,size,overlap,weighting", CASES)
def test_spread_sums_match_the_host(device_sums, shape, size, overlap, weighting):
    a, b = _pair(shape)
    grid = window_grid(shape, size, overlap)
    got = device_sums.spread_sums(a, b, grid, weighting)
    want = HostSums().spread_sums(a, b, grid, weighting)
    assert got.shape == (3, 9, *grid.count)
    for axis in range(3):
        for k in range(9):
            _close(got[axis, k], want[axis, k])
    assert np.all(got[:, 3:6] >= 0)  # sums of squares


@pytest.mark.parametrize("shape,size,overlap,weighting", CASES)
def test_correlated_factors_match_the_host(device_sums, queue, shape, size, overlap,
                                           weighting):
    """The uncertainty's correlated-sum factors on the device (box means, contribution
    fields and their lagged products, ``kernels/correlated.cl``) are the host's
    (``direct.correlated_factors``, SciPy's box filter and BLAS) within float32 sums, from
    host or device volumes; at least one factor is above 1 (correlated neighbours)."""
    rng = np.random.default_rng(sum(shape) + 1)
    a = (rng.random(shape) ** 6).astype(np.float32)
    b = (np.roll(a, 1, axis=2) + 0.02 * rng.random(shape)).astype(np.float32)
    grid = window_grid(shape, size, overlap)
    want = correlated_factors(a, b, grid, weighting)
    got = device_sums.correlated_factors(a, b, grid, weighting)
    np.testing.assert_allclose(got, want, rtol=tol.CORRELATED_FACTOR)
    on_device = [cl_array.to_device(queue, v) for v in (a, b)]
    assert device_sums.correlated_factors(*on_device, grid, weighting) == got
    assert max(want) > 1.0


@pytest.mark.parametrize("rows,cols", [(1, 1), (255, 9), (256, 4), (257, 9), (1000, 3)])
def test_column_partials_equal_their_twin_and_only_blocks_come_back(device_sums, rows, cols):
    """The lagged products' rows are added on the device in blocks
    (``column_partials``): each block's sums equal the twin's (bit for bit where the
    device has doubles, else within float32 sums), the column sums the rows' float64
    sums, and what comes back is the blocks' sums, not the rows."""
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.piv.devicesums import COLUMN_BLOCK
    from plenocl.reference.direct import column_partials

    rng = np.random.default_rng(rows + cols)
    host = (rng.standard_normal((rows, cols)) * 10.0 ** rng.integers(-3, 4, (rows, 1))
            ).astype(np.float32)
    dev = cl_array.to_device(device_sums.kernels.queue, host)
    with OpenCLProfile() as prof:
        got = device_sums.column_sums(dev, rows, cols)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    assert back == -(-rows // COLUMN_BLOCK) * cols * np.dtype(device_sums.accumulator).itemsize
    want = column_partials(host, COLUMN_BLOCK)
    np.testing.assert_allclose(got, want.sum(axis=0), rtol=1e-6, atol=1e-6 * np.abs(host).sum())
    if device_sums.accumulator == np.float64:
        assert np.array_equal(got, want.sum(axis=0))


@pytest.mark.parametrize("fp64", [None, False])
@pytest.mark.parametrize("shape,size,overlap,weighting", CASES[:4] + [
    ((27, 34, 41), (12, 12, 12), 0.75, 0.35)])
def test_window_fit_equals_its_twin_on_the_same_sums(queue, shape, size, overlap, weighting,
                                                      fp64):
    """``kernels/windowfit.cl`` fits the windows as the host's functions do on the same
    (device) sums: displacement, peak, flags and uncertainty, operation for operation in
    double (the logarithms aside: within 1e-9 voxel), within float32 sums on the float
    path; only eight numbers per window come back (and the factors' block sums)."""
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.piv.devicesums import COLUMN_BLOCK
    from plenocl.piv.direct import (
        direct_correlation,
        fitted_windows,
        lag_weight_sums,
        uncertainty_from_sums,
        weighed_voxels,
    )

    engine = DeviceSums(queue, fp64=fp64)
    pair = flows.volume_pair(shape, flows.Uniform((0.3, -0.2, 1.4)), density=0.01,
                             sigma=1.5, seed=sum(shape), noise=0.05)
    grid = window_grid(shape, size, overlap)
    a, b = (v.astype(np.float32) for v in (pair.vol_a, pair.vol_b))
    with OpenCLProfile() as prof:
        got = engine.window_fit(a, b, grid, weighting, uncertainty=True)
    windows = int(np.prod(grid.count))
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    blocks = -(-shape[0] * shape[1] // COLUMN_BLOCK)  # the factors' block sums, 9 x 9 lags
    assert back <= windows * (7 * 8 + 4) + 9 * 9 * 8 * blocks < windows * 315 * 4, back
    direct = direct_correlation(engine.correlation_sums(a, b, grid, weighting),
                                lag_weight_sums(grid, weighting))
    sigma = uncertainty_from_sums(engine.spread_sums(a, b, grid, weighting),
                                  engine.correlated_factors(a, b, grid, weighting),
                                  weighed_voxels(grid, weighting), direct)
    want = fitted_windows(direct, sigma)
    assert want.signal.any() and (want.fitted & want.signal).any()
    double = engine.accumulator == np.float64
    atol = 1e-9 if double else 2e-3
    for name in ("signal", "fitted", "off_centre"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    np.testing.assert_allclose(got.peak, want.peak, atol=1e-12 if double else 1e-5)
    np.testing.assert_allclose(got.displacement, want.displacement, atol=atol)
    assert np.array_equal(np.isnan(got.sigma), np.isnan(want.sigma))
    np.testing.assert_allclose(got.sigma, want.sigma, rtol=1e-9 if double else 1e-2,
                               atol=atol)


def test_device_correlation_and_uncertainty_equal_the_host(device_sums):
    pair = flows.volume_pair((27, 34, 41), flows.Uniform((0.3, -0.2, 0.4)), density=0.004,
                             sigma=1.5, seed=4, noise=0.05)
    grid = window_grid(pair.vol_a.shape, (12, 12, 12), 0.75)
    results = []
    for sums in (None, device_sums):
        corr = correlate_direct(pair.vol_a, pair.vol_b, grid, 0.35, sums)
        results.append((corr, correlation_uncertainty(pair.vol_a, pair.vol_b, grid, 0.35,
                                                      corr, sums)))
    (host, host_sigma), (dev, dev_sigma) = results
    np.testing.assert_allclose(dev.r, host.r, atol=tol.PIV_TWIN)
    assert np.array_equal(dev.signal, host.signal) and host.signal.mean() > 0.9
    np.testing.assert_allclose(fit_direct(dev.r)[0], fit_direct(host.r)[0], atol=1e-4)
    assert np.nanmedian(host_sigma) > 0
    np.testing.assert_allclose(dev_sigma, host_sigma, rtol=1e-3, atol=1e-6)


def test_the_sums_run_beside_the_deformer(queue):
    assert isinstance(sums_for(DeviceDeformer(queue, 3)), DeviceSums)
    assert sums_for(HostDeformer(3)) is None
    assert sums_for(HostDeformer(5)) is None
