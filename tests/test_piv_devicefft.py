"""The FFT correlation on a device (``kernels/fftcorr.cl``,
:class:`plenocl.piv.devicefft.DeviceCorrelation`) against NumPy's FFT, the per-window
twins of ``plenocl.reference.fftcorr`` and the host's correlation, on awkward sizes; the
route between them (:class:`plenocl.piv.devicefft.FFTRoute`), and deformed volumes kept
on the device for the window sums."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array
import pytest
import tolerances as tol

from plenocl import flows
from plenocl.piv import PIVSettings, piv3d
from plenocl.piv.correlation import (
    correlate,
    fft_shape_of,
    gaussian_weight,
    window_grid,
    window_lows,
)
from plenocl.piv.deformation import DeviceDeformer
from plenocl.piv.devicefft import DEVICE_GAIN, DeviceCorrelation, FFTRoute, measured_routes
from plenocl.piv.devicesums import DeviceSums
from plenocl.reference import fftcorr as ref

#: (volume shape, window, overlap, pad, weighting): cubes and non-cubes, FFT lengths with
#: factors 2, 3 and 5 (16 padded to 24; 9, 25, 15, 10), a step of 1, Gaussian and top-hat
#: windows.
CASES = [((40, 44, 48), (16, 16, 16), 0.5, True, None),
         ((30, 33, 41), (12, 10, 15), 0.5, False, 0.35),
         ((21, 27, 36), (9, 25, 20), 0.75, False, None),
         ((24, 26, 28), (8, 8, 8), 0.9, False, 0.5),
         ((36, 30, 45), (24, 20, 30), 0.5, True, None)]


@pytest.fixture(scope="module")
def engine(queue):
    return DeviceCorrelation(queue)


#: Work-items per FFT line and per window: the device's default (1 on a CPU: one item
#: walks a line's butterflies in blocks), a GPU's 64 (the items stride over them, more
#: items than butterflies in short lines) and 4.
GROUPS = [None, 4, 64]


@pytest.fixture(scope="module", params=GROUPS, ids=lambda g: f"group{g}")
def grouped(queue, request):
    return DeviceCorrelation(queue, group=request.param)


def _pair(shape, shift=(0.6, -1.3, 2.2), seed=0):
    """Gaussian particles moved by ``shift`` (x, y, z voxels), with an empty corner (a
    window there may have no signal)."""
    pair = flows.volume_pair(shape, flows.Uniform(shift), density=0.01, sigma=1.0, seed=seed)
    a, b = pair.vol_a.copy(), pair.vol_b.copy()
    a[:8, :8, :8] = b[:8, :8, :8] = 0.0
    return a, b


@pytest.mark.parametrize("box", [(1, 1, 8), (3, 5, 6), (5, 12, 10), (9, 25, 16),
                                 (2, 4, 128), (27, 40, 1), (1, 512, 3)])
@pytest.mark.parametrize("sign", [-1.0, 1.0])
def test_fft_lines_match_numpy(grouped, queue, box, sign):
    """Every mixed-radix length (2, 3, 4, 5, 8 passes; 1 skipped) in both directions,
    unnormalised as FFTW, within float32 rounding of the spectrum's peak."""
    rng = np.random.default_rng(sum(box))
    x = (rng.normal(size=(3, *box)) + 1j * rng.normal(size=(3, *box))).astype(np.complex64)
    dev = cl_array.to_device(queue, x.reshape(-1, box[2]))
    grouped.transform(dev, box, 3, sign)
    axes = (1, 2, 3)
    want = np.fft.fftn(x, axes=axes) if sign < 0 else np.fft.ifftn(x, axes=axes) * np.prod(box)
    got = dev.get().reshape(x.shape)
    np.testing.assert_allclose(got, want, atol=tol.FFT_LINES * float(np.abs(want).max()))


def test_fft_skips_only_zero_lines(engine, queue):
    """Told where the values lie, the forward transform skips the zero lines beyond
    them and gives the whole box's transform."""
    box, window = (12, 10, 16), (7, 4, 9)
    rng = np.random.default_rng(1)
    x = np.zeros((2, *box), np.complex64)
    x[:, :7, :4, :9] = rng.normal(size=(2, *window)) + 1j * rng.normal(size=(2, *window))
    dev = cl_array.to_device(queue, x.reshape(-1, box[2]))
    engine.transform(dev, box, 2, -1.0, window)
    want = np.fft.fftn(x, axes=(1, 2, 3))
    np.testing.assert_allclose(dev.get().reshape(x.shape), want,
                               atol=tol.FFT_LINES * float(np.abs(want).max()))


@pytest.mark.parametrize("shape,size,overlap,pad,weighting", CASES)
def test_device_correlation_matches_its_twin(grouped, shape, size, overlap, pad, weighting):
    """Each window's displacement, peak and peak ratio are the float64 twin's (the packed
    box, its FFT, the cross spectrum, the inverse and the peak fit, one window at a
    time; the first, the last and 40 more); windows without signal come back empty."""
    a, b = _pair(shape)
    grid = window_grid(shape, size, overlap)
    weight = None if weighting is None else gaussian_weight(size, weighting)
    got = grouped.correlate(a, b, grid, pad=pad, weight=weight)
    box = fft_shape_of(grid, pad)
    count = int(np.prod(grid.count))
    some = np.unique(np.r_[0, count - 1, np.random.default_rng(count).integers(0, count, 40)])
    for k, low in zip(some, window_lows(grid, some)):  # the twin is slow: 42 windows
        index = np.unravel_index(k, grid.count)
        if not got.signal[index]:
            assert not np.any(b[tuple(slice(lo, lo + w) for lo, w in zip(low, size))])
            assert got.peak[index] == 0 and np.all(got.displacement[(slice(None), *index)] == 0)
            continue
        *disp, peak, ratio = ref.correlate_window(a, b, low, size, box, weight)
        np.testing.assert_allclose(got.displacement[(slice(None), *index)], disp,
                                   atol=tol.DISPLACEMENT)
        assert got.peak[index] == pytest.approx(peak, abs=tol.FFT_PLANE)
        assert got.peak_ratio[index] == pytest.approx(ratio, rel=tol.FFT_PLANE)


@pytest.mark.parametrize("shape,size,overlap,pad,weighting", CASES)
def test_device_correlation_matches_the_host(engine, shape, size, overlap, pad, weighting):
    """The device's correlation is the host's (SciPy's FFT) within float32, a selection
    of windows included, from host or device volumes."""
    a, b = _pair(shape, seed=3)
    grid = window_grid(shape, size, overlap)
    weight = None if weighting is None else gaussian_weight(size, weighting)
    select = np.arange(int(np.prod(grid.count))).reshape(grid.count) % 3 == 1
    for sel in (None, select):
        want = correlate(a, b, grid, pad=pad, weight=weight, select=sel, backend="scipy")
        for vols in ((a, b), (engine.upload(a), engine.upload(b))):
            got = engine.correlate(*vols, grid, pad=pad, weight=weight, select=sel)
            assert np.array_equal(got.signal, want.signal)
            np.testing.assert_allclose(got.displacement, want.displacement,
                                       atol=tol.DISPLACEMENT)
            np.testing.assert_allclose(got.peak, want.peak, atol=tol.FFT_PLANE)
            np.testing.assert_allclose(got.peak_ratio, want.peak_ratio, rtol=tol.FFT_PLANE)
    assert want.signal.any()


def test_the_window_weight_goes_up_once_and_follows_a_change(queue):
    """A pair's passes correlate with one window weight, which the device keeps: given
    again, it is not uploaded again (its bytes fewer to the device); a different weight,
    or none, is used from the call that gives it (each result the host's)."""
    from plenocl.bench.clprofile import OpenCLProfile

    a, b = _pair((30, 33, 41), seed=5)
    size = (12, 10, 15)
    grid = window_grid(a.shape, size, 0.5)
    engine = DeviceCorrelation(queue)
    vols = engine.upload(a), engine.upload(b)
    gauss = gaussian_weight(size, 0.35)
    moved = []
    for weight in (gauss, gaussian_weight(size, 0.5), None, gauss, gauss):
        with OpenCLProfile() as prof:
            got = engine.correlate(*vols, grid, weight=weight)
        moved.append(sum(c.nbytes for c in prof.calls if c.kind == "h2d"))
        want = correlate(a, b, grid, weight=weight, backend="scipy")
        np.testing.assert_allclose(got.displacement, want.displacement,
                                   atol=tol.DISPLACEMENT)
        np.testing.assert_allclose(got.peak, want.peak, atol=tol.FFT_PLANE)
    assert moved[4] + 4 * gauss.size == moved[3]


def test_a_shift_is_found_by_the_padded_first_pass(engine):
    """Physics, not only agreement: a uniform shift up to a fifth of the window, found by
    the padded device correlation, not aliased (an undeformed window loses pairs, which
    biases it towards 0 by about a tenth of a voxel here, as on the host)."""
    shift = (5.0, -4.0, 3.0)  # x, y, z voxels
    pair = flows.volume_pair((48, 48, 48), flows.Uniform(shift), density=0.006, seed=2)
    grid = window_grid((48, 48, 48), (24, 24, 24), 0.5)
    got = engine.correlate(pair.vol_a, pair.vol_b, grid, pad=True)
    median = [float(np.median(got.displacement[axis][got.signal])) for axis in (2, 1, 0)]
    assert median == pytest.approx(shift, abs=0.3)


def test_unsupported_lengths_are_refused_by_name(engine):
    grid = window_grid((30, 30, 30), (14, 14, 14), 0.5)  # 14 = 2 x 7
    assert not engine.supports(grid)
    a = np.zeros((30, 30, 30), np.float32)
    with pytest.raises(ValueError, match="prime factor above 5; correlate on the host"):
        engine.correlate(a, a, grid)


def test_mismatched_volumes_are_refused(engine, queue):
    grid = window_grid((20, 20, 20), (10, 10, 10), 0.5)
    a = np.zeros((20, 20, 20), np.float32)
    with pytest.raises(ValueError, match="3-D float32 of one shape"):
        engine.correlate(a, np.zeros((20, 20, 21), np.float32), grid)
    with pytest.raises(ValueError, match="3-D float32 of one shape"):
        engine.correlate(cl_array.to_device(queue, a.astype(np.float64)), a, grid)


def test_windows_are_gathered_as_sliced(engine):
    rng = np.random.default_rng(4)
    vol = rng.random((13, 17, 22)).astype(np.float32)
    grid = window_grid(vol.shape, (5, 9, 7), 0.5)
    lows = window_lows(grid, [0, 3, int(np.prod(grid.count)) - 1])
    got = engine.windows(engine.upload(vol), lows, grid.size)
    for k, (z, y, x) in enumerate(lows):
        assert np.array_equal(got[k], vol[z:z + 5, y:y + 9, x:x + 7])


def test_routes(queue):
    """``"device"`` and the host backends go where they say; ``None`` measures each box
    once (host and device timed), keeps the device where it is clearly faster, else the
    host, and returns its result; no device: the host."""
    a, b = _pair((30, 33, 41), seed=5)
    grid = window_grid(a.shape, (10, 12, 20), 0.5)   # a box no other test measures
    host = correlate(a, b, grid, backend="scipy")
    device = DeviceCorrelation(queue).correlate(a, b, grid)
    route = FFTRoute("device", queue)
    assert np.array_equal(route.correlate(a, b, grid).peak, device.peak)
    assert route.used == {"device"}
    route = FFTRoute("scipy", queue)
    assert np.array_equal(route.correlate(a, b, grid).peak, host.peak)
    assert route.used == {"host"} and route.route(a, grid, False) == "host"
    assert FFTRoute(None, None).route(a, grid, False) == "host"
    measured = FFTRoute(None, queue)
    assert measured.route(a, grid, False) is None
    got = measured.correlate(a, b, grid)
    (key, (chosen, host_s, device_s)), = [
        (k, v) for k, v in measured_routes().items()
        if k == (queue.device.name.strip(), (10, 12, 20), "host", False)]
    assert measured.used == {chosen} and host_s > 0 and device_s > 0
    assert chosen == ("device" if device_s <= DEVICE_GAIN * host_s else "host")
    assert measured.route(a, grid, False) == chosen
    want = device if chosen == "device" else correlate(a, b, grid)
    np.testing.assert_allclose(got.displacement, want.displacement, atol=tol.DISPLACEMENT)


def test_piv_with_the_device_fft_matches_the_host(queue):
    """A whole PIV run with every FFT on the device equals the host's FFTs within the
    displacement tolerance, the routes logged per pass."""
    flow = flows.Uniform((1.3, -0.7, 0.4))
    pair = flows.volume_pair((40, 48, 56), flow, density=0.004, seed=5)
    runs = {fft: piv3d(pair.vol_a, pair.vol_b, windows=(32, 16), queue=queue, fft=fft,
                       correlation="fft") for fft in ("device", "scipy")}
    for comp in "uvw":
        np.testing.assert_allclose(getattr(runs["device"], comp), getattr(runs["scipy"], comp),
                                   atol=tol.DISPLACEMENT)
    assert [p["fft_route"] for p in runs["device"].passes] == ["device"] * 4
    assert [p["fft_route"] for p in runs["scipy"].passes] == ["host"] * 4
    assert abs(float(np.median(runs["device"].u)) - 1.3) < 0.05


@pytest.mark.parametrize("fft", ["device", "scipy"])
def test_piv3d_reads_the_volumes_device_copies_instead_of_uploading_them(queue, fft):
    """``piv3d(on_device=...)`` (a reconstruction's device volumes): the same field to
    the bit, and no copy of a volume's size goes to the device (the particle count, the
    deformation and the device's first-pass FFT read the copies), where without them
    the volumes are uploaded."""
    from plenocl.bench.clprofile import OpenCLProfile

    a, b = _pair((40, 44, 48), shift=(1.2, -0.8, 0.5), seed=4)
    copies = tuple(cl_array.to_device(queue, v) for v in (a, b))
    runs = {}
    for name, kept in (("uploaded", None), ("kept", copies)):
        with OpenCLProfile() as prof:
            runs[name] = piv3d(a, b, queue=queue, fft=fft, on_device=kept)
            queue.finish()
        runs[name + " bytes"] = max(c.nbytes for c in prof.calls if c.kind == "h2d")
    for comp in ("u", "v", "w", "valid", "sigma_u", "sigma_w", "peak_ratio"):
        assert np.array_equal(getattr(runs["kept"], comp), getattr(runs["uploaded"], comp),
                              equal_nan=True), comp
    assert runs["kept bytes"] < a.nbytes <= runs["uploaded bytes"]
    assert runs["kept"].passes[0]["fft_route"] == {"device": "device", "scipy": "host"}[fft]


def test_piv3d_refuses_device_copies_that_are_not_the_volumes(queue):
    """A wrong ``on_device`` is refused by name with the fix, never read."""
    import pyopencl as cl

    a, b = _pair((24, 26, 28))
    good = cl_array.to_device(queue, a)
    context = cl.Context([queue.device])  # held: a driver may drop an unreferenced one
    other = cl.CommandQueue(context)
    for bad in ((good,), (good, cl_array.to_device(queue, a[:, :, :27].copy())),
                (good, cl_array.to_device(queue, b.astype(np.float64))),
                (good, cl_array.to_device(other, b)), (good, b)):
        with pytest.raises(ValueError, match="on_device"):
            piv3d(a, b, queue=queue, on_device=bad)


def test_fft_setting_is_checked():
    assert PIVSettings(fft="device").fft == "device"
    with pytest.raises(ValueError, match="'device'"):
        PIVSettings(fft="cuda")


def test_deformed_volumes_kept_on_the_device_give_the_same_sums(queue):
    """The deformer's device array (``keep``) is its host copy, and the window sums of
    device volumes are those of the same volumes from the host, to the bit."""
    rng = np.random.default_rng(6)
    vol = rng.random((13, 17, 22)).astype(np.float32)
    disp = rng.normal(0.0, 1.0, (3, *vol.shape)).astype(np.float32)
    deformer = DeviceDeformer(queue, 3)
    coeffs, field = deformer.prepare(vol), deformer.field(disp)
    kept = deformer(coeffs, field, 0.5, keep=True)
    assert isinstance(kept, cl_array.Array)
    host = deformer(coeffs, field, 0.5)
    assert np.array_equal(kept.get(), host)
    sums, grid = DeviceSums(queue), window_grid(vol.shape, (8, 9, 10), 0.5)
    for got, want in zip(sums.correlation_sums(kept, kept, grid, 0.35),
                         sums.correlation_sums(host, host, grid, 0.35)):
        assert np.array_equal(got, want)


def test_windows_without_signal_come_back_empty(engine):
    """A window of a volume without variance has no signal: zero displacement, peak and
    ratio, as the host's."""
    a = np.random.default_rng(7).random((20, 20, 20)).astype(np.float32)
    b = np.full_like(a, 3.0)
    grid = window_grid(a.shape, (10, 10, 10), 0.5)
    got = engine.correlate(a, b, grid, pad=True)
    assert not got.signal.any()
    assert not got.displacement.any() and not got.peak.any() and not got.peak_ratio.any()
    assert not correlate(a, b, grid, pad=True).signal.any()
