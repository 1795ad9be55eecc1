"""What a GPU pays outside its kernels (issue 46, docs/design.md §7.5): the second
exposure's host preparation made ahead (``run_reconstruction(ahead=)`` and
``process_pair`` on a device that is not a CPU give what the images prepared in turn
give, bit for bit), and the solver's buffers kept over its iterations."""

from __future__ import annotations

import dataclasses
import threading
import weakref

import numpy as np
import pytest

import plenocl
from plenocl.pipeline import pair as pair_module
from plenocl.pipeline import process_pair
from plenocl.piv import PIVSettings
from plenocl.reconstruction import (
    ReconstructionSettings,
    UnusableImageError,
    prepare_on_host,
    run_reconstruction,
)

REC = ReconstructionSettings(iterations=3, coarse_iterations=2)
GRID = plenocl.Grid((16, 24, 24), x=(-1.2, 1.2), y=(-1.2, 1.2), z=(-1.5, 1.5))


@pytest.fixture(scope="module")
def scene(queue):
    """A small camera's projector and two raw images of 60 particles, the second moved
    0.2 mm along x, with a dark level and noise."""
    cam = plenocl.Camera.synthetic_850()
    pos, inten = plenocl.random_particles(((-1.1, 1.1), (-1.1, 1.1), (-1.4, 1.4)),
                                          count=60, seed=3, intensity=3e4)
    rng = np.random.default_rng(5)
    raws = [plenocl.simulate_image(cam, pos + [dx, 0.0, 0.0], inten, 1000, seed=k,
                                   blur_px=0.5, queue=queue)
            + 50.0 + rng.normal(0.0, 2.0, cam.pixels[::-1]) for k, dx in enumerate((0, 0.2))]
    return cam, plenocl.Projector(cam, GRID, queue), raws


def test_an_image_prepared_ahead_gives_the_same_reconstruction(scene):
    """The volume, its device copy, background, noise and the fit's background-free
    image as the image prepared in turn gives them, kept for the next stage or not;
    refused with other settings, a pixel mask or for several cameras."""
    cam, proj, (raw, _) = scene
    want, info = run_reconstruction(raw, proj, REC, keep_for_next_stage=True)
    ahead = prepare_on_host(raw, cam, REC)
    got, got_info = run_reconstruction(raw, proj, REC, keep_for_next_stage=True,
                                       ahead=ahead)
    want, got = want.get(), got.get()  # kept on the device (DeviceVolume)
    assert want.max() > 0
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_info.volume_on_device.get(), got)
    np.testing.assert_array_equal(got_info.background_free.values, info.background_free.values)
    assert got_info.background_free.scale == info.background_free.scale
    assert (got_info.background, got_info.noise) == (info.background, info.noise)
    with pytest.raises(ValueError, match="without a pixel mask"):
        run_reconstruction(raw, proj, REC, pixel_mask=np.ones(raw.shape, bool), ahead=ahead)
    with pytest.raises(ValueError, match="one camera"):
        run_reconstruction([raw, raw], [proj, proj], REC, ahead=ahead)
    plain, plain_info = run_reconstruction(raw, proj, REC, ahead=ahead)  # nothing kept
    assert isinstance(plain, np.ndarray)  # the host volume
    np.testing.assert_array_equal(plain, want)
    assert plain_info.volume_on_device is None and plain_info.background_free is None
    for other in (dataclasses.replace(REC, threshold=5.0),
                  dataclasses.replace(REC, smooth_px=0.7)):
        with pytest.raises(ValueError, match="other settings"):
            run_reconstruction(raw, proj, other, keep_for_next_stage=True, ahead=ahead)


def test_a_pair_off_a_cpu_prepares_its_second_image_on_a_helper_thread(scene, monkeypatch):
    """With ``is_cpu`` answering False (this device then takes a GPU's path) the second
    exposure's preparation runs on the helper thread while the first reconstructs: the
    same volumes and field, bit for bit; a blank second exposure is still named."""
    _, proj, (raw_a, raw_b) = scene
    kw = dict(reconstruction=REC, piv=PIVSettings(windows=[8]), particles=False)
    want = process_pair(raw_a, raw_b, proj, **kw)
    threads = []
    real = pair_module.prepare_on_host

    def spy(*args, **kwargs):
        threads.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(pair_module, "is_cpu", lambda device: False)
    monkeypatch.setattr(pair_module, "prepare_on_host", spy)
    monkeypatch.setenv("PLENOCL_THREADS", "1")  # one thread allowed: in turn
    process_pair(raw_a, raw_b, proj, **kw)
    assert threads == []
    monkeypatch.setenv("PLENOCL_THREADS", "2")
    got = process_pair(raw_a, raw_b, proj, **kw)
    assert len(threads) == 1 and threads[0].startswith("plenocl-prepare")
    assert want.vol_b.max() > 0
    for a, b in ((got.vol_a, want.vol_a), (got.vol_b, want.vol_b), (got.piv.u, want.piv.u),
                 (got.piv.v, want.piv.v), (got.piv.w, want.piv.w)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(UnusableImageError, match="raw_b: the image is blank") as err:
        process_pair(raw_a, np.zeros_like(raw_b), proj, **kw)
    assert err.value.which == "b"


def test_one_solver_at_a_time_holds_its_kept_buffers(scene, monkeypatch):
    """A coarse-to-fine reconstruction (three runs, each a solver, some cropped): each
    kept buffer is made once per solver and reused over its iterations, and a solver
    lets go of them when its iterations end or it is cropped, so at most one projection,
    ratio and back projection are alive at a time; the volume as without keeping them."""
    from plenocl.reconstruction import Solver

    cam, proj, (raw, _) = scene
    made, alive = [], []
    real = Solver.kept

    def tracking(self, name, make):
        def counted():
            out = make()
            made.append((name, weakref.ref(out[0] if isinstance(out, list) else out)))
            return out
        got = real(self, name, counted)
        alive.append(max(sum(1 for n, r in made if n == k and r() is not None)
                         for k in ("projection", "ratio", "back projection")))
        return got

    want, _ = run_reconstruction(raw, proj, REC)
    monkeypatch.setattr(Solver, "kept", tracking)
    got, info = run_reconstruction(raw, proj, REC)
    np.testing.assert_array_equal(got, want)
    assert len(made) % 3 == 0 and len(made) < len(alive)  # made per solver, then reused
    assert max(alive) == 1
    monkeypatch.setattr(Solver, "kept", lambda self, name, make: make())
    np.testing.assert_array_equal(run_reconstruction(raw, proj, REC)[0], want)


@pytest.mark.filterwarnings("ignore:the final windows", "ignore:every window's centre")
@pytest.mark.parametrize("fft", ["device", "scipy"])
def test_a_pair_asked_for_its_vectors_alone_leaves_its_volumes_on_the_device(scene, fft):
    """``process_pair(volumes=False)``: the same field, bit for bit, as the pair that
    returns its volumes, no volume in the result, and (the first pass's FFT on the
    device) no volume ever copied back: its bytes back fall by both volumes."""
    from plenocl.bench.clprofile import OpenCLProfile

    _, proj, raws = scene
    settings = {"reconstruction": REC, "piv": PIVSettings(windows=(16, 16), fft=fft)}
    runs = {}
    for volumes in (True, False):
        with OpenCLProfile() as prof:
            runs[volumes] = process_pair(*raws, proj, volumes=volumes, **settings)
        runs[volumes, "back"] = [c.nbytes for c in prof.calls if c.kind == "d2h"]
    kept, alone = runs[True], runs[False]
    assert alone.vol_a is None and alone.vol_b is None
    assert isinstance(kept.vol_a, np.ndarray) and kept.vol_a.max() > 0
    for name in ("u", "v", "w", "sigma_u", "sigma_w"):
        np.testing.assert_array_equal(getattr(alone.piv, name), getattr(kept.piv, name))
    assert alone.piv.refinement["pairs"] > 10  # the particles were found and paired
    nbytes = kept.vol_a.nbytes
    assert runs[True, "back"].count(nbytes) >= 2  # the volumes came back
    if fft == "device":
        assert nbytes not in runs[False, "back"]
        assert sum(runs[True, "back"]) - sum(runs[False, "back"]) >= 2 * nbytes
