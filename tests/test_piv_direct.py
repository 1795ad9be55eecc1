"""Direct correlation of deformed passes (``plenocl.piv.direct``) against its plain twin,
its symmetry, its sub-voxel accuracy against the FFT path, and its use in ``piv3d``."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol

from plenocl import flows
from plenocl.piv import piv3d
from plenocl.piv.correlation import correlate, gaussian_weight, window_grid
from plenocl.piv.direct import LAGS, correlate_direct, correlation_uncertainty, fit_direct
from plenocl.reference.direct import correlate_windows


@pytest.mark.parametrize("weighting", [0.35, 0.2, None])
@pytest.mark.parametrize("shape,size,overlap", [((13, 17, 22), (8, 9, 10), 0.5),
                                                 ((11, 25, 9), (9, 8, 8), 0.75),
                                                 ((5, 12, 10), (5, 8, 8), 0.5)])
def test_direct_correlation_matches_its_twin(shape, size, overlap, weighting):
    rng = np.random.default_rng(sum(shape))
    a, b = (rng.random(shape).astype(np.float32) for _ in range(2))
    grid = window_grid(shape, size, overlap)
    got = correlate_direct(a, b, grid, weighting).r
    want = correlate_windows(a, b, grid, weighting)
    assert got.shape == (len(LAGS), *grid.count) == (63, *grid.count)
    np.testing.assert_allclose(got, want, atol=tol.PIV_TWIN)
    assert np.all(np.abs(got) <= 1 + tol.PEARSON)  # a Pearson coefficient


def test_identical_windows_give_zero_displacement():
    """The weight sits between the two windows and reaches past the window, so a volume
    against itself correlates symmetrically: lag +s equals lag -s, the fit gives 0, as
    the FFT's circular autocorrelation does."""
    pair = flows.volume_pair((40, 48, 56), flows.Uniform((0, 0, 0)), density=0.002,
                             sigma=1.5, seed=2)
    grid = window_grid(pair.vol_a.shape, (24, 24, 24), 0.5)
    corr = correlate_direct(pair.vol_a, pair.vol_a, grid, 0.35)
    mirrored = corr.r[::-1]  # LAGS reversed is -LAGS
    assert np.array_equal(LAGS[::-1], -LAGS)
    np.testing.assert_allclose(corr.r, mirrored, atol=2e-3)   # zeros beyond the faces
    disp, peak, centred = fit_direct(corr.r)
    assert centred.all() and np.allclose(peak, 1.0, atol=tol.PEARSON)
    assert np.abs(disp).max() < 0.01


@pytest.mark.parametrize("shift", [(0.31, -0.27, 0.18), (0.45, 0.1, -0.4)])
def test_direct_sub_voxel_fit_beats_the_undeformed_fft(shift):
    """Rendered particles moved by less than a voxel: the direct fit is within 0.05 voxel
    RMS and no worse than the FFT of the same windows (circular, so edge pairs are lost)."""
    pair = flows.volume_pair((48, 64, 64), flows.Uniform(shift), density=0.0015, sigma=1.5,
                             seed=3, noise=0.02)
    grid = window_grid(pair.vol_a.shape, (24, 24, 24), 0.5)
    disp, _, centred = fit_direct(correlate_direct(pair.vol_a, pair.vol_b, grid, 0.35).r)
    fft = correlate(pair.vol_a, pair.vol_b, grid, weight=gaussian_weight((24,) * 3, 0.35))
    truth = np.array(shift[::-1])[:, None, None, None]   # (dz, dy, dx)
    rms_direct = np.sqrt(np.mean((disp - truth) ** 2, axis=(1, 2, 3)))
    rms_fft = np.sqrt(np.mean((fft.displacement - truth) ** 2, axis=(1, 2, 3)))
    assert centred.mean() > 0.9
    assert np.all(rms_direct < 0.05), rms_direct
    assert rms_direct.mean() <= rms_fft.mean() + 0.005, (rms_direct, rms_fft)


def test_a_peak_a_voxel_off_in_depth_is_fitted_without_the_fft(monkeypatch):
    """The depth lags reach three voxels: residuals of 1.3 and 2.3 voxels in depth (a
    plenoptic volume's usual ones after a deformation) are fitted among them as
    accurately as the FFT fits them, and no window goes to the FFT; 3.3 voxels is beyond
    them."""
    import plenocl.piv.direct as direct

    grid = window_grid((48, 64, 64), (24, 24, 24), 0.5)
    for depth in (1.3, 2.3):
        shift = (0.2, -0.1, depth)   # (x, y, z) voxels
        pair = flows.volume_pair((48, 64, 64), flows.Uniform(shift), density=0.0015,
                                 sigma=1.5, seed=5, noise=0.02)
        disp, peak, fitted = fit_direct(correlate_direct(pair.vol_a, pair.vol_b, grid,
                                                         0.35).r)
        truth = np.array(shift[::-1])[:, None, None, None]
        fft = correlate(pair.vol_a, pair.vol_b, grid, weight=gaussian_weight((24,) * 3, 0.35))
        assert fitted.all() and np.all(peak > 0.5)
        rms = np.sqrt(np.mean((disp - truth) ** 2, axis=(1, 2, 3)))
        rms_fft = np.sqrt(np.mean((fft.displacement - truth) ** 2, axis=(1, 2, 3)))
        assert np.all(rms < 0.06) and rms.mean() <= rms_fft.mean() + 0.005, (rms, rms_fft)
    res = piv3d(pair.vol_a, pair.vol_b, windows=(32, 24))   # each pass says how many
    assert [p["fft_windows"] for p in res.passes][1:] == [0, 0, 0]
    assert res.passes[0]["fft_windows"] == res.passes[0]["vectors"]   # the first: all
    sent = []
    monkeypatch.setattr(direct, "correlate", lambda *a, select, **k: sent.append(select))
    direct.correlate_deformed(pair.vol_a, pair.vol_b, grid, 0.35)
    assert not sent                                  # every window fitted directly
    far = flows.volume_pair((48, 64, 64), flows.Uniform((0.2, -0.1, 3.3)), density=0.0015,
                            sigma=1.5, seed=5, noise=0.02)
    r = correlate_direct(far.vol_a, far.vol_b, grid, 0.35).r
    assert not fit_direct(r)[2].any() and np.all(LAGS[np.argmax(r, axis=0)][..., 0] == 3)


def test_piv3d_direct_passes_equal_the_fft_passes_in_accuracy(queue):
    shift = (2.31, -1.47, 0.68)
    pair = flows.volume_pair((48, 64, 80), flows.Uniform(shift), density=0.002, sigma=1.5,
                             seed=1, noise=0.02)
    results = {mode: piv3d(pair.vol_a, pair.vol_b, windows=(32, 24), queue=queue,
                           correlation=mode) for mode in ("fft", "auto")}
    assert [p["correlation"] for p in results["auto"].passes] == ["fft", "direct", "direct",
                                                                  "direct"]
    assert {p["correlation"] for p in results["fft"].passes} == {"fft"}
    assert all(p["fft_windows"] == p["vectors"] for p in results["fft"].passes)
    errors = {}
    for mode, res in results.items():
        errors[mode] = np.array([np.sqrt(np.mean((c - s) ** 2))
                                 for c, s in zip((res.u, res.v, res.w), shift)])
        assert res.valid.mean() > 0.95
    assert np.all(errors["auto"] < 0.05) and errors["auto"].mean() <= errors["fft"].mean() + 0.005
    auto = results["auto"]
    assert np.all(np.isnan(auto.peak_ratio))        # no secondary peak in 63 lags
    assert not np.isnan(results["fft"].peak_ratio).any()
    ratio = piv3d(pair.vol_a, pair.vol_b, windows=(32, 24), queue=queue, min_peak_ratio=1.2)
    assert ratio.passes[-1]["correlation"] == "fft" and not np.isnan(ratio.peak_ratio).any()
    top_hat = piv3d(pair.vol_a, pair.vol_b, windows=(32, 24), queue=queue, weighting=None)
    assert {p["correlation"] for p in top_hat.passes} == {"fft"}
    with pytest.raises(ValueError, match="correlation must be"):
        piv3d(pair.vol_a, pair.vol_b, correlation="direct-ish")


def test_uncertainty_grows_with_noise_and_is_nan_where_invalid():
    shift = (0.2, -0.1, 0.3)
    sigmas = []
    for noise in (0.02, 0.3):
        pair = flows.volume_pair((40, 48, 48), flows.Uniform(shift), density=0.002,
                                 sigma=1.5, seed=6, noise=noise)
        grid = window_grid(pair.vol_a.shape, (24, 24, 24), 0.5)
        corr = correlate_direct(pair.vol_a, pair.vol_b, grid, 0.35)
        sigma = correlation_uncertainty(pair.vol_a, pair.vol_b, grid, 0.35, corr)
        assert sigma.shape == (3, *grid.count) and np.all(sigma[:, corr.signal] >= 0)
        sigmas.append(np.nanmedian(sigma))
    assert sigmas[1] > 2 * sigmas[0]
    flat = np.zeros((40, 48, 48), np.float32)
    grid = window_grid(flat.shape, (24, 24, 24), 0.5)
    corr = correlate_direct(flat, flat, grid, 0.35)
    assert not corr.signal.any()
    assert np.isnan(correlation_uncertainty(flat, flat, grid, 0.35, corr)).all()


def test_direct_sums_do_not_depend_on_the_thread_count(monkeypatch):
    """A serial run (all cores) and Dask workers (fewer threads each) must give the same
    fields bit for bit: each window sum is computed by one thread with one BLAS thread."""
    from threadpoolctl import threadpool_limits

    pair = flows.volume_pair((32, 48, 48), flows.Uniform((0.3, -0.2, 0.1)), density=0.004,
                             sigma=1.5, seed=8, noise=0.05)
    grid = window_grid(pair.vol_a.shape, (16, 16, 16), 0.75)
    results = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("PLENOCL_THREADS", threads)
        with threadpool_limits(int(threads), user_api="blas"):
            corr = correlate_direct(pair.vol_a, pair.vol_b, grid, 0.35)
            sigma = correlation_uncertainty(pair.vol_a, pair.vol_b, grid, 0.35, corr)
        results.append((corr.r, sigma))
    for r, sigma in results[1:]:
        assert np.array_equal(r, results[0][0])
        assert np.array_equal(sigma, results[0][1], equal_nan=True)
