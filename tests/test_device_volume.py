"""A volume kept on the device (``kernels/volume.cl``,
:class:`plenocl.opencl.volume.DeviceVolume`): its summary and voxels' neighbourhoods
against the NumPy twins (:mod:`plenocl.reference.volume`) on awkward shapes and values,
the stages that read it (the checks and particle count of :func:`plenocl.piv3d`, the
particles of :func:`plenocl.peaks.find_particles`) giving what its host copy gives, and
:func:`plenocl.process_pair` returning the vectors alone with fewer bytes back."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from plenocl import flows
from plenocl.opencl.volume import SUMMARY_PARTS, DeviceVolume, host_volume
from plenocl.peaks import find_particles
from plenocl.piv import count_particles, piv3d
from plenocl.piv.devicepeaks import DeviceMaxima
from plenocl.reference import volume as twin

#: ... and more rows than the summary's parts (393: not a multiple of them).
SHAPES = [(1, 1, 1), (1, 1, 5), (2, 7, 3), (13, 17, 21), (5, 1, 33), (3, 131, 4)]


def _awkward(shape, seed: int, special: bool = True) -> np.ndarray:
    """Noise with zeros, negatives and (``special``) NaN, +inf and -inf voxels; one row
    entirely not finite where the volume has more than one row."""
    rng = np.random.default_rng(seed)
    vol = (rng.random(shape) * 4 - 1).astype(np.float32)
    vol[rng.random(shape) < 0.3] = 0.0
    if special:
        flat = vol.reshape(-1)
        flat[rng.integers(0, flat.size, 3)] = [np.nan, np.inf, -np.inf]
        if shape[0] * shape[1] > 1:
            vol[-1, -1, :] = np.nan
    return vol


def _on(queue, vol: np.ndarray) -> DeviceVolume:
    return DeviceVolume(cla.to_device(queue, vol))


@pytest.mark.parametrize("shape", SHAPES)
def test_summary_is_the_twins_rows_combined(queue, shape):
    """Extremes of the finite voxels, voxels not finite and non-zero (NaN counted), as
    the twin's rows and NumPy's whole-volume figures say."""
    vol = _awkward(shape, sum(shape))
    low, high, bad, lit = twin.row_summary(vol)
    got = _on(queue, vol).summary()
    finite = vol[np.isfinite(vol)]
    assert got.low == float(low.min()) == (finite.min() if finite.size else np.inf)
    assert got.high == float(high.max()) == (finite.max() if finite.size else -np.inf)
    assert got.nonfinite == int(bad.sum()) == int((~np.isfinite(vol)).sum())
    assert got.nonzero == int(lit.sum()) == np.count_nonzero(vol)


def test_summary_reads_back_its_parts_not_its_rows(queue):
    """A volume of 30,000 rows (a paper-size reconstruction's) is summarised with a few
    kilobytes back, not 16 bytes a row, and the figures are NumPy's."""
    from plenocl.bench.clprofile import OpenCLProfile

    vol = _awkward((150, 200, 9), 5)
    on = _on(queue, vol)
    with OpenCLProfile() as prof:
        got = on.summary()
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    assert back <= 24 * SUMMARY_PARTS < 16 * 150 * 200
    assert (got.nonfinite, got.nonzero) == (int((~np.isfinite(vol)).sum()),
                                            np.count_nonzero(vol))
    assert got.high == vol[np.isfinite(vol)].max()


@pytest.mark.parametrize("shape", SHAPES)
def test_neighbourhoods_are_the_twins(queue, shape):
    """Every voxel's value and its six face neighbours, 0 beyond the faces, bit for bit
    (NaN where a voxel is NaN); the centre column is the volume itself."""
    vol = _awkward(shape, 3 * sum(shape))
    flat = np.random.default_rng(1).permutation(vol.size)
    got = _on(queue, vol).neighbourhoods(flat)
    want = twin.neighbourhoods(vol, flat)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[:, 0], vol.reshape(-1)[flat])
    assert _on(queue, vol).neighbourhoods(np.zeros(0, int)).shape == (0, 7)


def test_twin_neighbourhoods_read_the_faces_as_zero():
    """The twin itself: a voxel on the x = 0 face has 0 at x - 1, its x + 1 neighbour
    the next voxel, and a 1-voxel volume has zeros all round."""
    vol = np.arange(1, 25, dtype=np.float32).reshape(2, 3, 4)
    near = twin.neighbourhoods(vol, np.array([0, 23]))
    np.testing.assert_array_equal(near[0], [1, 0, 2, 0, 5, 0, 13])
    np.testing.assert_array_equal(near[1], [24, 23, 0, 20, 0, 12, 0])
    np.testing.assert_array_equal(twin.neighbourhoods(np.ones((1, 1, 1), np.float32),
                                                      [0])[0], [1, 0, 0, 0, 0, 0, 0])


def test_device_volume_is_copied_once_and_refuses_a_view(queue):
    vol = _awkward((4, 5, 6), 2, special=False)
    dev = _on(queue, vol)
    np.testing.assert_array_equal(np.asarray(dev), vol)
    assert dev.get() is dev.get() and host_volume(dev) is dev.get()
    assert np.asarray(dev) is dev.get() and np.array(dev) is not dev.get()  # copy=True
    with pytest.raises(IndexError, match=r"\[0, 120\)"):
        dev.neighbourhoods([0, 120])
    assert (dev.shape, dev.ndim, dev.size, dev.dtype) == (vol.shape, 3, vol.size, np.float32)
    with pytest.raises(ValueError, match="contiguous float32"):
        DeviceVolume(cla.to_device(queue, vol.astype(np.float64)))
    with pytest.raises(ValueError, match="contiguous float32"):
        DeviceVolume(cla.to_device(queue, vol[0]))


def _particles(seed: int, shape=(20, 26, 31), n: int = 60) -> np.ndarray:
    """Gaussian particles (one on a face) on a faint noisy floor."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform([0, 0, 0], np.array(shape[::-1]) - 1, (n, 3))
    pos[0] = (0.0, 5.0, 7.0)
    vol = flows.render_particles(shape, pos, sigma=1.0)
    return (vol + 0.01 * rng.random(shape)).astype(np.float32)


@pytest.mark.parametrize("reference", ["max", "robust"])
@pytest.mark.parametrize("on_device_maxima", [False, True])
def test_particles_of_a_device_volume_are_its_host_copys(queue, reference,
                                                         on_device_maxima):
    """The same positions and values, bit for bit, with the maxima found on the host (of
    the copy) or on the device; and a particle count the same."""
    vol = _particles(5)
    maxima = DeviceMaxima(queue) if on_device_maxima else None
    want = find_particles(vol, 0.1, reference=reference, maxima=maxima)
    got = find_particles(_on(queue, vol), 0.1, reference=reference, maxima=maxima)
    assert len(want[0]) > 20
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert (count_particles(_on(queue, vol), maxima=maxima)
            == count_particles(vol, maxima=maxima))


def test_particles_of_an_empty_or_dark_device_volume(queue):
    empty = _on(queue, np.zeros((0, 4, 5), np.float32)).summary()
    assert (empty.low, empty.high, empty.nonfinite, empty.nonzero) == (np.inf, -np.inf, 0, 0)
    for vol in (np.zeros((3, 4, 5), np.float32), -np.ones((3, 4, 5), np.float32)):
        peaks, values = find_particles(_on(queue, vol))
        assert peaks.shape == (0, 3) and values.shape == (0,)
        assert count_particles(_on(queue, vol)) == 0


@pytest.mark.parametrize("bad", [np.inf, np.nan])
def test_particles_of_a_device_volume_not_finite_are_its_host_copys(queue, bad):
    """A voxel not finite: the maximum NumPy's, so the same particles as the host copy's
    (what a direct caller gets; piv3d refuses such volumes first)."""
    vol = _particles(6)
    vol[2, 3, 4] = bad
    for g, w in zip(find_particles(_on(queue, vol)), find_particles(vol), strict=True):
        np.testing.assert_array_equal(g, w)
    assert count_particles(_on(queue, vol)) == count_particles(vol)


def test_device_maxima_read_a_device_volume_where_it_is(queue):
    """The device's maxima of a DeviceVolume on its context: no copy of the volume back."""
    from plenocl.bench.clprofile import OpenCLProfile

    vol = _particles(8)
    dev, maxima = _on(queue, vol), DeviceMaxima(queue)
    want = find_particles(vol, maxima=maxima)
    with OpenCLProfile() as prof:
        got = find_particles(dev, maxima=maxima)
    back = [c.nbytes for c in prof.calls if c.kind == "d2h"]
    assert back and max(back) < vol.nbytes
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("fft", ["device", "scipy"])
def test_piv_of_device_volumes_is_piv_of_their_host_copies(queue, fft):
    """The same field, bit for bit, whether the volumes come as host arrays or stay on
    the device (the first pass's FFT on the device, or on the host of their copies)."""
    a = _particles(7, shape=(24, 32, 32), n=180)
    b = np.roll(a, 2, axis=2)
    opts = {"windows": (16, 16), "fft": fft, "queue": queue}
    want = piv3d(a, b, **opts)
    got = piv3d(_on(queue, a), _on(queue, b), **opts)
    for name in ("u", "v", "w"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert abs(np.nanmedian(want.u) - 2.0) < 0.1  # a real field


@pytest.mark.parametrize("bad, message", [
    (np.nan, "1 NaN/Inf"), (-np.inf, "1 NaN/Inf"), ("constant", "is constant"),
    ("negative", "negative intensities")])
def test_piv_refuses_a_device_volume_as_its_host_copy(queue, bad, message):
    """The checks read the summary: the same errors as the host volume's."""
    vol = _particles(3, shape=(16, 16, 16), n=20)
    if bad == "constant":
        vol[:] = 2.0
    elif bad == "negative":
        vol = -vol
    else:
        vol[3, 4, 5] = bad
    for form in (vol, _on(queue, vol)):
        with pytest.raises(ValueError, match=message):
            piv3d(form, vol, windows=(16,), queue=queue)


@pytest.mark.filterwarnings("ignore:the final windows")
def test_piv_warns_of_a_device_volumes_background(queue):
    vol = _particles(4, shape=(16, 16, 16), n=20) + 5.0
    with pytest.warns(UserWarning, match="darkest voxel"):
        piv3d(_on(queue, vol), vol, windows=(16,), queue=queue)
