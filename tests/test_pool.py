"""Device memory kept for reuse (:mod:`plenocl.opencl.pool`, docs/design.md §7.5): a
dropped array's memory goes to the next array of about its size on the same queue,
never to another queue's; what the pool holds is given back on request; a pair's
results do not depend on what a reused block held; and a batch's pairs do not grow the
memory held."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.tools  # noqa: F401  (cl.tools)
import pytest

import plenocl
from plenocl.opencl import pool
from plenocl.pipeline import process_pair
from plenocl.piv import PIVSettings
from plenocl.reconstruction import ReconstructionSettings

REC = ReconstructionSettings(iterations=3, coarse_iterations=2)
GRID = plenocl.Grid((16, 24, 24), x=(-1.2, 1.2), y=(-1.2, 1.2), z=(-1.5, 1.5))


def _fresh(queue: cl.CommandQueue) -> cl.CommandQueue:
    """A new queue on ``queue``'s device (its own pool)."""
    return plenocl.get_queue(queue.device)


def test_a_dropped_array_gives_its_memory_to_the_next_of_its_size(queue):
    q = _fresh(queue)
    a = pool.empty(q, (1000,))
    address = a.data.int_ptr
    del a
    b = pool.empty(q, (1001,))  # the same bin (sizes rounded up by at most 1/16)
    assert b.data.int_ptr == address
    c = pool.empty(q, (4000,))  # another bin: new memory
    assert c.data.int_ptr != address
    assert pool.pool_of(q).active_blocks == 2


def test_another_queue_never_takes_a_queues_held_memory(queue):
    q1, q2 = _fresh(queue), _fresh(queue)
    a = pool.empty(q1, (1000,))
    address = a.data.int_ptr
    del a
    assert pool.pool_of(q1) is not pool.pool_of(q2)
    other = pool.empty(q2, (1000,))
    del other  # into q2's pool: q1 still hands out its own block
    assert pool.pool_of(q2).held_blocks == 1
    assert pool.empty(q1, (1000,)).data.int_ptr == address


def test_held_memory_is_given_back_on_request_and_arrays_in_use_keep_theirs(queue):
    q = _fresh(queue)
    kept = pool.empty(q, (2000,))
    kept.set(np.arange(2000, dtype=np.float32))
    dropped = [pool.empty(q, (n,)) for n in (3000, 50_000)]
    nbytes = sum(pool.pool_of(q).alloc_size(pool.pool_of(q).bin_number(a.nbytes))
                 for a in dropped)
    del dropped
    assert pool.pool_of(q).held_blocks == 2
    assert pool.release_held(q) == nbytes
    assert pool.pool_of(q).held_blocks == 0 and pool.pool_of(q).active_blocks == 1
    np.testing.assert_array_equal(kept.get(), np.arange(2000, dtype=np.float32))
    assert pool.release_held(q) == 0
    assert pool.release_held(_fresh(queue)) == 0  # a queue without a pool yet


def test_a_queue_whose_pool_is_switched_off_makes_its_arrays_directly(queue):
    q = _fresh(queue)
    dropped = pool.empty(q, (1000,))
    del dropped
    old = pool.pool_of(q)
    assert old.held_blocks == 1
    pool.use_pool(q, False)
    assert old.held_blocks == 0  # given back when switched off
    assert pool.pool_of(q) is None and pool.release_held(q) == 0
    assert not isinstance(pool.empty(q, (1000,)).data, cl.tools.PooledBuffer)
    pool.use_pool(q)
    again = pool.empty(q, (1000,))
    assert isinstance(again.data, cl.tools.PooledBuffer)


def test_held_memory_settles_past_its_share_of_the_device(queue):
    """Arrays whose sizes vary leave a block per size class: after a pair, held memory
    beyond the share is given back; below it, kept for the next pair."""
    q = _fresh(queue)
    rng = np.random.default_rng(4)
    for _ in range(20):
        dropped = pool.empty(q, (int(1e5 * rng.uniform(0.7, 1.3)),))
        del dropped
    held = pool.pool_of(q).managed_bytes
    assert pool.pool_of(q).held_blocks > 1
    assert pool.settle(q) == 0 and pool.pool_of(q).managed_bytes == held  # a small share
    assert pool.settle(q, share=held / q.device.global_mem_size / 2) == held
    assert pool.pool_of(q).held_blocks == 0


def test_an_allocation_refused_for_memory_is_made_again_after_the_held_is_given_back(
        queue):
    q = _fresh(queue)
    dropped = pool.empty(q, (5000,))
    del dropped
    calls = []

    def make():
        calls.append(pool.pool_of(q).held_blocks)
        if len(calls) == 1:
            raise cl.MemoryError("clCreateBuffer", -4, "out of device memory")
        return "made"

    assert pool.made(q, make) == "made"
    assert calls == [1, 0]  # the second try after the held block went back
    with pytest.raises(cl.MemoryError):  # nothing held: refused as the driver said
        pool.made(q, lambda: (_ for _ in ()).throw(cl.MemoryError("clCreateBuffer")))


def test_empty_sizes_and_types(queue):
    q = _fresh(queue)
    for shape, dtype in (((3, 5, 7), np.float32), ((11,), np.int32), ((4, 9), np.float64),
                         ((0,), np.float32)):
        a = pool.empty(q, shape, dtype)
        assert a.shape == shape and a.dtype == dtype and a.queue is q
    assert pool.pool_of(q).active_blocks == 0  # every one of them dropped


def test_a_size_the_pool_would_round_past_the_largest_buffer_is_made_directly(queue):
    p = pool.pool_of(_fresh(queue))
    for n in (1, 1000, 5_589_000, 50_000_000, 2**30 + 1):  # rounded up by at most 1/16
        assert n <= p.alloc_size(p.bin_number(n)) <= n + n / 16
    assert pool.fits_pooled(p, 1000, 1023)  # 1000 bytes take a block of 1023
    assert not pool.fits_pooled(p, 1000, 1010)  # under the largest, rounded past it
    assert not pool.fits_pooled(p, 0, 1023)


@pytest.fixture(scope="module")
def scene(queue):
    """A small camera and two raw images of 60 particles, the second moved 0.2 mm along
    x."""
    cam = plenocl.Camera.synthetic_850()
    pos, inten = plenocl.random_particles(((-1.1, 1.1), (-1.1, 1.1), (-1.4, 1.4)),
                                          count=60, seed=3, intensity=3e4)
    raws = [plenocl.simulate_image(cam, pos + [dx, 0.0, 0.0], inten, 1000, seed=k,
                                   blur_px=0.5, queue=queue) + 50.0
            for k, dx in enumerate((0, 0.2))]
    return cam, raws


def _pair(cam, raws, q, fft: str = "fftw"):
    res = process_pair(*raws, plenocl.Projector(cam, GRID, q), reconstruction=REC,
                       piv=PIVSettings(fft=fft))
    return np.stack([res.piv.u, res.piv.v, res.piv.w]), res.vol_a


class _Stale:
    """A queue's pool whose every block is handed out with all its bytes 0xFF (NaN in
    floats and complex numbers, -1 or the largest value in integers), as a block an
    earlier array left: the arrays :func:`pool.empty` makes and those pyopencl derives
    from them (``empty_like``, ``copy``, arithmetic) alike."""

    def __init__(self, real, queue):
        self.real, self.queue = real, queue
        self.alloc_size, self.bin_number = real.alloc_size, real.bin_number

    def __call__(self, nbytes):
        block = self.real(nbytes)
        cl.enqueue_fill_buffer(self.queue, block, np.uint8(0xFF), 0, nbytes)
        return block


@pytest.mark.parametrize("fft", ["fftw", "device"])
def test_a_pair_does_not_depend_on_what_its_reused_memory_held(scene, queue, monkeypatch,
                                                                fft):
    """Every pooled block handed out full of 0xFF bytes (:class:`_Stale`): the same
    vectors and volume, bit for bit, as from a fresh queue; PIV's FFTs on the host and
    on the device."""
    cam, raws = scene
    want_field, want_vol = _pair(cam, raws, _fresh(queue), fft)
    assert np.isfinite(want_field).any() and want_vol.max() > 0
    real = pool.pool_of
    handed = []

    def stale(q):
        handed.append(q)
        found = real(q)
        return None if found is None else _Stale(found, q)

    monkeypatch.setattr(pool, "pool_of", stale)
    got_field, got_vol = _pair(cam, raws, _fresh(queue), fft)
    assert handed  # the pair's arrays came through it
    np.testing.assert_array_equal(got_field, want_field)
    np.testing.assert_array_equal(got_vol, want_vol)


def test_a_batch_of_pairs_does_not_grow_the_memory_held(scene, queue):
    """After the first pairs, the next ones take their memory from what those left: five
    pairs hold at most twice the first one's (a pool that kept none would hold five
    times it; the order of the frees, with two threads, may take a block more)."""
    cam, raws = scene
    q = _fresh(queue)
    proj = plenocl.Projector(cam, GRID, q)
    managed = []
    for _ in range(5):
        process_pair(*raws, proj, reconstruction=REC)
        q.finish()
        managed.append(pool.pool_of(q).managed_bytes)
    assert managed[0] > 0
    assert max(managed) <= 2 * managed[0]
