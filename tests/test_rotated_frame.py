"""A rotated microlens array in a reconstruction frame that follows its rows: the separable
projector path, exact against the NumPy weighting function, and grids that map between
the frame and object space."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import tolerances as tol
from helpers import ROTATED, assert_adjoint, assert_close_to_peak, lens_camera

from plenocl import Camera, Grid, Projector, simulate_image
from plenocl.bench.realarray import agreement, sparse_volume
from plenocl.camera.lattice import (
    RectangularLattice,
    lattice_fit,
    lattice_rotation_deg,
    separable_rotation_deg,
)
from plenocl.metrics import recovery
from plenocl.reconstruction import reconstruct
from plenocl.reference.simulate import trace_particles
from plenocl.reference.weights import voxel_weights

VOXELS = [(2, 3, 4), (1, 3, 4), (3, 2, 5), (0, 5, 1), (4, 1, 7), (2, 0, 0), (4, 6, 8)]


def _camera(rotation: float, jitter: float = 0.0) -> Camera:
    cam = lens_camera(ml_rotation_deg=rotation, ml_offset_mm=ROTATED["ml_offset_mm"])
    if jitter:
        rng = np.random.default_rng(4)
        cam = cam.with_centers(cam.microlens_centers
                               + rng.uniform(-jitter, jitter, cam.microlens_centers.shape))
    return cam


def _frame_grid(cam: Camera, shape=(5, 7, 9)) -> Grid:
    return Grid(shape, x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-5.0, 5.0),
                rotation_deg=lattice_rotation_deg(cam.microlens_centers))


@pytest.mark.parametrize("rotation", [2.0, 0.15, -0.7])
def test_lattice_rotation_is_the_arrays(rotation):
    cam = _camera(rotation)
    assert lattice_rotation_deg(cam.microlens_centers) == pytest.approx(rotation, abs=1e-9)
    assert separable_rotation_deg(cam.microlens_centers, 1e-3) == pytest.approx(rotation)
    assert separable_rotation_deg(_camera(0.0).microlens_centers, 1e-3) == 0.0
    grid = Grid.for_camera(cam, z=(-1.0, 1.0))
    assert grid.rotation_deg == pytest.approx(rotation)
    assert Grid.for_camera(_camera(0.0), z=(-1.0, 1.0)).rotation_deg == 0.0


@pytest.mark.parametrize("rotation, jitter, shear_tol", [(2.0, 0.0, 1e-3), (0.15, 0.0, 1e-3),
                                                         (0.15, 0.1, 0.05)])
def test_rotated_array_in_its_frame_is_separable_and_exact(queue, rotation, jitter, shear_tol):
    cam = _camera(rotation, jitter)
    grid = _frame_grid(cam)
    proj = Projector(cam, grid, queue, shear_tol=shear_tol)
    assert proj.path == "separable"
    assert Projector(cam, Grid(grid.shape, grid.x, grid.y, grid.z), queue,
                     general="exact").path == "general"
    n = cam.pixels[0] * cam.pixels[1]
    for vox in VOXELS:
        idx, w = voxel_weights(cam, grid, *vox, shear_tol=shear_tol)
        ref = np.zeros(n)
        ref[idx] = w
        onehot = np.zeros(grid.shape, np.float32)
        onehot[vox] = 1.0
        for got in (proj.forward(onehot).ravel(), np.bincount(
                proj.voxel_weights(*vox)[0], proj.voxel_weights(*vox)[1], minlength=n)):
            assert_close_to_peak(got, ref, tol.WEIGHTS, vox)
            assert got.sum() == pytest.approx(ref.sum(), rel=tol.FOOTPRINT_TOTAL)
    assert_adjoint(proj)


@pytest.mark.parametrize("z", [-3.0, 0.0, 2.0])
def test_rotated_frame_weights_correlate_with_ray_tracing(queue, z):
    """Paper Fig. 8 in the rotated frame: particles spread through a rotated voxel, traced
    in object space, light the pixels its weights say."""
    cam = _camera(2.0)
    vox = cam.ml_pitch_mm / cam.magnification
    grid = Grid((1, 1, 1), x=(0.03, 0.03 + vox), y=(-0.04, -0.04 + vox),
                z=(z - vox / 2, z + vox / 2), rotation_deg=2.0)
    proj = Projector(cam, grid, queue)
    assert proj.path == "separable"
    idx, w = proj.voxel_weights(0, 0, 0)
    rng = np.random.default_rng(5)
    n = 2500
    fx, fy = rng.uniform(*grid.x, n), rng.uniform(*grid.y, n)
    wx, wy = grid.to_world(fx, fy)
    pos = np.column_stack([wx, wy, rng.uniform(*grid.z, n)])
    sim = trace_particles(cam, pos, 1.0, rays_per_particle=400, seed=2).ravel()
    dense = np.zeros(sim.size)
    dense[idx] = w
    assert np.corrcoef(dense, sim)[0, 1] >= 0.99


def test_rotated_grid_maps_points_between_frame_and_object_space(tmp_path):
    grid = Grid((4, 5, 6), x=(-1.0, 2.0), y=(-0.5, 1.0), z=(-1.0, 1.0), rotation_deg=10.0)
    centres = grid.centers()
    idx = grid.to_index(centres)
    iz, iy, ix = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    np.testing.assert_allclose(idx, np.column_stack([ix.ravel(), iy.ravel(), iz.ravel()]),
                               atol=1e-9)
    assert grid.contains(centres).all()
    # a frame corner, rotated into object space, is inside; the unrotated corner is not
    corner = np.array([[grid.x[1] - 1e-9, grid.y[1] - 1e-9, 0.0]])
    wx, wy = grid.to_world(corner[:, 0], corner[:, 1])
    assert grid.contains(np.column_stack([wx, wy, [0.0]])).all()
    assert not grid.contains(corner).any()
    vx, vy = grid.to_world(1.0, 0.0)  # the frame's x axis, in object space
    assert (float(vx), float(vy)) == pytest.approx((np.cos(np.radians(10)),
                                                    np.sin(np.radians(10))))
    grid.to_toml(tmp_path / "g.toml")
    assert Grid.from_toml(tmp_path / "g.toml") == grid
    with pytest.raises(ValueError, match="rotation_deg"):
        Grid((1, 1, 1), (0, 1), (0, 1), (0, 1), rotation_deg=float("nan"))


def test_reconstruction_in_the_rotated_frame_finds_the_particles(queue):
    """Simulated (ray-traced) particles seen through a 2 degree array, reconstructed on the
    frame grid (separable path): recovered at their object-space positions as well as the
    same scene (in the frame) seen through an aligned array."""
    found = {}
    for rotation in (0.0, 2.0):
        cam = _camera(rotation)
        grid = Grid.for_camera(cam, z=(-1.0, 1.0))
        assert grid.rotation_deg == pytest.approx(rotation)
        rng = np.random.default_rng(3)
        frame = np.column_stack([rng.uniform(grid.x[0] + 0.2, grid.x[1] - 0.2, 6),
                                 rng.uniform(grid.y[0] + 0.2, grid.y[1] - 0.2, 6),
                                 rng.uniform(-0.8, 0.8, 6)])
        wx, wy = grid.to_world(frame[:, 0], frame[:, 1])
        pos = np.column_stack([wx, wy, frame[:, 2]])
        img = simulate_image(cam, pos, 4000.0, rays_per_particle=4000, seed=1, queue=queue)
        proj = Projector(cam, grid, queue)
        assert proj.path == "separable"
        report = recovery(reconstruct(img, proj, iterations=30, supersample=1), grid, pos)
        found[rotation] = report.recovered
        assert report.position_rms_vox < 1.0
    assert found[2.0] >= found[0.0] >= 5


def test_only_a_volume_on_the_projectors_grid_is_kept_on_the_device(queue):
    """``run_reconstruction(keep_for_next_stage=True)`` on a grid across a rotated array's
    lens rows: the voxels (each iteration resampled) keep their device volume, returned
    as it (a DeviceVolume), the host one to the bit; sub-voxels on the lens-row frame,
    resampled onto the grid on the host, keep none rather than the frame's."""
    from plenocl.reconstruction import ReconstructionSettings, run_reconstruction

    cam = lens_camera(12, 10, **ROTATED)
    grid = Grid((4, 8, 8), x=(-0.5, 0.5), y=(-0.5, 0.5), z=(-0.5, 0.5))
    proj = Projector(cam, grid, queue)
    assert proj.path == "resampled"
    img = simulate_image(cam, np.array([[0.05, -0.1, 0.1], [-0.2, 0.15, -0.2]]), 2e4,
                         rays_per_particle=3000, seed=1, queue=queue)
    voxels = ReconstructionSettings(supersample=1, iterations=3)
    vol, info = run_reconstruction(img, proj, voxels, keep_for_next_stage=True)
    assert vol.array is info.volume_on_device and vol.get().any()
    assert np.array_equal(vol.get(), run_reconstruction(img, proj, voxels)[0])
    sub = ReconstructionSettings(supersample=2, coarse_iterations=2, iterations=2)
    vol, info = run_reconstruction(img, proj, sub, keep_for_next_stage=True)
    assert vol.shape == grid.shape and info.volume_on_device is None


def test_a_grid_across_the_lens_rows_is_resampled_or_says_it_is_slow(queue):
    """Never a silent 12x: a sensor-axis grid on a rotated array is projected through the
    lens-row frame quietly, a sheared array too (jittered centres: the rows' frame makes
    its map triangular); a frame that is not separable warns with the cause (the rows'
    turn, the columns' skew) and the fix; the grid Grid.for_camera gives stays quiet."""
    import warnings

    cam = lens_camera(12, 10, **ROTATED)
    sensor_axes = Grid((4, 8, 8), x=(-0.5, 0.5), y=(-0.5, 0.5), z=(-0.5, 0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        assert Projector(cam, sensor_axes, queue).path == "resampled"
        assert Projector(cam, sensor_axes, queue, general="exact").path == "general"
        assert Projector(cam, Grid.for_camera(cam, (-0.5, 0.5)), queue).path == "separable"
    rng = np.random.default_rng(7)
    sheared = cam.with_centers(cam.microlens_centers
                               + rng.uniform(-0.3, 0.3, cam.microlens_centers.shape))
    skew = RectangularLattice.fit(sheared.microlens_centers).skew_deg
    assert abs(skew) > 1e-3  # drifts more than shear_tol lenses across the rows
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        proj = Projector(sheared, sensor_axes, queue)
        assert proj.path == "resampled" and proj.frame.path == "separable"
        assert not proj.frame.lens_map.axis_aligned and proj.frame.lens_map.triangular
        exact = Projector(sheared, sensor_axes, queue, general="exact")
    with pytest.warns(UserWarning, match=rf"turned [+-]\d+\.\d+° against this grid's axes "
                      rf"and its columns {skew:+.4f}° off square.*general path"):
        assert Projector(sheared, sensor_axes, queue, frame=exact).path == "general"


def _sheared_camera(skew_deg: float = 0.05) -> Camera:
    """The 12 x 10 camera calibrated on an array whose columns lean ``skew_deg`` off square
    to its level rows (a real array's lattice: rows and columns 0.005° off square across
    20 rows drift 0.002 lenses, above ``shear_tol``)."""
    cam = lens_camera(ml_offset_mm=ROTATED["ml_offset_mm"])
    centres = cam.microlens_centers.copy()
    rows = centres.shape[0]
    pitch = lattice_fit(centres)[1, 1]
    lean = np.tan(np.radians(skew_deg)) * pitch * (np.arange(rows) - (rows - 1) / 2)
    centres[..., 0] += lean[:, None]
    return cam.with_centers(centres)


def test_sheared_array_is_separable_and_exact(queue):
    """A calibrated rectangular array whose columns are not square to its rows runs the
    separable path in its rows' frame (the columns' lean kept in the map, the aperture
    samples leaning with it), exact against the NumPy weighting function, equal to the
    general kernels on the same model, and adjoint."""
    cam = _sheared_camera()
    assert RectangularLattice.fit(cam.microlens_centers).skew_deg == pytest.approx(0.05)
    grid = _frame_grid(cam)
    proj = Projector(cam, grid, queue)
    lens_map = proj.lens_map
    assert proj.path == "separable" and lens_map.triangular and not lens_map.axis_aligned
    assert abs(lens_map.matrix[0, 1] / lens_map.matrix[1, 1]) * 10 > 1e-3  # kept: > tol
    assert proj.aperture.shear == pytest.approx(-lens_map.matrix[0, 1] / lens_map.matrix[0, 0])
    general = copy.copy(proj.model)
    general.path = "general"
    kernels = Projector(cam, grid, queue, model=general, general="exact")
    assert kernels.path == "general"
    n = cam.pixels[0] * cam.pixels[1]
    for vox in VOXELS:
        idx, w = voxel_weights(cam, grid, *vox)
        ref = np.bincount(idx, w, minlength=n)
        onehot = np.zeros(grid.shape, np.float32)
        onehot[vox] = 1.0
        assert_close_to_peak(proj.forward(onehot).ravel(), ref, tol.WEIGHTS, vox)
    rng = np.random.default_rng(3)
    vol = rng.random(grid.shape).astype(np.float32)
    img = rng.random(proj.image_shape).astype(np.float32)
    np.testing.assert_allclose(proj.forward(vol), kernels.forward(vol), rtol=tol.RECOMPUTED,
                               atol=tol.RECOMPUTED_FLOOR * vol.sum())
    np.testing.assert_allclose(proj.back(img), kernels.back(img), rtol=tol.RECOMPUTED,
                               atol=tol.RECOMPUTED_FLOOR * img.sum())
    assert_adjoint(proj)


def test_sheared_array_agrees_with_the_square_aperture_samples(queue):
    """The leaning aperture samples of a sheared array's separable path against the square
    samples of the general path it took before: the same light (totals within float32),
    placed alike: the images and their lens images' centroids differ by under a tenth of
    what the square samples differ from four times finer ones (the model's own sampling
    error)."""
    cam = _sheared_camera()
    grid = _frame_grid(cam)
    separable = Projector(cam, grid, queue)
    square = Projector(cam, grid, queue, shear_tol=-1.0, general="exact")  # no term dropped
    assert square.path == "general" and square.aperture.shear == 0.0
    fine = Projector(cam, grid, queue, shear_tol=-1.0, general="exact",
                     oversample=4 * square.model.oversample)
    vol = sparse_volume(grid, 12, seed=8)
    a, b, f = separable.forward(vol), square.forward(vol), fine.forward(vol)
    now, sampling = agreement(a, b, cam), agreement(b, f, cam)
    assert now.total < tol.FOOTPRINT_TOTAL
    assert now.peak < 0.1 * sampling.peak and now.centroid_px < 0.1 * sampling.centroid_px
