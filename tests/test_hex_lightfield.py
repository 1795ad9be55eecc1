"""Hexagonal microlens arrays through the pixels' lens cells, the light field and
refocusing (issue 29; docs/design.md §2, §4): every pixel belongs to the nearest
calibrated centre, a white image's views are uniform, a particle refocuses at its depth
and where the geometry puts it, the kernel matches its twin on staggered views, and MART
runs with its view blocks."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol
from helpers import lens_camera
from scipy.spatial import cKDTree

from plenocl import Camera, Grid, Projector
from plenocl.camera.lattice import RectangularLattice
from plenocl.lightfield import LightField, lens_lattice, lens_positions_mm, pixel_coordinates
from plenocl.metrics import matched_errors
from plenocl.optics.ownership import lens_owner, pixel_lenses
from plenocl.reconstruction import reconstruct, view_blocks
from plenocl.reference import reconstruct as ref
from plenocl.reference.refocus import refocus_views
from plenocl.simulate import simulate_image, simulate_white_image

ROW = np.sqrt(3) / 2
ZS = np.arange(-3.0, 3.01, 0.5)


def hex_camera(cols: int = 24, rows: int = 23, **changes) -> Camera:
    """A hexagonal camera of ~17 px lenses whose sensor the array fills, ideal centres
    marked calibrated."""
    cam = lens_camera(cols, rows, (int(16.98 * cols) + 1, int(16.98 * rows * ROW) + 1),
                      ml_layout="hexagonal", **changes)
    return cam.with_centers(cam.ideal_microlens_centers())


def jittered(cam: Camera, sigma_px: float = 0.4, missing: tuple | None = (5, 7)) -> Camera:
    """``cam`` with its calibrated centres off the lattice and one lens ``(ky, kx)``
    missing (``None``: none)."""
    rng = np.random.default_rng(1)
    centres = cam.microlens_centers + rng.normal(0, sigma_px, cam.microlens_centers.shape)
    if missing is not None:
        centres[missing] = np.nan
    return cam.with_centers(centres)


def _pixels(cam: Camera) -> np.ndarray:
    w, h = cam.pixels
    return np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(float)


# ---- the pixels' lens cells ---------------------------------------------------------------
@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_every_pixel_belongs_to_the_nearest_calibrated_centre(shift):
    """Against a brute-force k-d tree on a rotated array with jittered calibrated
    centres: a lens calibration missed counts at its fitted lattice position; pixels
    beyond the array (``-1``) lie at least half a pitch from every centre, and ``clamp``
    gives them the nearest edge lens."""
    cam = jittered(hex_camera(16, 15, ml_odd_row_shift=shift, ml_rotation_deg=2.5,
                              ml_offset_mm=(0.01, -0.02)))
    model = lens_lattice(cam)
    centres = cam.microlens_centers.copy()
    centres[5, 7] = np.r_[cam.lens_lattice_coords()[5, 7], 1.0] @ model
    ky, kx = np.mgrid[0:15, 0:16]
    dist, nearest = cKDTree(centres.reshape(-1, 2)).query(_pixels(cam))
    got_kx, got_ky = pixel_lenses(cam, clamp=True)
    np.testing.assert_array_equal(got_kx.ravel(), kx.ravel()[nearest])
    np.testing.assert_array_equal(got_ky.ravel(), ky.ravel()[nearest])
    owner = lens_owner(cam).ravel()
    beyond = owner < 0
    assert 0 < beyond.mean() < 0.1
    np.testing.assert_array_equal(owner[~beyond], (ky * 16 + kx).ravel()[nearest[~beyond]])
    pitch_px = np.linalg.norm(model[0])
    assert dist[beyond].min() > 0.45 * pitch_px


def test_the_axial_view_has_the_same_cells_and_rectangular_cells_are_the_lattice_fits():
    """The projector's axial view of a hexagonal camera gets the same hexagonal cells,
    numbered by its axial columns; a rectangular camera keeps its lattice cells."""
    cam = jittered(hex_camera(12, 11, ml_rotation_deg=-1.0))
    axial = cam.on_lens_lattice()
    kx, ky = pixel_lenses(cam, clamp=True)
    qx, qy = pixel_lenses(axial, clamp=True)
    np.testing.assert_array_equal(qy, ky)
    np.testing.assert_array_equal(axial.microlens_centers[qy, qx], cam.microlens_centers[ky, kx])
    np.testing.assert_array_equal(lens_owner(axial) < 0, lens_owner(cam) < 0)
    rect = jittered(lens_camera(12, 10, ml_rotation_deg=2.0))
    cells = RectangularLattice.fit(rect.microlens_centers).cells(*rect.pixels)
    for got, want in zip(pixel_lenses(rect), cells):
        np.testing.assert_array_equal(got, want)


# ---- the light field ----------------------------------------------------------------------
@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_samples_sit_at_the_hexagonal_lens_positions(shift):
    cam = hex_camera(12, 11, ml_odd_row_shift=shift, ml_rotation_deg=1.5)
    np.testing.assert_allclose(lens_positions_mm(cam), cam.microlens_positions_mm(),
                               atol=1e-12)
    pc = pixel_coordinates(cam)
    for kx, ky in ((4, 3), (5, 4), (1, 7)):  # even and odd rows
        col, row = np.rint(cam.microlens_centers[ky, kx]).astype(int)
        assert (pc.kx[row, col], pc.ky[row, col]) == (kx, ky)
        np.testing.assert_allclose((pc.x_mm[row, col], pc.y_mm[row, col]),
                                   cam.microlens_positions_mm()[ky, kx], atol=1e-12)


def test_a_white_image_lights_every_view_of_every_lens_alike(queue):
    """A full-aperture white image (each hexagon lit uniformly by the simulator): every
    lens has a sample in every view well inside the aperture, uniform across the lenses
    to the rays' noise (about 5 % per sample), and the views agree with each other."""
    cam = hex_camera(14, 13, ml_rotation_deg=1.0)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, rays_per_lens=40000,
                                 blur_px=0.0, seed=1, queue=queue)
    lf = LightField(white, cam, queue=queue)
    radius = np.hypot(*np.meshgrid(lf.u, lf.v)) / (cam.exit_pupil_diameter_mm / 2)
    inner = lf.views[radius < 0.8][:, 1:-1, 1:-1]  # the edge lenses' cells are cut
    assert np.isfinite(inner).all()
    means = inner.mean((1, 2))
    assert (inner.std((1, 2)) / means).max() < 0.09
    assert means.std() / means.mean() < 0.02


@pytest.mark.parametrize("shift, z", [(0.5, -2.0), (-0.5, -2.0), (0.5, 1.5), (-0.5, 1.5)])
def test_particle_refocuses_at_its_depth_and_where_geometry_puts_it(queue, shift, z):
    """Sharpest (peak and variance) at its own depth, at ``ξ = X'/α`` on the array
    plane (measured: within 0.03 pitch, as on the rectangular camera)."""
    cam = hex_camera(ml_odd_row_shift=shift)
    point = np.array([0.2, -0.15, z])
    lf = LightField(simulate_image(cam, point[None], 1e5, 20000, seed=1, queue=queue), cam,
                    queue=queue)
    stack = lf.focal_stack(ZS, supersample=2)
    flat = stack.reshape(len(ZS), -1)
    assert ZS[flat.max(1).argmax()] == z and ZS[flat.var(1).argmax()] == z
    img = stack[list(ZS).index(z)]
    w = np.clip(img - 0.2 * img.max(), 0, None)
    found = (w[..., None] * lf.output_positions_mm(supersample=2)).sum((0, 1)) / w.sum()
    expected = cam.image_points(point[None])[0, :2] / cam.alpha(z)
    assert found == pytest.approx(expected, abs=0.1 * cam.ml_pitch_mm)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_refocusing_reproduces_a_linear_field_of_the_staggered_lens_positions(queue, shift):
    """Views that are a linear function of each lens's array-frame position ``(a, b) =
    (kx + shift (ky mod 2), ky)``: every row's B-spline weights reproduce it, so the
    refocused image is that function at ``(a, b) + shift`` wherever all taps exist (a
    kernel reading the stagger with the wrong sign is off by a lens in the odd rows)."""
    cam = hex_camera(12, 11, ml_odd_row_shift=shift)
    lf = LightField(np.zeros(cam.pixels[::-1], np.float32), cam, queue=queue)
    ab = cam.lens_lattice_coords()
    field = 2.0 * ab[..., 0] + 3.0 * ab[..., 1] + 1.0
    lf.views = field[None, None]
    shifts = np.array([[[0.0, 0.0]], [[0.3, -0.4]], [[-1.2, 0.7]], [[0.45, 1.1]]])
    got = lf.shift_and_add(shifts, supersample=2)
    a, b = lf.output_lens_coordinates(supersample=2)
    for p, s in enumerate(shifts[:, 0]):
        want = 2.0 * (a[None, :] + s[0]) + 3.0 * (b[:, None] + s[1]) + 1.0
        np.testing.assert_allclose(got[p][6:-6, 6:-6], want[6:-6, 6:-6], rtol=1e-5)


@pytest.mark.parametrize("shift, supersample", [(0.5, 1), (-0.5, 3)])
def test_kernel_matches_reference_on_staggered_views(queue, shift, supersample):
    rng = np.random.default_rng(7)
    cam = hex_camera(12, 11, ml_odd_row_shift=shift)
    lf = LightField(np.zeros(cam.pixels[::-1], np.float32), cam, queue=queue)
    nuv, ny, nx = 7, 13, 17  # odd sizes, not multiples of any work-group size
    views = rng.uniform(0, 10, (nuv, ny, nx)).astype(np.float32)
    views[rng.random(views.shape) < 0.1] = np.nan
    views[:, :2, :3] = np.nan  # a dead region: zero output, no NaN
    lf.views = views.reshape(1, nuv, ny, nx)
    shifts = rng.uniform(-2.5, 2.5, (3, nuv, 2))
    shifts[0] = 0.0
    got = lf.shift_and_add(shifts, supersample)
    want = refocus_views(views, shifts, supersample, row_shift=shift)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=tol.REFOCUS, atol=tol.REFOCUS_FLOOR)
    assert np.abs(want - refocus_views(views, shifts, supersample)).max() > 0.1


def test_the_light_field_refuses_the_projectors_axial_view(queue):
    cam = hex_camera(8, 8)
    with pytest.raises(ValueError, match="not its axial view"):
        LightField(np.ones(cam.pixels[::-1]), cam.on_lens_lattice(), queue=queue)


# ---- MART's view blocks -------------------------------------------------------------------
def test_mart_view_blocks_on_a_hexagonal_camera(queue):
    """MART's blocks are the reference's nearest-centre blocks at every pixel, the same
    for the camera and the projector's axial view; MART with them reconstructs four ray
    traced particles (measured: 0.5 / 2.2 voxel at worst; block MART finds 3 of them on
    the rectangular camera of the same pitch at this threshold)."""
    cam = jittered(hex_camera(16, 19, ml_rotation_deg=1.0), missing=None)
    for n in (2, 3):
        np.testing.assert_array_equal(view_blocks(cam, n), ref.view_blocks(cam, n))
        np.testing.assert_array_equal(view_blocks(cam.on_lens_lattice(), n),
                                      view_blocks(cam, n))
    cam = hex_camera(16, 19)
    grid = Grid((24, 16, 16), x=(-1.0, 1.0), y=(-1.0, 1.0), z=(-2.0, 2.0))
    pos = np.array([[-0.5, -0.4, -1.2], [0.45, 0.3, 0.8], [0.1, -0.5, 0.2],
                    [-0.4, 0.5, 1.5]])
    img = simulate_image(cam, pos, np.full(4, 2e4), 20000, seed=3, blur_px=1.0, queue=queue)
    vol = reconstruct(img, Projector(cam, grid, queue), method="mart", mart_blocks=2,
                      supersample=1)
    d = matched_errors(vol, grid, pos, threshold=0.01, lateral=1.5, depth=4.0)
    assert len(d) == 4
    assert np.abs(d[:, :2]).max() <= 0.6 and np.abs(d[:, 2]).max() <= 3.0
