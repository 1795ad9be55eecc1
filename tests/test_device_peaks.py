"""A volume's local maxima on the device (``kernels/peaks.cl``,
:class:`plenocl.piv.devicepeaks.DeviceMaxima`) against the host's maximum filter
(:func:`plenocl.peaks.host_maxima`), and the particles and counts found with them."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl import flows
from plenocl.peaks import find_particles, host_maxima
from plenocl.piv import count_particles, devicepeaks
from plenocl.piv.devicepeaks import DeviceMaxima


def _awkward_volume(shape, seed: int) -> np.ndarray:
    """Noise with plateaus (ties), negative voxels on the faces and a few bright peaks."""
    rng = np.random.default_rng(seed)
    vol = rng.random(shape).astype(np.float32)
    vol[rng.random(shape) < 0.2] = 0.5                  # plateaus of equal voxels
    vol[0], vol[:, -1] = -rng.random(vol[0].shape), -0.25  # faces below the outside's 0
    vol[tuple(rng.integers(0, n, 5) for n in shape)] = 7.0
    return vol


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 7, 3), (13, 17, 21), (40, 9, 33)])
@pytest.mark.parametrize("reach", [1, 2])
def test_device_maxima_are_the_host_maximum_filters(queue, shape, reach):
    """The same voxels, in the same (ascending) order, at several floors: ties count as
    maxima, a negative voxel at a face is none (the filter's zeros beyond it), and the
    first launch's too few slots (noise has a maximum in every few voxels) are grown."""
    vol = _awkward_volume(shape, sum(shape) + reach)
    device = DeviceMaxima(queue)
    for floor in (-1.0, 0.0, 0.3, 0.99, 7.0):
        want = host_maxima(vol, floor, reach)
        got = device(vol, floor, reach)
        np.testing.assert_array_equal(got, want)
    assert len(host_maxima(vol, -1.0, reach)) > 0  # the test compares real maxima


def test_device_maxima_grow_their_slots(queue, monkeypatch):
    """More candidates than the first launch has slots for: the list is grown and the
    kernel run again, nothing lost."""
    monkeypatch.setattr(devicepeaks, "START_SHARE", 1e-9)
    vol = _awkward_volume((30, 40, 50), 3)
    want = host_maxima(vol, 0.0)
    assert len(want) > 1024  # beyond the smallest first list
    np.testing.assert_array_equal(DeviceMaxima(queue)(vol, 0.0), want)


def test_particles_and_counts_are_the_same_with_the_device_maxima(queue):
    """find_particles (both references) and count_particles give the host's results bit
    for bit with the device's maxima, on a particle volume."""
    pair = flows.volume_pair((24, 30, 36), flows.Uniform((0.5, 0.2, 0.1)), density=0.002,
                             sigma=1.2, seed=4, noise=0.02)
    device = DeviceMaxima(queue)
    for reference in ("max", "robust"):
        want = find_particles(pair.vol_a, 0.1, reference=reference)
        got = find_particles(pair.vol_a, 0.1, reference=reference, maxima=device)
        assert len(want[0]) > 5
        for w, g in zip(want, got):
            np.testing.assert_array_equal(g, w)
    assert count_particles(pair.vol_a, maxima=device) == count_particles(pair.vol_a) > 5
