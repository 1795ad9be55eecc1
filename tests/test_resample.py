"""A grid across a rotated array's lens rows, projected through the lens-row frame: the
resampling kernels against their NumPy twin, the composed operator's exactness
(``A_frame S``, adjoint, light conserved), agreement with the exact weighting function,
and particles reconstructed on a sensor-axis grid as on the lens-row grid."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
import tolerances as tol
from helpers import ROTATED, assert_adjoint, lens_camera

from plenocl import Grid, Projector, simulate_image
from plenocl.metrics import recovery
from plenocl.projection.resample import frame_grid
from plenocl.reconstruction import reconstruct
from plenocl.reference.resample import resample_matrix, resample_volume

#: Taps from float32 positions (index ~50 known to ~4e-6): within 1e-5 of unit values.
RECOMPUTED = dict(rtol=tol.RECOMPUTED, atol=1e-5)
#: An awkward sensor-axis grid: odd sizes, unequal lateral voxels.
GRID = Grid((5, 9, 13), x=(-0.7, 0.7), y=(-0.55, 0.6), z=(-4.0, 4.0))


def _projector(queue, rotation: float = 2.0, grid: Grid = GRID, **kw) -> Projector:
    return Projector(lens_camera(ml_rotation_deg=rotation,
                                 ml_offset_mm=ROTATED["ml_offset_mm"]), grid, queue, **kw)


@pytest.mark.parametrize("rotation", [0.15, 2.0, -7.0, 30.0])
def test_frame_grid_holds_every_tap_of_the_grid(rotation):
    frame = frame_grid(GRID, rotation)
    assert frame.rotation_deg == rotation and frame.z == GRID.z
    assert frame.shape[0] == GRID.shape[0]
    np.testing.assert_allclose(frame.spacing, GRID.spacing, rtol=1e-12)
    # every user voxel centre, one voxel beyond in each direction, lies in the frame
    idx = np.stack(np.meshgrid(np.arange(-1, GRID.shape[2] + 1), np.arange(-1, GRID.shape[1] + 1),
                               [0], indexing="ij"), -1).reshape(-1, 3).astype(float)
    inside = frame.to_index(GRID.from_index(idx))
    _, fny, fnx = frame.shape
    assert (inside[:, 0] >= -0.5).all() and (inside[:, 0] <= fnx - 0.5).all()
    assert (inside[:, 1] >= -0.5).all() and (inside[:, 1] <= fny - 0.5).all()
    # and the user voxels each receive taps summing to about 1 (light conserved after
    # normalisation; the raw sums drift with the angle's aliasing)
    sums = np.asarray(resample_matrix(GRID, frame, normalised=False).sum(axis=0)).ravel()
    assert sums.min() > 0.5 and sums.max() < 1.5
    np.testing.assert_allclose(resample_matrix(GRID, frame).sum(axis=0), 1.0, rtol=1e-12)


@pytest.mark.parametrize("max_alloc", [None, 150_000])
def test_resampling_kernels_match_the_numpy_twin(queue, max_alloc):
    """One buffer, and depth slabs split differently on the two grids; inactive planes
    are left alone."""
    grid = Grid((16, 43, 57), x=(-0.7, 0.7), y=(-0.55, 0.6), z=(-4.0, 4.0))
    proj = _projector(queue, grid=grid, max_alloc_bytes=max_alloc)
    assert proj.path == "resampled"
    frame = proj.frame.grid
    if max_alloc:
        assert len(proj.plan.slabs) > 1 and proj.plan.slabs != proj.frame.plan.slabs
    rng = np.random.default_rng(1)
    vol = rng.random(grid.shape, np.float32)
    fvol = rng.random(frame.shape, np.float32)
    active = rng.random(grid.shape[0]) < 0.6
    got = proj.frame.empty_volume()
    for s in got:
        s.fill(0.0)
    proj.resampler.to_frame(proj.volume_to_device(vol), proj.plan.slabs, got,
                             proj.frame.plan.slabs, active)
    want = resample_volume(vol, grid, frame) * active[:, None, None]
    np.testing.assert_allclose(proj.frame.volume_to_host(got), want, **RECOMPUTED)
    back = proj.empty_volume()
    for s in back:
        s.fill(0.0)
    proj.resampler.from_frame(proj.frame.volume_to_device(fvol), proj.frame.plan.slabs, back,
                               proj.plan.slabs, active)
    s = resample_matrix(grid, frame)
    want = np.stack([(s.T @ p.ravel()).reshape(grid.shape[1:]) for p in fvol])
    np.testing.assert_allclose(proj.volume_to_host(back), want * active[:, None, None],
                               **RECOMPUTED)


@pytest.mark.parametrize("rotation", [0.15, 2.0, -7.0])
def test_resampled_projector_is_the_frame_projector_of_the_resampled_volume(queue, rotation):
    proj = _projector(queue, rotation)
    assert proj.path == "resampled" and proj.frame.path == "separable"
    frame = proj.frame.grid
    s = resample_matrix(GRID, frame)
    rng = np.random.default_rng(2)
    vol = rng.random(GRID.shape, np.float32)
    img = rng.random(proj.image_shape, np.float32)
    fwd = proj.forward(vol)
    np.testing.assert_allclose(fwd, proj.frame.forward(resample_volume(vol, GRID, frame)),
                               rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED * fwd.max())
    fb = proj.frame.back(img)
    want = np.stack([(s.T @ p.ravel()).reshape(GRID.shape[1:]) for p in fb])
    np.testing.assert_allclose(proj.back(img), want, rtol=tol.RECOMPUTED,
                               atol=tol.RECOMPUTED * want.max())
    assert_adjoint(proj)


def test_resampled_weights_conserve_light_and_agree_with_the_projection(queue):
    """Each voxel's weights (its frame voxels' weights mixed by its normalised column of
    S) sum to at most 1, equal Aᵀ 1 there, and are its one-hot forward projection."""
    proj = _projector(queue)
    raw = np.asarray(resample_matrix(GRID, proj.frame.grid, normalised=False).sum(axis=0))
    np.testing.assert_allclose(proj.resampler.norm.ravel(), raw.ravel(), rtol=1e-5)
    sens = proj.back(np.ones(proj.image_shape, np.float32))
    assert sens.max() <= 1 + tol.CONSERVATION and sens.min() >= 0
    n = proj.image_shape[0] * proj.image_shape[1]
    for vox in [(2, 4, 6), (0, 0, 0), (4, 8, 12), (1, 5, 0)]:
        idx, w = proj.voxel_weights(*vox)
        assert float(w.astype(np.float64).sum()) == pytest.approx(sens[vox], abs=1e-5)
        onehot = np.zeros(GRID.shape, np.float32)
        onehot[vox] = 1.0
        np.testing.assert_allclose(np.bincount(idx, w, minlength=n),
                                   proj.forward(onehot).ravel(), atol=1e-7)


def test_resampled_back_projection_on_a_support_is_the_full_one_there(queue):
    proj = _projector(queue)
    rng = np.random.default_rng(3)
    support = (rng.random(GRID.shape) < 0.1).astype(np.float32)
    img = rng.random(proj.image_shape, np.float32)
    full = proj.back(img)
    got = proj.volume_to_host(proj.back_device(cla.to_device(queue, img),
                                               support=proj.volume_to_device(support)))
    on = support > 0
    np.testing.assert_allclose(got[on], full[on], rtol=tol.RECOMPUTED,
                               atol=tol.RECOMPUTED * full.max())


def test_resampled_projection_follows_the_exact_weighting_function(queue):
    """On a volume smooth on the voxel scale (particles of a voxel or more) the resampled
    projection and the general kernels' exact one agree closely; the refined and cropped
    projectors resample too."""
    proj = _projector(queue, 2.0)
    exact = _projector(queue, 2.0, general="exact")
    assert exact.path == "general"
    z, y, x = np.meshgrid(*(np.arange(n) for n in GRID.shape), indexing="ij")
    vol = np.exp(-((x - 6.3) ** 2 + (y - 3.6) ** 2) / 4.0 - (z - 2.0) ** 2 / 2).astype(np.float32)
    a, b = proj.forward(vol), exact.forward(vol)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
    assert a.sum() == pytest.approx(b.sum(), rel=0.01)
    assert proj.refined(3).path == "resampled"
    assert proj.cropped((slice(1, 4), slice(2, 8), slice(3, 11))).path == "resampled"


@pytest.mark.parametrize("supersample", [1, 3])
def test_particles_on_a_sensor_axis_grid_reconstruct_as_on_the_lens_row_grid(queue,
                                                                             supersample):
    """Particles traced through a 2-degree array: the sensor-axis grid (resampled every
    iteration on voxels; reconstructed in the frame and resampled once on sub-voxels)
    finds as many, as well placed, as the lens-row grid of Grid.for_camera."""
    cam = lens_camera(ml_rotation_deg=2.0, ml_offset_mm=ROTATED["ml_offset_mm"])
    lens_rows = Grid.for_camera(cam, z=(-1.0, 1.0))
    sensor = Grid(lens_rows.shape, lens_rows.x, lens_rows.y, lens_rows.z)
    rng = np.random.default_rng(3)
    pos = np.column_stack([rng.uniform(-0.5, 0.5, 6), rng.uniform(-0.4, 0.4, 6),
                           rng.uniform(-0.8, 0.8, 6)])
    img = simulate_image(cam, pos, 4000.0, rays_per_particle=4000, seed=1, queue=queue)
    found = {}
    for name, grid in (("lens rows", lens_rows), ("sensor", sensor)):
        proj = Projector(cam, grid, queue)
        vol = reconstruct(img, proj, iterations=30, supersample=supersample,
                          coarse_iterations=0)
        report = recovery(vol, grid, pos)
        found[name] = report
        assert report.position_rms_vox < 1.0, name
    assert found["sensor"].recovered >= found["lens rows"].recovered - 1 >= 4


def test_an_unknown_general_mode_is_refused(queue):
    with pytest.raises(ValueError, match="general must be one of"):
        _projector(queue, general="fast")
