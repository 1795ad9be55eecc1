"""Dark-microlens skipping (plenocl.projection.lenses): lit lenses cover the exact set, projections
restricted to them are exact where they must be, and reconstructions do not change."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
from helpers import ROTATED, lens_camera

from plenocl import Grid
from plenocl.projection import Projector
from plenocl.projection.lenses import lit_lenses
from plenocl.reconstruction import reconstruct
from plenocl.reference.weights import lit_lenses as exact_lit_lenses
from plenocl.simulate import simulate_image

GRID = Grid((5, 7, 9), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-5.0, 5.0))


@pytest.fixture(scope="module")
def cameras(small_camera):
    """Ideal (separable path), calibrated with a missing lens and rotated (general path)."""
    rng = np.random.default_rng(4)
    centres = small_camera.microlens_centers + rng.uniform(-0.3, 0.3,
                                                           small_camera.microlens_centers.shape)
    centres[4, 6] = np.nan
    rotated = lens_camera(**ROTATED)
    return {"ideal": small_camera, "missing": small_camera.with_centers(centres),
            "rotated": rotated}


@pytest.fixture(scope="module")
def projectors(cameras, queue):
    return {name: Projector(cam, GRID, queue) for name, cam in cameras.items()}


def _sparse_image(shape, spots: int, seed: int) -> np.ndarray:
    """Zero except a few 3 x 3 bright spots (and one corner pixel)."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for r, c in zip(rng.integers(1, shape[0] - 1, spots), rng.integers(1, shape[1] - 1, spots),
                    strict=True):
        img[r - 1:r + 2, c - 1:c + 2] = rng.uniform(0.5, 2.0)
    img[-1, 0] = 1.0
    return img


@pytest.mark.parametrize("reach", [0, 2, 7])
@pytest.mark.parametrize("shape", [(37, 53), (9, 64), (61, 5)])
def test_lit_lenses_are_the_patches_holding_a_pixel_above_the_threshold(shape, reach):
    """Each lens is lit exactly when the square patch ``reach`` pixels around its centre,
    clipped to the sensor, holds a pixel above the threshold: against a loop over the
    lenses, with centres on and beyond every edge and missing ones (far outside)."""
    rng = np.random.default_rng(shape[0] + reach)
    img = np.where(rng.random(shape) < 0.03, rng.uniform(0.2, 2.0, shape), 0.0)
    centres = np.column_stack([rng.integers(-reach - 3, shape[1] + reach + 3, 400),
                               rng.integers(-reach - 3, shape[0] + reach + 3, 400)])
    centres[::37] = -(2 ** 40)  # missing
    for threshold in (0.0, 1.0):
        got = lit_lenses(img, centres, reach, threshold)
        want = [(img[max(y - reach, 0):max(y + reach + 1, 0),
                     max(x - reach, 0):max(x + reach + 1, 0)] > threshold).any()
                for x, y in centres]
        np.testing.assert_array_equal(got, want)
        assert got.any() and not got.all()  # both kinds of lens in every case


@pytest.mark.parametrize("name", ["ideal", "missing", "rotated"])
def test_lit_lenses_cover_the_exact_set(name, cameras, projectors):
    cam, proj = cameras[name], projectors[name]
    for seed in range(3):
        img = _sparse_image(proj.image_shape, 4, seed)
        lit, exact = proj.lit_lenses(img), exact_lit_lenses(cam, img)
        assert exact.any()
        assert not (exact & ~lit).any(), f"lenses reaching a lit pixel left out: {exact & ~lit}"
        assert lit.sum() <= exact.sum() + 4 * 5, "the patch bound is far too loose"
    missing = ~np.isfinite(cam.microlens_centers).all(axis=-1).ravel()
    assert not (proj.lit_lenses(np.ones(proj.image_shape)) & missing).any()


@pytest.mark.parametrize("name", ["ideal", "missing", "rotated"])
def test_lit_lenses_on_the_device_are_the_hosts(name, projectors, queue):
    """The device's flags (``kernels/lenses.cl``, from the image the solver reads) are the
    host's, bit for bit: pixels at and next to thresholds float32 cannot hold, patches cut
    by the sensor's edges, missing lenses dark."""
    proj = projectors[name]
    rng = np.random.default_rng(7)
    for seed in range(3):
        img = _sparse_image(proj.image_shape, 6, seed)
        img[rng.random(img.shape) < 0.002] = np.float32(0.1)
        for threshold in (0.0, 0.1, float(np.float32(0.1)), np.float64(0.1), 0.3, 1.5):
            want = proj.lit_lenses(img, threshold)
            got = proj.lit_lenses(cla.to_device(queue, img), threshold)
            assert np.array_equal(got, want), threshold
    with pytest.raises(ValueError, match="float32 of shape"):
        proj.lit_lenses(cla.to_device(queue, np.zeros((3, 4), np.float32)))


@pytest.mark.parametrize("n", [1, 7, 8, 9, 1001])
def test_packed_flags_are_numpys_packbits(queue, n):
    """``pack_flags`` (what the device's lit flags come back as) holds bit ``i`` of byte
    ``j`` for flag ``8 j + i``, as ``numpy.packbits(..., bitorder="little")``, the last
    byte's spare bits zero, any non-zero flag set."""
    from plenocl.opencl.arrays import upload
    from plenocl.opencl.program import KernelSet

    k = KernelSet(queue, "lenses.cl", ["lit_patches", "pack_flags"])
    flags = (np.random.default_rng(n).integers(0, 3, n)).astype(np.uint8)
    packed = k.array(-(-n // 8), np.uint8)
    k.launch("pack_flags", packed.shape, upload(queue, flags), np.int32(n), packed)
    np.testing.assert_array_equal(packed.get(), np.packbits(flags > 0, bitorder="little"))


def test_lit_flags_come_back_eight_to_a_byte(projectors, queue):
    """The device's lit flags cross as one bit per lens, not a byte."""
    from plenocl.bench.clprofile import OpenCLProfile

    proj = projectors["missing"]
    img = cla.to_device(queue, _sparse_image(proj.image_shape, 6, 1))
    with OpenCLProfile() as prof:
        lit = proj.lit_lenses(img)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    assert back == -(-lit.size // 8) and lit.any()


def test_one_pixel_lights_few_lenses(projectors):
    proj = projectors["ideal"]
    cols, rows = proj.camera.ml_count
    for r, c in [(85, 102), (0, 0), (169, 203), (40, 17)]:
        img = np.zeros(proj.image_shape, np.float32)
        img[r, c] = 1.0
        assert 1 <= proj.lit_lenses(img).sum() <= 4, (r, c)
    assert proj.lit_lenses(np.zeros(proj.image_shape)).sum() == 0
    assert proj.lit_lenses(np.ones(proj.image_shape)).sum() == cols * rows


@pytest.mark.parametrize("name", ["ideal", "missing", "rotated"])
def test_forward_on_lit_lenses_is_exact_at_lit_pixels(name, projectors, queue):
    proj = projectors[name]
    rng = np.random.default_rng(1)
    vol = rng.random(GRID.shape).astype(np.float32)
    img = _sparse_image(proj.image_shape, 3, 7)
    lenses = proj.lens_set(proj.lit_lenses(img))
    assert lenses.fraction() < 0.5
    full = proj.forward(vol)
    active = np.array([True, False, True, True, False])
    part = proj.forward_device(proj.volume_to_device(vol * active[:, None, None]),
                               active=active, lenses=lenses).get()
    lit = img > 0
    # the same arithmetic at every lit pixel, bit for bit
    full_active = proj.forward(vol * active[:, None, None])
    assert np.array_equal(part[lit], full_active[lit])
    assert (full[lit] > 0).mean() > 0.5  # the comparison is not between zeros
    # nothing behind the unlisted lenses
    outside = np.ones(proj.image_shape, bool)
    rnd = proj.camera.microlens_centers.reshape(-1, 2)
    e = proj.lens_reach
    for k in np.flatnonzero(lenses.lit):
        c, r = np.round(rnd[k]).astype(int)
        outside[max(r - e, 0):r + e + 1, max(c - e, 0):c + e + 1] = False
    assert not part[outside].any()


@pytest.mark.parametrize("name", ["ideal", "missing", "rotated"])
def test_back_from_lit_lenses_is_exact(name, cameras, projectors, queue):
    img = _sparse_image(projectors[name].image_shape, 5, 3)
    # several aperture-column chunks too: the light field is zeroed per chunk
    for proj in (projectors[name], Projector(cameras[name], GRID, queue,
                                             scratch_bytes=64 * 1024)):
        lenses = proj.lens_set(proj.lit_lenses(img))
        full = proj.back(img)
        part = proj.volume_to_host(proj.back_device(cla.to_device(queue, img), lenses=lenses))
        assert full.max() > 0
        assert np.array_equal(part, full)


def test_empty_lens_set(projectors, queue):
    proj = projectors["ideal"]
    none = proj.lens_set(np.zeros(proj.camera.ml_count[::-1], bool))
    assert none.count == 0
    vol = proj.volume_to_device(np.ones(GRID.shape, np.float32))
    assert not proj.forward_device(vol, lenses=none).get().any()
    ones = cla.to_device(queue, np.ones(proj.image_shape, np.float32))
    assert not proj.volume_to_host(proj.back_device(ones, lenses=none)).any()


def test_lens_set_groups_colour_classes(projectors):
    proj = projectors["ideal"]
    cols, rows = proj.camera.ml_count
    lit = np.random.default_rng(0).random(cols * rows) < 0.3
    lenses = proj.lens_set(lit)
    ids, cs = lenses.ids.get()[:lenses.count], proj.colour_stride
    assert sorted(ids) == list(np.flatnonzero(lit))
    for c, (a, b) in enumerate(zip(lenses.offsets[:-1], lenses.offsets[1:], strict=True)):
        ky, kx = np.divmod(ids[a:b], cols)
        assert np.all((ky % cs) * cs + kx % cs == c)
    assert np.array_equal(lenses.rows.get(), lit.reshape(rows, cols).any(axis=1))
    with pytest.raises(ValueError, match="one flag per microlens"):
        proj.lens_set(lit[:-1])
    with pytest.raises(ValueError, match="expected"):
        proj.lit_lenses(np.zeros((3, 3)))


def test_a_lens_set_goes_up_once_per_queue(projectors, queue):
    """Two projectors of one camera on one queue asking for the same lit lenses share
    one upload; other lenses, or the same flags changed in the caller's array afterwards,
    make their own; a queue keeps the few asked for last."""
    from plenocl.projection.lenses import KEPT_SETS

    a = projectors["ideal"]
    b = Projector(a.camera, Grid((4, 10, 10), x=(-0.5, 0.5), y=(-0.5, 0.5), z=(-1, 1)),
                  queue)
    cols, rows = a.camera.ml_count
    lit = np.random.default_rng(1).random(cols * rows) < 0.4
    first = a.lens_set(lit)
    assert b.colour_stride == a.colour_stride
    assert b.lens_set(lit.copy()) is first
    lit[0] = not lit[0]  # the caller's array changed: the kept set is not
    other = a.lens_set(lit)
    assert other is not first and other.count == first.count + (1 if lit[0] else -1)
    assert first.lit[0] != lit[0]
    for k in range(KEPT_SETS - 1):  # newer sets; the first one asked for again each time
        a.lens_set(np.roll(lit, k + 1))
        assert a.lens_set(lit) is other
    a.lens_set(np.roll(lit, KEPT_SETS))
    assert a.lens_set(lit) is other  # kept: among the last asked for
    for k in range(KEPT_SETS):  # pushed out by newer sets
        a.lens_set(np.roll(lit, -k - 1))
    assert a.lens_set(lit) is not other
    np.testing.assert_array_equal(np.sort(a.lens_set(lit).ids.get()[:other.count]),
                                  np.flatnonzero(lit))


@pytest.mark.parametrize("method", ["mlem", "smart", "mart"])
def test_reconstruction_unchanged_by_skipping(method, small_camera, queue):
    grid = Grid((6, 12, 12), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.5, 1.5))
    proj = Projector(small_camera, grid, queue)
    pos = np.array([[0.1, 0.2, 0.3], [-0.3, -0.1, -0.8], [0.4, -0.3, 1.0]])
    img = simulate_image(small_camera, pos, 1e4, 4000, seed=2)
    kw = dict(method=method, iterations=6, threshold=0.5, return_info=True, supersample=1)
    on, info_on = reconstruct(img, proj, skip_dark=True, **kw)
    off, info_off = reconstruct(img, proj, skip_dark=False, **kw)
    assert info_off.lit_lens_fraction == 1.0
    assert 0 < info_on.lit_lens_fraction < 0.6
    assert on.max() > 0
    assert np.array_equal(on, off)
