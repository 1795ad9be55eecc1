"""The image fit's sums on the device (kernels/imagefit.cl, plenocl/piv/fitsums.py)
against their NumPy twins (plenocl/reference/imagefit.py) on awkward patches, and the
fit with them against the fit summed on the host."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyopencl as cl
import pytest
import tolerances as tol
from helpers import traced_fit_scene

from plenocl.bench.accuracy_section import paper_optics
from plenocl.optics.raybundle import Patches, RayBundle
from plenocl.piv.devicebundle import SLOT, DeviceRayBundle
from plenocl.piv.fitsums import GPU_SCRATCH_BYTES, HOST_CHUNK, DeviceFitSums, fit_chunk
from plenocl.piv.imagefit import ImageFit, ImageFitSettings
from plenocl.reference import imagefit as ref

CAM, GRID = paper_optics((32, 24))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm
SENSOR = (53, 71)  # (rows, cols): not multiples of any work-group or column block


def awkward_patches(count: int, rng: np.random.Generator) -> Patches:
    """``count`` patches on a ``SENSOR``: random ones, one cut by the right and bottom
    edges, a 1 x 1 one, one wider than a GPU group, and one wholly off the sensor (as
    :meth:`RayBundle.patches` clips it: one column at ``col0 = cols``)."""
    rows, cols = SENSOR
    col0, row0 = rng.integers(0, cols - 2, count), rng.integers(0, rows - 2, count)
    width = np.minimum(rng.integers(1, 40, count), cols - col0)
    height = np.minimum(rng.integers(1, 30, count), rows - row0)
    special = [(cols - 9, rows - 4, 9, 4), (5, 7, 1, 1), (0, 2, cols, 3), (cols, 10, 1, 6)]
    for k, patch in enumerate(special[:count]):
        col0[k], row0[k], width[k], height[k] = patch
    offset = np.concatenate([[0], np.cumsum(width * height)])
    return Patches(offset, col0, row0, width, height)


def sparse_rows(patches: Patches, rng: np.random.Generator, count: int = 5) -> np.ndarray:
    """Rows ``(count, total)`` float32 like rendered ones: light on a third of the
    elements (positive value and d/dI), zero elsewhere."""
    total = int(patches.offset[-1])
    lit = rng.random(total) < 0.35
    rows = rng.normal(0.0, 1.0, (count, total)) * lit
    rows[0] = rng.uniform(0.0, 50.0, total) * lit
    if count == 5:
        rows[4] = rows[0] / 40.0
    return rows.astype(np.float32)


@pytest.fixture(params=[None, 64], ids=["device-group", "group64"])
def sums(queue, request) -> DeviceFitSums:
    """The sums with the device's work-group (1 on a CPU) and with a GPU's 64."""
    return DeviceFitSums(DeviceRayBundle(RayBundle.of(CAM, rays=64), queue), chunk=5,
                         group=request.param)


@pytest.mark.parametrize("count", [1, 4, 7, 37])
def test_model_matches_reference(sums, count):
    rng = np.random.default_rng(count)
    patches = awkward_patches(count, rng)
    rows = sparse_rows(patches, rng, 1)
    got = sums.model(sums.upload(rows[0]), patches, SENSOR).get()
    want = ref.patch_model(rows[0].astype(np.float64), patches, SENSOR)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=tol.ROUNDING * 10, atol=tol.ROUNDING * 10 * 50)


@pytest.mark.parametrize("count", [1, 4, 7, 37])
def test_normal_sums_match_reference(sums, count):
    """Every sum, against float64: each within float32 rounding of the sum of the
    magnitudes of its terms (the lit count exactly)."""
    rng = np.random.default_rng(10 + count)
    patches = awkward_patches(count, rng)
    rows = sparse_rows(patches, rng)
    data = rng.uniform(-5.0, 60.0, SENSOR)
    model = rng.uniform(0.0, 50.0, SENSOR).astype(np.float32)
    jac = rng.normal(0.0, 1.0, (count, 3, 3))
    got = sums.reduce_normals(sums.upload(rows.ravel()), sums.upload(data),
                              sums.upload(model), patches, jac)
    want = ref.normal_sums(rows.astype(np.float64), data.astype(np.float32).astype(np.float64),
                           model.astype(np.float64), patches, jac.astype(np.float32))
    scale = ref.normal_sums(np.abs(rows.astype(np.float64)), np.abs(data) + np.abs(model),
                            np.zeros(SENSOR), patches, np.abs(jac))
    assert np.isfinite(got).all()
    np.testing.assert_array_equal(got[:, 14], want[:, 14])
    assert np.all(np.abs(got - want) <= 1e-5 * scale + 1e-30), np.abs(got - want) / scale


@pytest.mark.parametrize("count", [1, 7, 37])
def test_unit_sums_match_reference(sums, count):
    rng = np.random.default_rng(20 + count)
    patches = awkward_patches(count, rng)
    unit = sparse_rows(patches, rng, 1)[0] / 40.0
    data = rng.uniform(-5.0, 60.0, SENSOR).astype(np.float32)
    got = sums.reduce_units(sums.upload(unit), sums.upload(data), patches)
    want = ref.unit_sums(unit.astype(np.float64), data.astype(np.float64), patches)
    scale = ref.unit_sums(unit.astype(np.float64), np.abs(data.astype(np.float64)), patches)
    assert np.all(np.abs(got - want) <= 1e-5 * scale + 1e-30)


@pytest.mark.parametrize("count", [1, 7, 37])
def test_sums_read_an_image_scaled_to_its_brightest_pixel(sums, count):
    """``data_scale``: the sums of a reconstruction's image (divided by its brightest
    pixel, :func:`plenocl.optics.rawimage.divided_to_float32`) read times that pixel are
    the references' on ``values * scale``, within float32 rounding of the magnitudes."""
    from plenocl.optics.rawimage import divided_to_float32

    rng = np.random.default_rng(30 + count)
    patches = awkward_patches(count, rng)
    rows = sparse_rows(patches, rng)
    image = rng.uniform(0.0, 6e4, SENSOR)
    scale = float(image.max())
    values = divided_to_float32(image, scale)
    data = values.astype(np.float64) * scale  # the image the sums stand for
    model = rng.uniform(0.0, 5e4, SENSOR).astype(np.float32)
    jac = rng.normal(0.0, 1.0, (count, 3, 3))
    got = sums.reduce_normals(sums.upload(rows.ravel()), sums.upload(values),
                              sums.upload(model), patches, jac, scale)
    want = ref.normal_sums(rows.astype(np.float64), data, model.astype(np.float64), patches,
                           jac.astype(np.float32))
    size = ref.normal_sums(np.abs(rows.astype(np.float64)), data + model, np.zeros(SENSOR),
                           patches, np.abs(jac))
    np.testing.assert_array_equal(got[:, 14], want[:, 14])
    assert np.all(np.abs(got - want) <= 1e-5 * size + 1e-30), np.abs(got - want) / size
    unit = rows[0] / 40.0
    got = sums.reduce_units(sums.upload(unit), sums.upload(values), patches, scale)
    want = ref.unit_sums(unit.astype(np.float64), data, patches)
    assert np.all(np.abs(got - want) <= 1e-5 * want + 1e-30)


def test_fit_with_device_sums_matches_host_sums(queue):
    """The same device-rendered fit, summed on the device and on the host: positions
    within float32 tolerance, intensities close; no particles gives no positions."""
    start, img = traced_fit_scene(CAM, VOXEL, 11, 2)
    fits = [ImageFit(CAM, GRID, [img], ImageFitSettings(chunk=4), queue=queue,
                     host_sums=host) for host in (True, False)]
    assert fits[1].sums is not None and fits[0].sums is None
    host, device = (f.fit(0, start) for f in fits)
    assert np.abs(device.positions - host.positions).max(axis=0) / VOXEL == \
        pytest.approx(np.zeros(3), abs=tol.IMAGEFIT_POSITION_VOXELS)
    assert device.intensities == pytest.approx(host.intensities, rel=1e-3)
    assert device.sigma == pytest.approx(host.sigma, rel=1e-3)
    assert fits[1].refine(0, np.zeros((0, 3))).shape == (0, 3)


def test_group_must_be_a_power_of_two(queue):
    with pytest.raises(ValueError, match="power of two"):
        DeviceFitSums(DeviceRayBundle(RayBundle.of(CAM, rays=64), queue), 8, group=48)


def test_kept_buffers_give_fresh_results(queue):
    """The rows, model and slot buffers kept from one computation to the next (grown,
    then used in part): the same sums as a fresh object's, bit for bit."""
    bundle = RayBundle.of(CAM, rays=37)
    rng = np.random.default_rng(4)
    pts = CAM.image_points(np.column_stack([rng.uniform(-2.5, 2.5, 9),
                                            rng.uniform(-2, 2, 9), rng.uniform(-9, 9, 9)]))
    data = rng.uniform(0.0, 50.0, CAM.pixels[::-1])
    jac = np.tile(np.eye(3), (9, 1, 1))
    kept = DeviceFitSums(DeviceRayBundle(bundle, queue), chunk=4)
    for n in (3, 9, 2):  # small, larger (the buffers grow), small again (in part)
        part = pts[:n]
        patches = bundle.patches(part)
        fresh = DeviceFitSums(DeviceRayBundle(bundle, queue), chunk=4)
        for sums in (kept, fresh):
            image = sums.upload(data)
            got = (sums.normal_sums(image, part, np.full(n, 300.0), patches, jac[:n]),
                   sums.unit_sums(image, part, patches))
            if sums is kept:
                want = got
        for a, b in zip(want, got, strict=True):
            np.testing.assert_array_equal(a, b)


def test_rows_growing_a_little_are_kept_in_one_buffer(queue, monkeypatch):
    """A fit's patches grow a little from step to step as its particles move: the rows
    buffer is made once with headroom (``KEPT_HEADROOM``), not again at each step (a
    fresh buffer's first touch costs page faults on a CPU device)."""
    from plenocl.opencl.program import KernelSet
    from plenocl.piv.fitsums import KEPT_HEADROOM

    made = []
    array = KernelSet.array

    def counted(self, size, *args, **kwargs):
        made.append(int(size))
        return array(self, size, *args, **kwargs)

    bundle = RayBundle.of(CAM, rays=37)
    rng = np.random.default_rng(5)
    pts = CAM.image_points(np.column_stack([rng.uniform(-2.5, 2.5, 10),
                                            rng.uniform(-2, 2, 10), rng.uniform(-9, 9, 10)]))
    data = rng.uniform(0.0, 50.0, CAM.pixels[::-1])
    sums = DeviceFitSums(DeviceRayBundle(bundle, queue), chunk=4)
    image = sums.upload(data)
    monkeypatch.setattr(KernelSet, "array", counted)
    totals = []
    for n in (9, 10):  # the second step's patches a few per cent more elements
        patches = bundle.patches(pts[:n])
        totals.append(5 * int(patches.offset[-1]))
        sums.normal_sums(image, pts[:n], np.full(n, 300.0), patches,
                         np.tile(np.eye(3), (n, 1, 1)))
    assert totals[0] < totals[1] <= KEPT_HEADROOM * totals[0]
    rows = [size for size in made if size >= totals[0]]
    assert rows == [int(KEPT_HEADROOM * totals[0])], (made, totals)


def test_a_kept_buffers_headroom_stays_within_the_largest_buffer():
    """The headroom is cut at the device's largest buffer, never below the size asked
    (which the driver may then refuse by name) and never empty."""
    from plenocl.piv.fitsums import kept_size

    assert kept_size(1000, 10**9, 1.25) == 1250
    assert kept_size(1000, 1100, 1.25) == 1100
    assert kept_size(1200, 1100, 1.25) == 1200
    assert kept_size(0, 10, 1.25) == 1 and kept_size(7, 10**9, 1.0) == 7


def test_the_chunk_changes_no_sum(queue):
    """Particles rendered 2 at a time and all at once (the default on a GPU): the same
    normal and unit sums, bit for bit (each particle's rows are written alone)."""
    bundle = RayBundle.of(CAM, rays=37)
    rng = np.random.default_rng(8)
    pts = CAM.image_points(np.column_stack([rng.uniform(-2.5, 2.5, 7),
                                            rng.uniform(-2, 2, 7), rng.uniform(-9, 9, 7)]))
    patches = bundle.patches(pts)
    data = rng.uniform(0.0, 50.0, CAM.pixels[::-1])
    jac = np.tile(np.eye(3), (7, 1, 1))
    got = []
    for chunk in (2, 7):
        sums = DeviceFitSums(DeviceRayBundle(bundle, queue), chunk=chunk)
        image = sums.upload(data)
        got.append((sums.normal_sums(image, pts, np.full(7, 250.0),
                                     patches, jac), sums.unit_sums(image, pts, patches)))
    for a, b in zip(*got, strict=True):
        np.testing.assert_array_equal(a, b)


def test_default_chunk_is_the_cpus_or_a_gpus_scratch(queue):
    """``None``: 128 on a CPU device; on a GPU every particle 256 MB of ray slots hold
    (200 rays: 2,892 particles, the paper pair's 2,789 in one launch), within the
    device's largest buffer; a chunk given is kept."""
    renderer = DeviceRayBundle(RayBundle.of(CAM, rays=200), queue)
    assert fit_chunk(renderer, 9) == 9
    if queue.device.type & cl.device_type.CPU:
        assert fit_chunk(renderer) == HOST_CHUNK
    def gpu(max_alloc: int) -> SimpleNamespace:
        return SimpleNamespace(queue=SimpleNamespace(device=SimpleNamespace(
            type=cl.device_type.GPU, max_mem_alloc_size=max_alloc)), bundle=renderer.bundle)

    per_particle = 200 * 4 * (SLOT + 1) * 4
    chunk = fit_chunk(gpu(2**34))
    assert chunk * per_particle <= GPU_SCRATCH_BYTES < (chunk + 1) * per_particle
    assert chunk == 2892 >= 2789
    small = fit_chunk(gpu(2**28 // 4))  # a small GPU's largest buffer bounds it
    assert small * per_particle <= 2**28 // 4 < (small + 1) * per_particle
    assert fit_chunk(gpu(2**20)) == HOST_CHUNK  # never below the CPU's
    assert ImageFitSettings().chunk is None
    with pytest.raises(ValueError, match="chunk"):
        ImageFitSettings(chunk=0)
