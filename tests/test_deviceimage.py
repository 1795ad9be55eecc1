"""A camera's integer counts prepared on the device (``kernels/rawcounts.cl``,
:mod:`plenocl.reconstruction.deviceimage`; issue 46): the kernel against its NumPy twin,
and the whole preparation against the host's, to the bit."""

from __future__ import annotations

import numpy as np
import pytest

import plenocl
from plenocl.bench.clprofile import OpenCLProfile
from plenocl.opencl.arrays import upload
from plenocl.optics.rawimage import CountHistogram, check_exposure, count_histogram
from plenocl.pipeline import process_pair
from plenocl.piv import PIVSettings
from plenocl.reconstruction import (
    ReconstructionSettings,
    UnusableImageError,
    prepare_on_host,
    prepares_on_device,
    run_reconstruction,
)
from plenocl.reconstruction.deviceimage import (
    COUNT_TYPES,
    LEVEL_BLOCK,
    DeviceCounts,
    occupied_runs,
)
from plenocl.reconstruction.images import prepare_image
from plenocl.reference.rawcounts import level_blocks, level_counts, scaled_counts

REC = ReconstructionSettings(iterations=3, coarse_iterations=2)
GRID = plenocl.Grid((16, 24, 24), x=(-1.2, 1.2), y=(-1.2, 1.2), z=(-1.5, 1.5))


@pytest.fixture(scope="module")
def scene(queue):
    """A small camera's projector and two 16-bit raw images of 60 particles (a dark
    level of 50 counts and read noise), the second moved 0.2 mm along x."""
    cam = plenocl.Camera.synthetic_850()
    pos, inten = plenocl.random_particles(((-1.1, 1.1), (-1.1, 1.1), (-1.4, 1.4)),
                                          count=60, seed=3, intensity=3e4)
    rng = np.random.default_rng(5)
    raws = [np.rint(plenocl.simulate_image(cam, pos + [dx, 0.0, 0.0], inten, 1000, seed=k,
                                           blur_px=0.5, queue=queue)
                    + 50.0 + rng.normal(0.0, 2.0, cam.pixels[::-1])).astype(np.uint16)
            for k, dx in enumerate((0, 0.2))]
    return cam, plenocl.Projector(cam, GRID, queue), raws


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two float32 arrays hold the same bits."""
    return a.shape == b.shape and np.array_equal(np.asarray(a, np.float32).view(np.uint32),
                                                 np.asarray(b, np.float32).view(np.uint32))


@pytest.mark.parametrize("dtype", sorted(COUNT_TYPES, key=str))
@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (129, 67)])
def test_scaled_counts_match_their_twin_bit_for_bit(queue, dtype, shape):
    """Every type, awkward sizes, whole and half-count medians, scales that do not divide
    evenly: the kernel's float32 image is the twin's (float64 division rounded once)."""
    info = np.iinfo(dtype)
    rng = np.random.default_rng(shape[0] * shape[1])
    raw = rng.integers(max(info.min, 0), info.max, shape, endpoint=True).astype(dtype)
    counts = DeviceCounts(queue, dtype)
    for median, scale in ((0.0, 1.0), (3.5, 7.0), (17.0, 3.0), (100.5, info.max - 100.5)):
        got = counts.scaled(raw, median, scale).get()
        want = scaled_counts(raw, median, scale)
        assert same_bits(got, want), (median, scale)
        assert got.min() >= 0  # counts below the median clipped


@pytest.mark.parametrize("group", [None, 64], ids=["device-group", "group64"])
@pytest.mark.parametrize("dtype", sorted(COUNT_TYPES, key=str))
@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (129, 67), (600, 701)])
def test_level_counts_on_the_device_are_the_hosts(queue, dtype, shape, group):
    """Every type, awkward sizes (one pixel; sizes no multiple of the groups), both
    extreme levels and a background level most pixels share (the atomics' hot spot with
    groups of 64): the device's histogram is the host's bincount, to the count, its
    lowest and highest levels the frame's."""
    info = np.iinfo(dtype)
    rng = np.random.default_rng(shape[0] + shape[1])
    raw = rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)
    raw[rng.random(shape) < 0.7] = 100
    if raw.size > 2:
        raw.flat[0], raw.flat[-1] = info.max, info.min
    counts = DeviceCounts(queue, dtype, group=group)
    hist = counts.histogram(raw)
    assert (hist.low, hist.high, hist.size) == (raw.min(), raw.max(), raw.size)
    want = level_counts(raw, counts.low, counts.levels)
    np.testing.assert_array_equal(hist.counts, want[hist.low - counts.low:
                                                    hist.high - counts.low + 1])
    if info.min == 0:  # the host's own histogram of the frame
        host = count_histogram(raw)
        assert host.low == hist.low
        np.testing.assert_array_equal(host.counts, hist.counts)
    assert counts.histogram(raw[:0]) is None


@pytest.mark.parametrize("dtype", sorted(COUNT_TYPES, key=str))
def test_level_blocks_are_their_twins(queue, dtype):
    """``level_blocks`` over a device histogram with pixels at scattered levels (the
    first and last level, a block's edges, the last block partial where the levels are no
    multiple of the block) is its twin's, to the count."""
    counts = DeviceCounts(queue, dtype)
    rng = np.random.default_rng(counts.levels)
    levels = np.zeros(counts.levels, np.uint32)
    picked = rng.choice(counts.levels, min(40, counts.levels), replace=False)
    levels[picked] = rng.integers(1, 10**6, len(picked))
    levels[[0, -1, min(255, counts.levels - 1)]] = (7, 9, 11)
    np.testing.assert_array_equal(counts.level_blocks(upload(queue, levels)),
                                  level_blocks(levels, LEVEL_BLOCK))
    some = np.arange(300)
    assert level_blocks(some, 256).tolist() == [some[:256].sum(), some[256:].sum()]


def test_a_frame_of_few_levels_reads_back_its_blocks_not_every_level(queue):
    """A 16-bit frame whose counts fill 300 of its 65,536 levels (a camera's dark level
    and particles) reads back its blocks and the few occupied ones, not 256 kB; the
    histogram is the frame's."""
    rng = np.random.default_rng(8)
    raw = (1000 + rng.integers(0, 300, (64, 96))).astype(np.uint16)
    counts = DeviceCounts(queue, np.uint16)
    on_device = counts.upload(raw)
    with OpenCLProfile() as prof:
        hist = counts.histogram(raw, on_device)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    assert back <= 4 * (65536 // LEVEL_BLOCK + 3 * LEVEL_BLOCK) < 4 * 65536 / 50
    host = count_histogram(raw)
    assert (hist.low, hist.high) == (host.low, host.high) == (raw.min(), raw.max())
    np.testing.assert_array_equal(hist.counts, host.counts)


def test_a_dark_frame_with_saturated_pixels_reads_two_runs_not_the_levels_between(queue):
    """A 16-bit frame at a dark level of about 100 with a few pixels at 65,535 reads its
    two occupied runs of levels (the 256 levels of each block), not the 65,000 empty
    ones between; the histogram is the frame's, its highest level the saturated one."""
    rng = np.random.default_rng(9)
    raw = (90 + rng.integers(0, 20, (50, 70))).astype(np.uint16)
    raw.flat[[5, 77, 3000]] = 65535
    counts = DeviceCounts(queue, np.uint16)
    on_device = counts.upload(raw)
    with OpenCLProfile() as prof:
        hist = counts.histogram(raw, on_device)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    assert back == 4 * (65536 // LEVEL_BLOCK + 2 * LEVEL_BLOCK)
    host = count_histogram(raw)
    assert (hist.low, hist.high, hist.counts[-1]) == (host.low, 65535, 3)
    np.testing.assert_array_equal(hist.counts, host.counts)


def test_occupied_runs_join_neighbouring_blocks():
    """Runs of consecutive occupied blocks, each as its levels ``[start, stop)``, the
    last block's ending at the histogram's last level."""
    blocks = np.array([0, 3, 1, 0, 0, 7, 0, 2])
    assert occupied_runs(blocks, 2048) == [(256, 768), (1280, 1536), (1792, 2048)]
    assert occupied_runs(blocks, 1900) == [(256, 768), (1280, 1536), (1792, 1900)]
    assert occupied_runs(np.array([5]), 256) == [(0, 256)]


def test_scaled_counts_refuse_what_float32_cannot_hold(queue):
    """A median that is not a whole or half count, or a scale of zero, named."""
    counts = DeviceCounts(queue, np.uint16)
    raw = np.arange(12, dtype=np.uint16).reshape(3, 4)
    for median, scale in ((0.1, 2.0), (1.0, 0.0), (1.0, 16777217.0)):
        with pytest.raises(ValueError, match="exact in float32"):
            counts.scaled(raw, median, scale)
    with pytest.raises(ValueError, match="prepared on the host"):
        DeviceCounts(queue, np.uint32)


def test_a_histogram_checks_and_measures_as_the_frame_does():
    """:class:`CountHistogram`: the median, noise and exposure refusals of the frame."""
    from plenocl.optics.rawimage import median_and_noise

    rng = np.random.default_rng(0)
    frame = rng.poisson(40, (50, 70)).astype(np.uint16)
    frame[:3, :5] = 4000
    hist = count_histogram(frame)
    assert (hist.low, hist.high, hist.size) == (frame.min(), frame.max(), frame.size)
    med, noise = np.median(frame), 1.4826 * np.median(np.abs(frame - np.median(frame)))
    assert hist.median_and_noise() == pytest.approx((med, noise), abs=0) == median_and_noise(frame)
    for bad in (np.zeros_like(frame), np.full_like(frame, 7),
                np.where(np.arange(frame.size).reshape(frame.shape) % 3, 900, 20)):
        with pytest.raises(ValueError) as want:
            check_exposure(bad)
        with pytest.raises(ValueError) as got:
            count_histogram(bad.astype(np.uint16)).check_exposure()
        assert str(got.value) == str(want.value)
    assert CountHistogram(5, np.array([2, 0, 1])).high == 7


@pytest.mark.parametrize("settings", [REC, ReconstructionSettings(background=None),
                                      ReconstructionSettings(threshold=3.0)],
                         ids=["median", "no-background", "threshold"])
def test_counts_prepared_on_the_device_are_the_hosts(scene, settings):
    """The default preparation of 16-bit counts on the device: no host image, and the
    host's scale, threshold, background, noise, lit lenses and image bits; the norm
    (from the histogram, in float64) within float32's sums of the host's."""
    cam, proj, (raw, _) = scene
    assert prepares_on_device(raw, settings.background, settings.smooth_px, None)
    host = prepare_on_host(raw, cam, settings)
    with OpenCLProfile() as prof:
        dev = prepare_image(raw, proj, settings)
    assert dev.image is None
    assert (dev.scale, dev.threshold, dev.background, dev.noise) == (
        host.scale, host.threshold, host.background, host.noise)
    assert same_bits(dev.on_device(proj.queue).get(), host.image)
    assert same_bits(dev.host_image(), host.image)
    np.testing.assert_array_equal(dev.lit, prepare_image(raw.astype(float), proj, settings).lit)
    assert dev.norm() == pytest.approx(host.norm(), rel=1e-4)
    uploads = sum(call.nbytes for call in prof.calls if call.kind == "h2d")
    assert raw.nbytes <= uploads < raw.nbytes + 0.01 * host.image.nbytes  # the counts alone


def test_other_images_are_prepared_on_the_host(scene):
    """Floats, wider integers, counts below zero, a pixel mask or smoothing: the host."""
    cam, proj, (raw, _) = scene
    signed = raw.astype(np.int16) - np.int16(60)  # a dark level over-subtracted
    for image, settings, mask in ((raw.astype(np.float32), REC, None),
                                  (raw.astype(np.uint32), REC, None),
                                  (signed, REC, None),
                                  (raw, ReconstructionSettings(smooth_px=0.7), None),
                                  (raw, REC, np.ones(raw.shape, bool))):
        prepared = prepare_image(image, proj, settings, observed=mask)
        want = prepare_on_host(image, cam, settings, observed=mask)
        assert prepared.image is not None
        assert same_bits(prepared.image, want.image) and prepared.scale == want.scale


def test_an_unusable_frame_of_counts_is_refused_as_on_the_host(scene):
    """Blank, uniform, saturated and all-dark frames: the host's refusal, word for word."""
    cam, proj, (raw, _) = scene
    saturated = raw.copy()
    saturated[: 3 * raw.shape[0] // 4] = 65535
    for bad in (np.zeros_like(raw), np.full_like(raw, 50), saturated):
        with pytest.raises(UnusableImageError) as want:
            prepare_on_host(bad, cam, REC)
        with pytest.raises(UnusableImageError) as got:
            prepare_image(bad, proj, REC)
        assert str(got.value) == str(want.value)
    above = ReconstructionSettings(threshold=1e6)  # every pixel at or below it
    with pytest.raises(UnusableImageError, match="dark-pixel threshold") as want:
        prepare_image(raw.astype(float), proj, above)
    with pytest.raises(UnusableImageError) as got:
        prepare_image(raw, proj, above)
    assert str(got.value) == str(want.value)


def test_a_reconstruction_and_pair_of_counts_are_those_of_their_floats(scene):
    """The volume and the fit's background-free image of 16-bit counts prepared on the
    device are those of the same counts as floats (prepared on the host), bit for bit;
    the fit's image is not copied to the host unless read. A pair's vectors alike."""
    _, proj, raws = scene
    want, want_info = run_reconstruction(raws[0].astype(float), proj, REC,
                                         keep_for_next_stage=True)
    got, got_info = run_reconstruction(raws[0], proj, REC, keep_for_next_stage=True)
    assert want.get().max() > 0
    np.testing.assert_array_equal(got.get(), want.get())
    free = got_info.background_free
    assert free.on_device is not None
    with OpenCLProfile() as prof:
        assert free.shape == raws[0].shape and free.dtype == np.float32
        first, again = free.values, free.values
    back = [call.nbytes for call in prof.calls if call.kind == "d2h"]
    assert back == [first.nbytes] and again is first  # copied at the first read, once
    assert same_bits(first, want_info.background_free.values)
    assert free.scale == want_info.background_free.scale
    kw = dict(reconstruction=REC, piv=PIVSettings(windows=(16, 16)))
    pair, floats = (process_pair(*raws, proj, **kw),
                    process_pair(*(r.astype(float) for r in raws), proj, **kw))
    for name in ("u", "v", "w", "sigma_u", "sigma_w"):
        np.testing.assert_array_equal(getattr(pair.piv, name), getattr(floats.piv, name))


def test_a_pair_off_a_cpu_prepares_counts_on_the_device_not_ahead(scene, monkeypatch):
    """Off a CPU (``is_cpu`` answering False) the second exposure of floats is prepared
    ahead on a helper thread; a camera's counts are prepared on the device instead, with
    no host preparation at all, and the same field as the floats'."""
    from plenocl.pipeline import pair as pair_module

    _, proj, raws = scene
    calls = []
    real = pair_module.prepare_on_host

    def spy(*args, **kwargs):
        calls.append(args[0].dtype)
        return real(*args, **kwargs)

    monkeypatch.setattr(pair_module, "is_cpu", lambda device: False)
    monkeypatch.setattr(pair_module, "prepare_on_host", spy)
    monkeypatch.setenv("PLENOCL_THREADS", "2")
    kw = dict(reconstruction=REC, piv=PIVSettings(windows=[8]), particles=False)
    floats = process_pair(*(r.astype(np.float32) for r in raws), proj, **kw)
    assert calls == [np.dtype(np.float32)]
    counts = process_pair(*raws, proj, **kw)
    assert calls == [np.dtype(np.float32)]  # none for the counts
    for name in ("u", "v", "w"):
        np.testing.assert_array_equal(getattr(counts.piv, name), getattr(floats.piv, name))
