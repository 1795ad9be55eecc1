"""The fast PIV paths against their references: the deformation kernel
(``kernels/deform.cl``) against SciPy's ``map_coordinates``, FFTW against SciPy's
pocketfft, and ``piv3d`` on a device against ``piv3d`` on the host."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol

from plenocl import flows
from plenocl.piv import fft as pivfft
from plenocl.piv import piv3d
from plenocl.piv.correlation import correlate, padded_size, window_grid
from plenocl.piv.deformation import DeviceDeformer, HostDeformer, make_deformer


@pytest.mark.parametrize("order", [1, 3])
@pytest.mark.parametrize("shape", [(13, 17, 21), (9, 30, 11)])
def test_deform_kernel_matches_scipy(queue, order, shape):
    rng = np.random.default_rng(sum(shape) + order)
    vol = rng.random(shape).astype(np.float32)
    # smooth enough to be a predictor, large enough that samples leave the volume
    disp = rng.normal(0.0, 2.5, (3, *shape)).astype(np.float32)
    host, device = HostDeformer(order), DeviceDeformer(queue, order)
    for factor in (-0.5, 0.5):
        want = host(host.prepare(vol), host.field(disp), factor)
        got = device(device.prepare(vol), device.field(disp), factor)
        np.testing.assert_allclose(got, want, atol=tol.PIV_TWIN * float(np.abs(want).max()))
    assert np.count_nonzero(want == 0) < want.size  # the test samples real data


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 7, 3), (13, 17, 21), (40, 9, 33)])
def test_spline_prefilter_kernel_matches_scipy(queue, shape):
    """The device's B-spline coefficients of a padded volume are SciPy's (the host
    prepare) within float32, on awkward sizes, a bright sparse volume included; order 1
    is the padded volume itself, bit for bit."""
    from plenocl.piv.interpolate import prepare

    rng = np.random.default_rng(sum(shape))
    for vol in (rng.random(shape).astype(np.float32),
                (rng.random(shape) ** 12 * 1e4).astype(np.float32)):
        want = prepare(vol, 3)
        got = DeviceDeformer(queue, 3).prepare(vol).get()
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=tol.PIV_TWIN * float(np.abs(want).max()))
        assert np.array_equal(DeviceDeformer(queue, 1).prepare(vol).get(), prepare(vol, 1))


@pytest.mark.parametrize("kind", ["cubic", "linear"])
@pytest.mark.parametrize("counts, shape", [((3, 4, 5), (13, 17, 21)), ((1, 2, 7), (5, 9, 40)),
                                           ((6, 3, 2), (31, 8, 7))])
def test_predictor_kernel_matches_the_host_resampling(queue, kind, counts, shape):
    """The dense predictor made on the device (``resample_axis``, x, y, then z) is the
    host's tensor-product resampling within float32, on awkward sizes: fewer than three
    centres on an axis (linear there), centres not starting at the first voxel, and
    voxels beyond the outermost centres (extrapolated linearly)."""
    rng = np.random.default_rng(sum(counts) + sum(shape))
    field = rng.normal(0.0, 2.0, (3, *counts))
    source = tuple(np.sort(rng.uniform(1.0, n - 2.0, c)) + np.arange(c) * 1e-3
                   for c, n in zip(counts, shape))
    want = HostDeformer(3).predictor(field, source, shape, kind)
    got = DeviceDeformer(queue, 3).predictor(field, source, shape, kind).get()
    assert got.shape == want.shape == (3, *shape)
    np.testing.assert_allclose(got, want, atol=tol.PIV_TWIN * float(np.abs(want).max()))
    if kind == "linear" and min(counts) >= 2:  # a linear field stays linear, beyond too
        z, y, x = np.meshgrid(*source, indexing="ij")
        plane = np.stack([0.5 * z - 0.2 * y + 0.1 * x + 1.0] * 3)
        zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
        exact = 0.5 * zz - 0.2 * yy + 0.1 * xx + 1.0
        dense = DeviceDeformer(queue, 3).predictor(plane, source, shape, kind).get()
        np.testing.assert_allclose(dense[0], exact, atol=1e-4 * float(np.abs(exact).max()))


def test_device_deformer_refuses_the_quintic_spline(queue):
    with pytest.raises(ValueError, match="queue=False"):
        DeviceDeformer(queue, 5)


def test_deformers_follow_the_device_choice(queue):
    """None and a queue deform on a device (the default one for None), False on the
    host; the quintic spline, which has no kernel, on the host whatever the queue (so
    deform_order = 5 works where process_pair passes its projector's queue)."""
    assert isinstance(make_deformer(3, None), DeviceDeformer)
    assert make_deformer(3, queue).kernels.queue is queue
    assert isinstance(make_deformer(3, False), HostDeformer)
    assert isinstance(make_deformer(5, queue), HostDeformer)
    assert isinstance(make_deformer(5, None), HostDeformer)


def test_without_a_device_the_deformer_names_the_host(monkeypatch):
    """No OpenCL device: the default choice's error also says how to deform on the host."""
    from plenocl.opencl.device import NoOpenCLError
    from plenocl.piv import deformation

    def none(*args, **kwargs):
        raise NoOpenCLError("no OpenCL device here builds plenocl's kernels")

    monkeypatch.setattr(deformation, "get_queue", none)
    with pytest.raises(NoOpenCLError, match=r"queue=False"):
        make_deformer(3, None)
    assert isinstance(make_deformer(3, False), HostDeformer)


@pytest.mark.skipif(pivfft.pyfftw is None, reason="pyfftw is not installed")
@pytest.mark.parametrize("window, fft_shape, count", [((8, 12, 10), (8, 12, 10), 5),
                                                      ((8, 8, 8), (12, 12, 12), 7)])
def test_fftw_correlation_matches_scipy(window, fft_shape, count):
    rng = np.random.default_rng(3)
    data = rng.random((2, count, *window)).astype(np.float32)
    planes = []
    for backend in ("fftw", "scipy"):
        fft = pivfft.CorrelationFFT(9, window, fft_shape, 2, backend)
        for k in range(2):
            fft.windows(k, count)[...] = data[k]
        planes.append(fft.correlate(count) / fft.scale)
    np.testing.assert_allclose(planes[0], planes[1], atol=tol.PIV_TWIN * float(planes[1].max()))
    # the definition: c(s) = sum_p a(p) b(p + s), circular over the FFT shape
    a = np.zeros(fft_shape, np.float32)
    b = np.zeros(fft_shape, np.float32)
    a[:window[0], :window[1], :window[2]] = data[0, 0]
    b[:window[0], :window[1], :window[2]] = data[1, 0]
    s = (1, 2, 3)
    want = float(np.sum(a * np.roll(b, [-k for k in s], axis=(0, 1, 2))))
    assert planes[1][0][s] == pytest.approx(want, rel=1e-4)


@pytest.mark.skipif(pivfft.pyfftw is None, reason="pyfftw is not installed")
def test_fftw_plans_kept_are_the_most_recently_used_within_the_budget(monkeypatch):
    """A thread keeps the plans it used last: one used again is not planned again while
    newer ones come (the second pair of a process replanned its first pass when the
    oldest made went first); past the count or the byte budget the least recently used
    go, the newest always stays."""
    monkeypatch.setattr(pivfft._LOCAL, "plans", {}, raising=False)
    monkeypatch.setattr(pivfft, "PLAN_COUNT", 3)
    window = (4, 4, 4)

    def plans(batch: int):
        return pivfft._fftw_plans((batch, 8, 8, 8), window, 1)

    first = plans(1)
    for batch in (2, 3):
        plans(batch)
        assert plans(1) is first  # used again: kept as the most recent
    plans(4)  # the fourth: batch 2, the least recently used, goes
    kept = [key[0][0] for key in pivfft._LOCAL.plans]
    assert kept == [3, 1, 4]
    one = pivfft._plan_bytes({"k": first})
    assert one == 3 * 8**3 * 4 + 2 * 8 * 8 * 5 * 8  # three real boxes, two half spectra
    monkeypatch.setattr(pivfft, "PLAN_BYTES", 5 * one)  # batches 1 + 4 fit, not + 3
    plans(1)
    assert [key[0][0] for key in pivfft._LOCAL.plans] == [4, 1]
    monkeypatch.setattr(pivfft, "PLAN_BYTES", 1)
    big = plans(5)
    assert list(pivfft._LOCAL.plans.values()) == [big]  # the newest, alone over budget


def test_padded_first_pass_is_linear_up_to_a_third_of_the_window():
    for w in range(8, 97):
        size = padded_size(w)
        assert 3 * (size - w) >= w and size % 2 == 0 and size < 1.6 * w + 4
        rest = size
        for p in (2, 3, 5):
            while rest % p == 0:
                rest //= p
        assert rest == 1, (w, size)
    shift = (0.0, 5.0, -7.0)   # (x, y, z): z by -7 voxels, more than a quarter of 24
    pair = flows.volume_pair((24, 24, 64), flows.Uniform(shift), density=0.01, seed=4)
    grid = window_grid((24, 24, 64), (24, 24, 32), 0.5)
    corr = correlate(pair.vol_a, pair.vol_b, grid, pad=True)
    dz, dy, dx = (np.median(c) for c in corr.displacement)
    # found, not aliased; an undeformed window loses pairs, which biases it towards 0
    assert (dx, dy, dz) == pytest.approx(shift, abs=0.3)


def test_piv_on_a_device_equals_piv_on_the_host(queue):
    flow = flows.Uniform((1.3, -0.7, 0.4))
    pair = flows.volume_pair((40, 48, 56), flow, density=0.004, seed=5)
    host = piv3d(pair.vol_a, pair.vol_b, windows=(32, 16), queue=False)
    device = piv3d(pair.vol_a, pair.vol_b, windows=(32, 16), queue=queue)
    for comp in "uvw":
        np.testing.assert_allclose(getattr(device, comp), getattr(host, comp),
                                   atol=tol.DISPLACEMENT)
    assert np.array_equal(device.valid, host.valid)
    assert abs(float(np.median(host.u)) - 1.3) < 0.05
