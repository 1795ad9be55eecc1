"""The OpenCL profile of the benchmarks (plenocl.bench.clprofile), the stage spans of a
pair it attributes calls to, and the one composition of volumes to a refined field
(plenocl.pipeline.refined_field) that times those stages."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import pytest

from plenocl import get_queue
from plenocl.bench.clprofile import (
    OpenCLProfile,
    covered,
    kernel_lines,
    split_lines,
    total_profile,
)
from plenocl.pipeline import StageClock


def test_profile_counts_bytes_launches_and_host_time(queue):
    """Bytes each way are the arrays copied, launches the kernels run, the kernels' device
    time comes from their events, and a stage's host work is its wall time less the time
    inside OpenCL calls (a sleep between calls is host work)."""
    pq = get_queue(queue, profiling=True)
    host = np.arange(250_000, dtype=np.float32)
    clock = StageClock()
    with OpenCLProfile() as prof:
        with clock.stage("up"):
            dev = cl_array.to_device(pq, host)
            time.sleep(0.05)
        with clock.stage("work"):
            for _ in range(3):
                dev *= 2.0
            pq.finish()
        with clock.stage("down"):
            back = dev.get()
    assert np.array_equal(back, host * 8)
    split = prof.split(clock.spans)
    assert split["up"].h2d_bytes == host.nbytes and split["up"].d2h_bytes == 0
    # the host waited for the queue in the blocking write, the finish and the read
    assert (split["up"].waits, split["work"].waits, split["down"].waits) == (1, 1, 1)
    assert split["down"].d2h_bytes == host.nbytes and split["down"].h2d_bytes == 0
    assert split["work"].launches == 3 and split["up"].launches == 0
    assert split["work"].kernel is not None and 0 < split["work"].kernel <= split["work"].wall
    assert split["up"].host >= 0.05 > split["up"].opencl
    assert split["up"].wall == pytest.approx(clock.seconds["up"])
    lines = split_lines(split)
    assert lines[-1].split()[0] == "total" and len(lines) == 5
    total = total_profile(split)
    assert total.h2d_bytes == total.d2h_bytes == host.nbytes and total.launches == 3
    assert total.waits == 3
    assert total.wall == pytest.approx(sum(clock.seconds.values()))
    # by kernel: pyopencl's one multiply kernel, three launches, all the kernels' time
    by_kernel = prof.kernel_seconds()
    assert [n for n, _ in by_kernel.values()] == [3]
    assert sum(t for _, t in by_kernel.values()) == pytest.approx(split["work"].kernel)
    table = kernel_lines(by_kernel)
    assert len(table) == 2 and table[1].split()[1:3] == ["3", f"{split['work'].kernel:.4f}"]


def test_uploads_made_with_their_buffers_count_as_copies_to_the_device(queue):
    """plenocl's uploads (``arrays.upload``: the buffer made from the host array, no
    command on the queue) count their bytes to the device like ``enqueue_copy``; an
    empty array moves none; the profile puts the function back after the block."""
    from plenocl.opencl import arrays

    host = np.arange(12_345, dtype=np.int32)
    clock = StageClock()
    saved = arrays.buffer_from_host
    with OpenCLProfile() as prof:
        with clock.stage("up"):
            dev = arrays.upload(queue, host)
            empty = arrays.upload(queue, np.zeros(0, np.float32))
    assert arrays.buffer_from_host is saved
    assert np.array_equal(dev.get(), host) and empty.size == 0
    split = prof.split(clock.spans)
    assert split["up"].h2d_bytes == host.nbytes and split["up"].calls == {"h2d": 1}
    assert split["up"].waits == 0  # no command on the queue, nothing waited for


def test_covered_is_the_length_of_the_union():
    """Overlapping, nested, touching and disjoint intervals, in any order."""
    assert covered([]) == 0.0
    assert covered([(0.0, 1.0), (0.5, 2.0)]) == pytest.approx(2.0)
    assert covered([(0.0, 3.0), (1.0, 2.0)]) == pytest.approx(3.0)
    assert covered([(4.0, 5.0), (0.0, 1.0), (1.0, 1.5)]) == pytest.approx(2.5)


def test_two_threads_waiting_at_once_count_once(queue):
    """A stage whose two threads each wait on the device at the same time spends that
    time in OpenCL once: the sum of the calls (0.3 s) would exceed the stage's wall time
    and hide its host work."""
    clock = StageClock()
    barrier = threading.Barrier(2)

    def wait_together():
        barrier.wait()
        cl.wait_for_events([_slow_event(queue.context, 0.15)])

    with OpenCLProfile() as prof, clock.stage("both"):
        threads = [threading.Thread(target=wait_together) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    stage = prof.split(clock.spans)["both"]
    assert stage.calls["wait"] == 2
    # each wait starts a moment after its event's timer, so it lasts a little under
    # 0.15 s (0.149 s under load): the union is bounded by the waits' own spans
    spans = [(c.start, c.end) for c in prof.calls if c.kind == "wait"]
    longest, total = max(e - s for s, e in spans), sum(e - s for s, e in spans)
    assert longest > 0.1 and stage.opencl == pytest.approx(covered(spans))
    assert longest <= stage.opencl < 0.25 and stage.opencl < total - 0.1
    assert stage.opencl <= stage.wall


def _slow_event(context: cl.Context, seconds: float) -> cl.UserEvent:
    """A user event completed ``seconds`` from now by a timer thread."""
    event = cl.UserEvent(context)
    timer = threading.Timer(seconds, event.set_status, (cl.command_execution_status.COMPLETE,))
    timer.start()
    return event


def test_profile_restores_pyopencl(queue):
    """Outside the block every pyopencl function is its own again, on an error too."""
    before = (cl.enqueue_copy, cl.CommandQueue.finish, cl.Event.wait, cl.wait_for_events)
    with pytest.raises(RuntimeError), OpenCLProfile():
        assert cl.enqueue_copy is not before[0]
        raise RuntimeError("inside")
    assert (cl.enqueue_copy, cl.CommandQueue.finish, cl.Event.wait,
            cl.wait_for_events) == before


def _small_pair(queue, camera, count: int, shift: float, seed: int):
    """A projector on a 24-voxel cube and two raw images of ``count`` particles moved by
    ``shift`` mm along every axis."""
    from plenocl import Grid, Projector, simulate_image

    grid = Grid((24, 24, 24), x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-1.0, 1.0))
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-0.5, 0.5, count), rng.uniform(-0.4, 0.4, count),
                           rng.uniform(-0.8, 0.8, count)])
    raws = [simulate_image(camera, pos + d, 2e4, 500, seed=k, queue=queue)
            for k, d in enumerate((0.0, shift))]
    return Projector(camera, grid, queue), raws


@pytest.mark.filterwarnings("ignore:the final windows")  # a tiny volume: one vector
def test_a_pairs_stage_spans_follow_each_other(queue, small_camera):
    """process_pair's spans are ordered, disjoint and as long as its seconds."""
    from plenocl import process_pair

    proj, raws = _small_pair(queue, small_camera, 30, 0.05, seed=2)
    pair = process_pair(*raws, proj, image_fit=None)
    names = list(pair.spans)
    assert names[:3] == ["reconstruct_a", "reconstruct_b", "piv"]
    assert set(names) == set(pair.seconds) and pair.dropped == 0  # no image fit
    ends = [pair.spans[n] for n in names]
    assert all(a[1] <= b[0] for a, b in zip(ends, ends[1:]))
    for n in names:
        assert pair.spans[n][1] - pair.spans[n][0] == pytest.approx(pair.seconds[n])


@pytest.mark.filterwarnings("ignore:the final windows")  # a tiny volume: one vector
def test_refined_field_is_the_pairs_composition(queue, small_camera):
    """process_pair's field is refined_field's on its volumes (the one composition the
    piv command and the demo call too), bit for bit; without the particle switch it is
    the correlation alone."""
    from plenocl import process_pair
    from plenocl.pipeline import PairSettings, refined_field
    from plenocl.pipeline.pair import known_backgrounds
    from plenocl.piv import piv3d

    proj, raws = _small_pair(queue, small_camera, 40, 0.04, seed=3)
    grid = proj.grid
    pair = process_pair(*raws, proj)
    settings = PairSettings()
    again = refined_field(pair.vol_a, pair.vol_b, grid, settings, queue, camera=small_camera,
                          raws=raws, backgrounds=known_backgrounds(pair.info_a, pair.info_b))
    for name in ("u", "v", "w", "valid"):
        np.testing.assert_array_equal(getattr(again, name), getattr(pair.piv, name))
    assert again.refinement == pair.piv.refinement
    plain = refined_field(pair.vol_a, pair.vol_b, grid, PairSettings(particles=False), queue)
    np.testing.assert_array_equal(plain.u, piv3d(pair.vol_a, pair.vol_b, queue=queue).u)


@pytest.mark.filterwarnings("ignore:the final windows")  # a tiny volume: one vector
def test_a_pairs_volumes_go_from_its_reconstructions_to_piv_on_the_device(queue,
                                                                        small_camera):
    """process_pair hands each reconstruction's device volume to PIV and the particle
    stage: neither sends a volume to the device (the same chain on the host volumes
    does), the field is the same to the bit, and the pair's infos hold no device memory
    (and no kept image) after."""
    from plenocl import process_pair
    from plenocl.pipeline import PairSettings, refined_field

    proj, raws = _small_pair(queue, small_camera, 40, 0.04, seed=3)
    settings = PairSettings(image_fit=None)
    with OpenCLProfile() as prof:
        pair = process_pair(*raws, proj, settings)
        queue.finish()
    nbytes = pair.vol_a.nbytes

    def largest_upload(start: float, end: float = np.inf) -> int:
        return max([c.nbytes for c in prof.calls
                    if c.kind == "h2d" and start <= c.start < end], default=0)

    assert largest_upload(pair.spans["piv"][0]) < nbytes
    assert all(info.volume_on_device is None and info.background_free is None
               for info in (pair.info_a, pair.info_b))
    with OpenCLProfile() as prof:
        again = refined_field(pair.vol_a, pair.vol_b, proj.grid, settings, queue,
                              camera=small_camera)
        queue.finish()
    assert largest_upload(0.0) >= nbytes  # the host volumes are uploaded
    for name in ("u", "v", "w", "valid", "sigma_u", "sigma_w"):
        assert np.array_equal(getattr(again, name), getattr(pair.piv, name),
                              equal_nan=True), name


@pytest.mark.filterwarnings("ignore:the final windows")  # a tiny volume: one vector
def test_a_pairs_image_fit_reads_the_images_its_reconstructions_uploaded(queue,
                                                                        small_camera):
    """With the image fit, process_pair sends each raw image to the device once: the
    particle stage uploads no image (the fit reads the reconstructions' device copies,
    ``info.background_free.on_device``), where the same fit given the host images alone
    uploads both; the field is the same to the bit."""
    from plenocl import process_pair
    from plenocl.pipeline import PairSettings, refined_field
    from plenocl.pipeline.pair import known_backgrounds

    proj, raws = _small_pair(queue, small_camera, 40, 0.04, seed=3)
    image_bytes = 4 * raws[0].size  # one float32 image

    def image_uploads(prof, start: float) -> int:
        return sum(c.kind == "h2d" and c.nbytes >= image_bytes and c.start >= start
                   for c in prof.calls)

    with OpenCLProfile() as prof:
        pair = process_pair(*raws, proj)
        queue.finish()
    assert pair.piv.refinement["pairs"] > 0  # the fit ran on matched particles
    assert image_uploads(prof, 0.0) == 2 and image_uploads(prof, pair.spans["piv"][0]) == 0
    with OpenCLProfile() as prof:
        again = refined_field(pair.vol_a, pair.vol_b, proj.grid, PairSettings(), queue,
                              camera=small_camera, raws=raws,
                              backgrounds=known_backgrounds(pair.info_a, pair.info_b))
        queue.finish()
    assert image_uploads(prof, 0.0) == 2
    for name in ("u", "v", "w", "valid", "sigma_u", "sigma_w"):
        assert np.array_equal(getattr(again, name), getattr(pair.piv, name),
                              equal_nan=True), name


@pytest.mark.filterwarnings("ignore:the final windows")  # a tiny volume: one vector
def test_a_pair_with_one_background_known_fits_as_before(queue, small_camera):
    """Without background removal (``background=None``) a dark-subtracted image (pixels
    below zero: background 0) and one without such pixels (no background known): the
    image fit removes both images' backgrounds itself, as before the hand-over, and the
    pair's field is ``refined_field``'s on its volumes and raw images, bit for bit."""
    from plenocl import process_pair
    from plenocl.pipeline import PairSettings, refined_field
    from plenocl.pipeline.pair import known_backgrounds
    from plenocl.reconstruction import ReconstructionSettings

    proj, raws = _small_pair(queue, small_camera, 40, 0.04, seed=3)
    noisy = raws[0] + np.random.default_rng(1).normal(0.0, 1.0, raws[0].shape)
    raws = [noisy.astype(np.float32), raws[1]]
    settings = PairSettings(reconstruction=ReconstructionSettings(background=None))
    pair = process_pair(*raws, proj, settings)
    assert pair.info_a.background == 0.0 and pair.info_b.background is None
    assert known_backgrounds(pair.info_a, pair.info_b) is None
    again = refined_field(pair.vol_a, pair.vol_b, proj.grid, settings, queue,
                          camera=small_camera, raws=raws)
    for name in ("u", "v", "w", "valid"):
        assert np.array_equal(getattr(again, name), getattr(pair.piv, name)), name


def _package_function(source: str, module: str, **names):
    """A function compiled as if it were in plenocl's package at ``module`` (the frames
    :func:`copy_site` names), its globals ``names``."""
    from plenocl.bench import clprofile

    namespace = dict(names)
    exec(compile(source, str(clprofile.PACKAGE / module), "exec"), namespace)
    return namespace


def test_copies_are_told_by_the_plenocl_function_that_made_them(queue):
    """With ``sites=True`` each copy's bytes go to the innermost plenocl function outside
    its OpenCL layer (and that function's caller); a copy made outside plenocl goes to
    ''; without ``sites`` nothing is recorded."""
    from plenocl.bench.clprofile import copy_site, site_lines
    from plenocl.opencl import arrays

    ns = _package_function(
        "def fetch(dev):\n    return dev.get()\n"
        "def upload(queue, host):\n    return arrays.upload(queue, host)\n"
        "def both(queue, host):\n    return fetch(upload(queue, host))\n"
        "def listed(queue, host):\n    return [arrays.upload(queue, h) for h in [host]]\n",
        "piv/madeup.py", arrays=arrays)
    host = np.arange(1000, dtype=np.float32)
    with OpenCLProfile(sites=True) as prof:
        back = ns["both"](queue, host)
        cl_array.to_device(queue, host[:10])
        ns["listed"](queue, host[:5])  # the comprehension counts as its function
    assert np.array_equal(back, host)
    by_site = prof.bytes_by_site()
    assert by_site["h2d"] == {"piv/madeup.py:upload < piv/madeup.py:both": host.nbytes,
                              "": 40, "piv/madeup.py:listed": 20}
    assert by_site["d2h"] == {"piv/madeup.py:fetch < piv/madeup.py:both": host.nbytes}
    lines = site_lines(by_site)
    assert lines[0] == f"to the device: {(host.nbytes + 40) / 1e6:.2f} MB"
    assert "(outside plenocl)" in lines[2]
    assert copy_site() == ""  # this test is not in the package
    with OpenCLProfile() as plain:
        ns["both"](queue, host)
    assert plain.bytes_by_site()["h2d"] == {"": host.nbytes}


def test_a_copy_site_is_found_when_plenocl_is_imported_through_a_link(tmp_path):
    """The package imported through a linked folder (its modules' frames name the linked
    path, as the function compiled here does) is still the package: its functions are
    named, not taken for code outside it."""
    from plenocl.bench import clprofile

    link = tmp_path / "linked"
    link.symlink_to(clprofile.PACKAGE.resolve().parent, target_is_directory=True)
    code = ("from plenocl.bench import clprofile\n"
            "ns = {'copy_site': clprofile.copy_site}\n"
            "exec(compile('def f():\\n    return copy_site()\\n', "
            f"{str(link / 'plenocl' / 'piv' / 'madeup.py')!r}, 'exec'), ns)\n"
            "print(clprofile.PACKAGE, ns['f']())")
    env = {**os.environ, "PYTHONPATH": str(link)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=120, check=True, cwd=tmp_path)
    package, site = out.stdout.split()
    assert package.startswith(str(link)) and site == "piv/madeup.py:f"
