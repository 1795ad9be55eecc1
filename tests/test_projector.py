"""The matrix-free projector against the NumPy weighting function (docs/design.md §5)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cl_array
import pytest
import tolerances as tol
from helpers import ROTATED, assert_adjoint, assert_close_to_peak, lens_camera

from plenocl import Camera, Grid
from plenocl.projection import Projector
from plenocl.projection.projector import cpu_vector_width
from plenocl.reference.simulate import trace_particles
from plenocl.reference.weights import ApertureGrid, lens_index_map, voxel_weights, weight_matrix

# Voxel centres at z = -4, -2, 0, 2, 4 mm; the outer columns reach the sensor edges.
GRID = Grid((5, 7, 9), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-5.0, 5.0))
VOXELS = [(2, 3, 4), (1, 3, 4), (3, 2, 5), (0, 5, 1), (4, 1, 7), (2, 0, 0), (4, 6, 8), (0, 6, 8)]
#: The exact weighting function on every path: a grid across the lens rows on the general
#: kernels (projected through the lens-row frame by default: test_resample.py).
EXACT = {"general": "exact"}
#: The same projection computed another way (absolute floor: inputs of order 1).
RECOMPUTED = dict(rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)


def _perturbed(cam: Camera, seed: int = 3, missing=(2, 3)) -> Camera:
    """Calibrated centres off the ideal grid by up to ±0.3 px, one lens missing."""
    rng = np.random.default_rng(seed)
    centres = cam.microlens_centers + rng.uniform(-0.3, 0.3, cam.microlens_centers.shape)
    centres[missing] = np.nan
    return cam.with_centers(centres)


@pytest.fixture(scope="module")
def cameras(small_camera):
    """Ideal, perturbed (general and snapped separable paths) and rotated cameras."""
    rotated = lens_camera(**ROTATED)
    pert = _perturbed(small_camera)
    return {"ideal": (small_camera, {}), "perturbed": (pert, {}),
            "perturbed-separable": (pert, {"shear_tol": 0.05}), "rotated": (rotated, {})}


@pytest.fixture(scope="module")
def projectors(cameras, queue):
    """The exact weighting function: a grid across the lens rows on the general kernels
    (projected through the lens-row frame by default: test_resample.py)."""
    return {name: Projector(cam, GRID, queue, **EXACT, **kw)
            for name, (cam, kw) in cameras.items()}


def _dense(idx, w, n):
    out = np.zeros(n)
    out[idx] = w
    return out


def test_paths_selected(projectors):
    assert projectors["ideal"].path == "separable"
    assert projectors["perturbed"].path == "general"
    assert projectors["perturbed-separable"].path == "separable"
    assert projectors["rotated"].path == "general"


@pytest.mark.parametrize("name", ["ideal", "perturbed", "perturbed-separable", "rotated"])
def test_weights_and_forward_match_reference(name, cameras, projectors):
    cam, kw = cameras[name]
    proj = projectors[name]
    n = cam.pixels[0] * cam.pixels[1]
    for vox in VOXELS:
        ref = _dense(*voxel_weights(cam, GRID, *vox, **kw), n)
        kern = _dense(*proj.voxel_weights(*vox), n)
        onehot = np.zeros(GRID.shape, np.float32)
        onehot[vox] = 1.0
        fwd = proj.forward(onehot).ravel()
        for got in (kern, fwd):
            assert_close_to_peak(got, ref, tol.WEIGHTS, (name, vox))
            np.testing.assert_allclose(got.sum(), ref.sum(), rtol=tol.FOOTPRINT_TOTAL)
        assert np.array_equal(np.flatnonzero(kern > 1e-6 * ref.max()),
                              np.flatnonzero(ref > 1e-6 * ref.max()))


def test_voxel_weights_format(projectors):
    idx, w = projectors["ideal"].voxel_weights(2, 3, 4)
    assert idx.dtype == np.int64 and w.dtype == np.float32
    assert np.all(np.diff(idx) > 0) and np.all(w > 0)
    assert 500 < len(idx) < 3000
    with pytest.raises(IndexError, match="voxel indices"):
        projectors["ideal"].voxel_weights(5, 0, 0)


@pytest.mark.parametrize("name", ["ideal", "perturbed", "rotated"])
def test_adjoint(name, projectors):
    assert_adjoint(projectors[name])


def test_back_is_transpose_of_dense_matrix(small_camera, queue):
    grid = Grid((3, 2, 3), x=(-0.3, 0.3), y=(-0.2, 0.2), z=(-3.0, 3.0))
    a = weight_matrix(small_camera, grid)
    proj = Projector(small_camera, grid, queue)
    img = np.random.default_rng(1).random(proj.image_shape).astype(np.float32)
    np.testing.assert_allclose(proj.back(img).ravel(), a.T @ img.ravel(), rtol=tol.BACK_VS_MATRIX,
                               atol=tol.BACK_VS_MATRIX_FLOOR * np.abs(a.T @ img.ravel()).max())


@pytest.mark.parametrize("name", ["ideal", "perturbed"])
def test_weight_sums(name, cameras, projectors):
    """1 when all light reaches the sensor, < 1 near the edges or a missing lens, never > 1."""
    cam, kw = cameras[name]
    proj = projectors[name]
    vox = np.array(list(np.ndindex(*GRID.shape)))
    idx, w = proj.footprint_entries(vox)
    sums = np.where(idx >= 0, w, 0).astype(np.float64).sum(axis=1)
    ref = np.array([voxel_weights(cam, GRID, *v, **kw)[1].sum() for v in vox])
    np.testing.assert_allclose(sums, ref, rtol=tol.CONSERVATION)
    assert sums.max() <= 1 + tol.CONSERVATION
    whole = ref > 1 - 1e-9  # all light on the sensor (checked in double precision)
    assert whole.sum() >= 10 and (ref < 0.9).any()  # edge voxels lose light
    np.testing.assert_allclose(sums[whole], 1.0, rtol=tol.CONSERVATION)
    if name == "perturbed":  # voxel (2, 5, 6) is imaged in focus onto the missing lens
        assert sums[np.ravel_multi_index((2, 5, 6), GRID.shape)] < 0.5


@pytest.mark.parametrize("z", [-3.0, 0.0, 2.0])
def test_weights_correlate_with_ray_tracing(small_camera, queue, z):
    """Paper Fig. 8: a voxel's weights against particles spread through the voxel."""
    vox = small_camera.ml_pitch_mm / small_camera.magnification
    grid = Grid((1, 1, 1), x=(0.03, 0.03 + vox), y=(-0.04, -0.04 + vox),
                z=(z - vox / 2, z + vox / 2))
    idx, w = Projector(small_camera, grid, queue).voxel_weights(0, 0, 0)
    rng = np.random.default_rng(5)
    n = 2500
    pos = np.column_stack([rng.uniform(*grid.x, n), rng.uniform(*grid.y, n),
                           rng.uniform(*grid.z, n)])
    sim = trace_particles(small_camera, pos, 1.0, rays_per_particle=400, seed=2).ravel()
    corr = np.corrcoef(_dense(idx, w, sim.size), sim)[0, 1]
    assert corr >= 0.99, corr


def test_slab_split_matches_single_buffer(small_camera, queue):
    grid = Grid((16, 40, 60), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-4.0, 4.0))
    pert = _perturbed(small_camera)
    rng = np.random.default_rng(2)
    vol = rng.random(grid.shape).astype(np.float32)
    img = rng.random((170, 204)).astype(np.float32)
    for cam, kw in ((small_camera, {}), (pert, {"shear_tol": 0.05}), (pert, {})):
        whole = Projector(cam, grid, queue, **EXACT, **kw)
        split = Projector(cam, grid, queue, max_alloc_bytes=150_000, **EXACT, **kw)
        assert len(whole.plan.slabs) == 1 and len(split.plan.slabs) > 1
        assert len(split.plan.columns) > 1 and split.plan.zchunk < grid.shape[0]
        np.testing.assert_allclose(split.forward(vol), whole.forward(vol), **RECOMPUTED)
        np.testing.assert_allclose(split.back(img), whole.back(img), **RECOMPUTED)


def test_memory_errors(small_camera, queue):
    with pytest.raises(MemoryError, match="image needs"):
        Projector(small_camera, GRID, queue, max_alloc_bytes=100_000)
    wide = Grid((2, 300, 300), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.0, 1.0))
    with pytest.raises(MemoryError, match="depth slice needs 360000 bytes"):
        Projector(small_camera, wide, queue, max_alloc_bytes=200_000)
    huge = Grid((100, 20_000, 20_000), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.0, 1.0))
    with pytest.raises(MemoryError, match="needs"):  # more than any device holds
        Projector(small_camera, huge, queue)


def test_variants_agree(small_camera, queue):
    """The GPU-style layout (scalar, one element per work-item) and the direct kernels."""
    pert = _perturbed(small_camera)
    rng = np.random.default_rng(4)
    vol = rng.random(GRID.shape).astype(np.float32)
    img = rng.random((170, 204)).astype(np.float32)
    for kw in ({"shear_tol": 0.05}, {}):
        ref = Projector(pert, GRID, queue, **EXACT, **kw)
        for other in (Projector(pert, GRID, queue, vector_width=1, segment=1, **EXACT, **kw),
                      Projector(pert, GRID, queue, method="direct", **EXACT, **kw)):
            np.testing.assert_allclose(other.forward(vol), ref.forward(vol), **RECOMPUTED)
            np.testing.assert_allclose(other.back(img), ref.back(img), **RECOMPUTED)


@pytest.mark.parametrize("name", ["ideal", "rotated"])
def test_outputs_finite_and_non_negative(name, projectors, queue):
    proj = projectors[name]
    rng = np.random.default_rng(9)
    vol = proj.volume_to_device(rng.random(GRID.shape) ** 4)
    out = cl_array.empty(queue, proj.image_shape, np.float32).fill(np.nan)
    img = proj.forward_device(vol, out).get()
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() > 0
    back_out = [s.fill(np.nan) for s in proj.empty_volume()]
    back = proj.volume_to_host(proj.back_device(out, back_out))
    assert np.isfinite(back).all() and back.min() >= 0 and back.max() > 0
    np.testing.assert_allclose(back, proj.back(img), rtol=tol.ROUNDING)


def test_bad_inputs(small_camera, queue, projectors):
    proj = projectors["ideal"]
    with pytest.raises(ValueError, match=r"expected \(5, 7, 9\)"):
        proj.forward(np.zeros((5, 9, 7)))
    with pytest.raises(ValueError, match=r"expected \(170, 204\)"):
        proj.back(np.zeros((204, 170)))
    bad = np.zeros(GRID.shape)
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"NaN or Inf.*\(1, 2, 3\)"):
        proj.forward(bad)
    with pytest.raises(ValueError, match="NaN or Inf"):
        proj.back(np.full((170, 204), np.inf))
    with pytest.raises(TypeError, match="real numbers"):
        proj.forward(np.zeros(GRID.shape, complex))
    with pytest.raises(ValueError, match="float32 device array"):
        proj.forward_device(cl_array.zeros(queue, (5, 7, 8), np.float32))
    with pytest.raises(ValueError, match="method"):
        Projector(small_camera, GRID, queue, method="sparse")
    limit = small_camera.focal_length_mm - small_camera.object_distance_mm  # -50 mm
    near = Grid((2, 2, 2), x=(-0.5, 0.5), y=(-0.5, 0.5), z=(limit - 1, 0.0))
    with pytest.raises(ValueError, match="no real image"):
        Projector(small_camera, near, queue)
    away = Grid((2, 2, 2), x=(30.0, 40.0), y=(-0.5, 0.5), z=(-1.0, 1.0))
    with pytest.raises(ValueError, match="outside the camera's field of view"):
        Projector(small_camera, away, queue)


def test_reference_building_blocks(small_camera):
    ap = ApertureGrid.for_camera(small_camera, 1.25)
    i, j = ap.samples()
    u, v = (i - ap.center) * ap.step, (j - ap.center) * ap.step
    assert np.all(u**2 + v**2 <= ap.radius**2)
    assert len(i) > 0.9 * np.pi * (ap.radius / ap.step) ** 2
    lo, hi = ap.column_ranges()
    assert np.array_equal(np.repeat(np.arange(ap.n), hi - lo + 1), i)
    m = lens_index_map(small_camera)
    assert m.axis_aligned
    kx, ky = m(*small_camera.microlens_positions_mm()[4, 7])
    np.testing.assert_allclose([kx, ky], [7, 4], atol=1e-9)


def test_sensitivity_is_computed_once_and_kept(small_camera, queue):
    from plenocl.reconstruction import reconstruct
    proj = Projector(small_camera, GRID, queue)
    sens = proj.sensitivity()
    assert proj.sensitivity() is sens
    ones = np.ones(proj.image_shape, np.float32)
    host = proj.volume_to_host(sens)
    np.testing.assert_array_equal(host, proj.back(ones))
    # Σ sensitivity = 1ᵀ A 1 = Σ of the projection of ones (the uniform start's scale)
    total = proj.forward(np.ones(GRID.shape, np.float32)).astype(np.float64).sum()
    assert host.astype(np.float64).sum() == pytest.approx(total, rel=tol.CONSERVATION)
    img = proj.forward(np.random.default_rng(0).random(GRID.shape).astype(np.float32))
    kw = dict(iterations=3, supersample=1, background=None)  # a projection: as it is
    first = reconstruct(img, proj, **kw)
    assert first.any()
    np.testing.assert_array_equal(reconstruct(img, proj, **kw), first)
    np.testing.assert_array_equal(proj.volume_to_host(sens), host)  # solvers only read it


def test_cropped_projector_keeps_the_cropped_sensitivity(small_camera, queue):
    """A sub-projector crops its parent's sensitivity instead of back-projecting again;
    it matches the sub-grid's own back projection of ones to float32 rounding."""
    proj = Projector(small_camera, GRID, queue)
    box = (slice(1, 4), slice(2, 6), slice(3, 8))
    fresh = proj.cropped(box).sensitivity()  # parent's not yet computed: back-projected
    full = proj.volume_to_host(proj.sensitivity())
    sub = proj.cropped(box)
    kept = sub.volume_to_host(sub.sensitivity())
    np.testing.assert_array_equal(kept, full[box])
    np.testing.assert_allclose(kept, sub.volume_to_host(fresh), rtol=tol.RECOMPUTED,
                               atol=tol.RECOMPUTED_FLOOR * full.max())


@pytest.mark.parametrize("name", ["ideal", "perturbed-separable"])
def test_atomic_scatter_back_twin_matches_the_gather(name, cameras, projectors):
    """``back="atomic"`` (``back_y_scatter``, timed against ``back_y`` in
    benchmarks/projector.py) computes the same back projection: float atomics change only
    the summation order."""
    proj = projectors[name]
    cam, kw = cameras[name]
    atomic = Projector(cam, proj.grid, proj.queue, back="atomic", **EXACT, **kw)
    assert atomic.path == "separable"
    image = np.random.default_rng(5).random(proj.image_shape, dtype=np.float32)
    ref = proj.back(image)
    assert_close_to_peak(atomic.back(image), ref, tol.WEIGHTS, name)


@pytest.mark.parametrize("name", ["perturbed", "rotated"])
def test_gathering_general_forward_equals_the_scatter_bit_for_bit(name, cameras, queue):
    """fwd_gen_gather (one work-item per light-field element, for GPUs) sums the same
    products in the same order as fwd_gen (one per aperture sample), on PoCL too."""
    cam, kw = cameras[name]
    rng = np.random.default_rng(11)
    vol = rng.standard_normal(GRID.shape).astype(np.float32)
    vol[rng.random(GRID.shape) < 0.5] = 0.0  # sparse, as reconstructions are
    got = {g: Projector(cam, GRID, queue, gather_forward=g, scratch_bytes=2**14, **EXACT, **kw)
           for g in (False, True)}
    assert got[True].path == "general" and len(got[True].plan.columns) > 1
    np.testing.assert_array_equal(got[True].forward(vol), got[False].forward(vol))


@pytest.mark.parametrize("name", ["ideal", "perturbed-separable"])
def test_separable_element_kernels_equal_the_row_kernels_bit_for_bit(name, cameras, queue):
    """fwd_x and back_x with one work-item per output element (GPUs) sum the same products
    in the same order as the row kernels (CPUs), over several column chunks."""
    cam, kw = cameras[name]
    rng = np.random.default_rng(12)
    vol = rng.random(GRID.shape, dtype=np.float32)
    vol[rng.random(GRID.shape) < 0.5] = 0.0
    image = rng.random(cam.pixels[::-1], dtype=np.float32)
    got = {g: Projector(cam, GRID, queue, gather_forward=g, scratch_bytes=2**14, **EXACT, **kw)
           for g in (False, True)}
    assert got[True].path == "separable" and len(got[True].plan.columns) > 1
    np.testing.assert_array_equal(got[True].forward(vol), got[False].forward(vol))
    np.testing.assert_array_equal(got[True].back(image), got[False].back(image))


def test_sparse_rows_longer_than_one_list_project_as_the_element_kernels(small_camera,
                                                                         queue):
    """The row kernels list a sparse row's non-zero voxels ``PL_XLIST`` (128) at a time:
    on rows of 600 voxels with 200-290 of them non-zero (three lists, under half the row),
    ``fwd_x_row`` equals the element kernel ``fwd_x`` (to float32 rounding: on rows this
    long their sums of some 70 voxels per lens round differently, as before the lists),
    and ``back_x_row`` on the volume as its support gives the full back projection there
    bit for bit, 0 elsewhere, also when the columns come in several chunks that
    accumulate."""
    grid = Grid((3, 2, 600), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-4.0, 4.0))
    rows, gather = (Projector(small_camera, grid, queue, scratch_bytes=2**14,
                              gather_forward=g) for g in (False, True))
    assert rows.path == "separable" and len(rows.plan.columns) > 1
    rng = np.random.default_rng(14)
    vol = np.where(rng.random(grid.shape) < rng.uniform(0.34, 0.48, (3, 2, 1)),
                   rng.random(grid.shape), 0).astype(np.float32)
    lit = np.count_nonzero(vol, axis=2)
    assert lit.min() > 2 * 128 - 56 and 2 * lit.max() < grid.shape[2]
    np.testing.assert_allclose(rows.forward(vol), gather.forward(vol), **RECOMPUTED)
    image = cl_array.to_device(queue, rng.random(small_camera.pixels[::-1], dtype=np.float32))
    full = rows.volume_to_host(rows.back_device(image))
    got = rows.volume_to_host(rows.back_device(image, support=rows.volume_to_device(vol)))
    on = vol != 0
    assert np.count_nonzero(full[on]) > 0.9 * on.sum()
    np.testing.assert_array_equal(got[on], full[on])
    assert not got[~on].any()


def test_row_kernels_at_vector_widths_8_and_16_give_the_same_bits(small_camera, queue):
    """A CPU's default vector width follows its native float vectors (16 with AVX-512,
    else 8: ``cpu_vector_width``); the row kernels' sums do not depend on it: the
    forward and the back projection (with a support) at 8 and at 16 agree bit for bit,
    over several column chunks."""
    grid = Grid((3, 5, 40), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-4.0, 4.0))
    projs = {vw: Projector(small_camera, grid, queue, scratch_bytes=2**14, vector_width=vw,
                           gather_forward=False) for vw in (8, 16)}
    assert all(len(p.plan.columns) > 1 for p in projs.values())
    rng = np.random.default_rng(15)
    vol = np.where(rng.random(grid.shape) < 0.3, rng.random(grid.shape), 0).astype(np.float32)
    image = cl_array.to_device(queue, rng.random(small_camera.pixels[::-1], dtype=np.float32))
    fwd = {vw: p.forward(vol) for vw, p in projs.items()}
    back = {vw: p.volume_to_host(p.back_device(image, support=p.volume_to_device(vol)))
            for vw, p in projs.items()}
    assert fwd[8].any() and back[8].any()
    np.testing.assert_array_equal(fwd[8], fwd[16])
    np.testing.assert_array_equal(back[8], back[16])
    native = queue.device.native_vector_width_float
    assert cpu_vector_width(queue.device) == (16 if native >= 16 else 8)


@pytest.mark.parametrize("gather", [False, True])
@pytest.mark.parametrize("name", ["ideal", "rotated"])
def test_back_projection_on_a_support_is_the_full_one_there(name, gather, cameras, queue):
    """``support=``: the back projection at the support's non-zero voxels is the full one
    bit for bit, also when the columns come in several chunks that accumulate; elsewhere
    it is the full one or 0. The separable path's kernels skip the zero voxels of sparse
    rows (0 there) and compute dense rows whole; the general path computes every voxel."""
    cam, kw = cameras[name]
    proj = Projector(cam, GRID, queue, gather_forward=gather, scratch_bytes=2**14, **EXACT, **kw)
    rng = np.random.default_rng(13)
    support = rng.random(GRID.shape)
    support[:, :3] = np.where(rng.random((5, 3, 9)) < 0.1, support[:, :3], 0)  # sparse rows
    support[:, 3:] = np.where(rng.random((5, 4, 9)) < 0.9, support[:, 3:], 0)  # dense rows
    image = cl_array.to_device(queue, rng.random(cam.pixels[::-1], dtype=np.float32))
    full = proj.volume_to_host(proj.back_device(image))
    out = proj.back_device(image, support=proj.volume_to_device(support.astype(np.float32)))
    got = proj.volume_to_host(out)
    on = support != 0
    np.testing.assert_array_equal(got[on], full[on])
    assert full[~on].all() and np.all((got == 0) | (got == full))
    sparse, dense = ~on[:, :3], ~on[:, 3:]
    if proj.path == "separable" and not gather:  # the row kernel: rows decide
        assert not got[:, :3][sparse].any()
        np.testing.assert_array_equal(got[:, 3:][dense], full[:, 3:][dense])
    elif proj.path == "separable":  # one work-item per voxel skips every zero one
        assert not got[~on].any()
    else:
        np.testing.assert_array_equal(got, full)
