"""The image fit's ray bundle on a hexagonal microlens array (issue 29; docs/design.md
§7.2): the lens shares of the hexagonal cells (continuous, summing to one, exact
derivatives), the bundle's image against the exact tracer, its derivatives, the kernel
against the NumPy bundle, and the fit on ray-traced particles."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol
from helpers import lens_camera

from plenocl import Grid, Projector, simulate_image
from plenocl.optics.hexcells import HEX_RAMP_MAX, HexCells
from plenocl.optics.raybundle import RayBundle
from plenocl.pipeline import process_pair
from plenocl.piv import PIVSettings
from plenocl.piv.devicebundle import DeviceRayBundle
from plenocl.piv.imagefit import ImageFit
from plenocl.reference.simulate import trace_particles

ROW = np.sqrt(3) / 2


def hex_camera(cols: int = 16, rows: int = 18, **changes):
    """A hexagonal camera of the synthetic optics (~17 px lenses), its sensor cut to the
    array, turned by 1 degree."""
    changes = {"ml_rotation_deg": 1.0, **changes}
    return lens_camera(cols, rows, (int(16.98 * cols) + 1, int(16.98 * rows * ROW) + 1),
                       ml_layout="hexagonal", **changes)


CAM = hex_camera()


def image(bundle: RayBundle, pos: np.ndarray, shift=None) -> np.ndarray:
    """Every rendered row (value, d/dX', d/dY', d/dd', d/dI) of unit particles at ``pos``
    on the whole sensor (flat), the image points moved by ``shift``."""
    cam = bundle.camera
    pts = cam.image_points(pos)
    patches = bundle.patches(pts)
    moved = pts if shift is None else pts + shift
    elements, rows = bundle.render(moved, np.ones(len(pts)), patches)
    _, pixel = patches.pixels(cam.pixels[0], elements)
    full = np.zeros((len(rows), cam.pixels[0] * cam.pixels[1]))
    for k, row in enumerate(rows):
        np.add.at(full[k], pixel, row)
    return full


def regular_cells(shift: float = 0.5) -> HexCells:
    """The cells of an ideal array of unit pitch (rows along x)."""
    q, r = np.meshgrid(np.arange(8.0), np.arange(8.0))
    lenses = np.stack([q + shift * r, r * ROW], -1)
    return HexCells.fit(lenses)


def test_the_hexagonal_bundle_is_not_refused_and_keeps_its_lenses():
    """The bundle takes the axial view's lenses (NaN where it has none) and its fitted
    lattice: every lens of the camera is in it, at its own centre."""
    bundle = RayBundle.of(CAM, rays=64)
    view = CAM.on_lens_lattice()
    assert bundle.cells is not None and bundle.lenses.shape == (*view.ml_count[::-1], 2)
    pos = CAM.microlens_positions_mm().reshape(-1, 2)
    lat = pos @ bundle.to_lattice[:2] + bundle.to_lattice[2]
    q, r = bundle.cells.nearest(lat).T
    np.testing.assert_allclose(bundle.lenses[r, q], pos, atol=1e-9)
    assert bundle.cells.pitch == pytest.approx(CAM.ml_pitch_mm, rel=1e-9)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_shares_follow_the_nearest_centre_and_are_continuous(shift):
    """Away from edges a ray is its nearest lens's alone; the shares sum to 1, are 1/2
    each on an edge, 1/3 each at a vertex, fall linearly over the ramp along an edge,
    and do not jump where the nearest lens changes."""
    cells = regular_cells(shift)
    rng = np.random.default_rng(2)
    lat = rng.uniform(2, 5, (20000, 2))
    pts = np.column_stack([lat, np.ones(len(lat))]) @ cells.model
    index, share, *_ = cells.shares(lat, 0.2)
    assert np.allclose(share.sum(-1), 1)
    lenses = np.column_stack([index.reshape(-1, 2), np.ones(index[..., 0].size)])
    dist = np.hypot(*(pts[:, None] - (lenses @ cells.model).reshape(*index.shape)).T).T
    assert np.array_equal(np.argmin(dist, axis=1), np.zeros(len(lat)))  # first: nearest
    assert (share[:, 0] >= share.max(-1) - 1e-12).all() and (share > 0).sum(-1).max() == 3
    power = (dist[:, 1:] ** 2 - dist[:, :1] ** 2) / 2  # distances from the bisectors
    alone = power.min(-1) > 0.2  # beyond the ramp of every edge
    assert np.all(share[alone, 0] == 1)

    def lens_shares(point):  # the shares by lens, for points in lattice units
        idx, sh, *_ = cells.shares(point, 0.2)
        out = {}
        for k, s in zip(map(tuple, idx.reshape(-1, 2)), sh.ravel(), strict=True):
            out[k] = out.get(k, 0.0) + s
        return out

    a, b = np.array([3.0, 3.0]), np.array([4.0, 3.0])  # neighbours along a row
    mid = (a + b) / 2
    for eps in (1e-9, 0.05, 0.1):
        one, other = lens_shares(mid - [eps, 0]), lens_shares(mid + [eps, 0])
        assert one[(3, 3)] == pytest.approx(other[(4, 3)], abs=1e-12)
        assert one[(3, 3)] == pytest.approx(0.5 + eps / 0.4, abs=1e-9)  # the linear ramp
    vertex = np.array([1.0, 1.0]) / 3 if shift > 0 else np.array([2.0, 1.0]) / 3
    third = lens_shares(np.array([3.0, 3.0]) + vertex + 1e-12)
    assert sorted(third.values())[-3:] == pytest.approx([1 / 3] * 3, abs=1e-9)
    assert HEX_RAMP_MAX < 0.5


def test_share_derivatives_match_central_differences():
    """The shares' derivatives by the point and by the ramp, near edges and vertices,
    against central differences (away from the ramps' ends, where they kink)."""
    cells = HexCells.fit(CAM.on_lens_lattice().microlens_centers * 0.01)  # any unit
    rng = np.random.default_rng(3)
    lat = rng.uniform(3, 9, (4000, 2))
    ramp = 0.3
    index, share, dx, dr = cells.shares(lat, ramp)
    h = 1e-7 * cells.pitch
    to_lat = np.linalg.inv(cells.model[:2])
    for axis in range(2):
        step = h * to_lat[axis]
        ip, plus, *_ = cells.shares(lat + step, ramp)
        im, minus, *_ = cells.shares(lat - step, ramp)
        same = (ip == index).all((1, 2)) & (im == index).all((1, 2))
        assert same.mean() > 0.99
        numeric = (plus - minus)[same] / (2 * h)
        np.testing.assert_allclose(dx[same, :, axis], numeric, atol=1e-5 / cells.pitch)
    plus, minus = cells.shares(lat, ramp + 1e-7)[1], cells.shares(lat, ramp - 1e-7)[1]
    np.testing.assert_allclose(dr, (plus - minus) / 2e-7, atol=1e-5)
    assert np.abs(dx).max() > 1 / cells.pitch  # the ramps were crossed


@pytest.mark.parametrize("z", [-2.5, 1.5, 3.0])
def test_bundle_matches_the_exact_hexagonal_tracer(z):
    """Against the simulator's twin (rays to the nearest centre, 200 000 random rays): the
    same light, the images within the tracer's own noise (4-6 %; two seeds of the tracer
    differ by 6-8 %; the rectangular bundle on its own camera: 4-6 %), the centroid
    within 0.1 px (the tracer's own scatters by 0.07 px RMS between seeds at z = 3;
    measured: 0.01-0.05 px)."""
    pos = np.array([[0.11, -0.07, z]])
    ref = trace_particles(CAM, pos, 1.0, 200_000, seed=5, blur_px=0.8).ravel()
    img = image(RayBundle.of(CAM, rays=3000, blur_px=0.8), pos)[0]
    assert img.sum() == pytest.approx(ref.sum(), rel=2e-3)
    assert np.linalg.norm(img - ref) / np.linalg.norm(ref) < 0.08
    cols = np.arange(ref.size) % CAM.pixels[0]
    rows = np.arange(ref.size) // CAM.pixels[0]
    for coord in (cols, rows):
        assert (coord * img).sum() / img.sum() == pytest.approx(
            (coord * ref).sum() / ref.sum(), abs=0.1)


@pytest.mark.parametrize("axis, step", [(0, 1e-4), (1, 1e-4), (2, 1e-3)])
def test_derivatives_match_central_differences(axis, step):
    """Every derivative row against central differences of the image (1.3 %, 0.5 %,
    0.9 %: the differences straddle the ramps' kinks), for particles on both sides of
    focus and one whose ramp is cut (``HEX_RAMP_MAX``)."""
    bundle = RayBundle.of(CAM, rays=500, blur_px=0.8)
    pos = np.array([[-0.5, 0.1, 2.5], [0.3, -0.4, -9.0], [0.2, 0.3, -1.5]])
    ramp, _ = bundle._ramp(CAM.image_points(pos)[:, 2])
    assert ramp[1] > HEX_RAMP_MAX > ramp[0] > 0.05
    shift = np.zeros(3)
    shift[axis] = step
    rows = image(bundle, pos)
    numeric = (image(bundle, pos, shift)[0] - image(bundle, pos, -shift)[0]) / (2 * step)
    assert np.linalg.norm(rows[1 + axis] - numeric) < 0.03 * np.linalg.norm(numeric)
    assert np.allclose(rows[4], rows[0])  # d/dI is the unit image


def awkward_points(bundle: RayBundle, count: int) -> np.ndarray:
    """Image points: chief rays on a cell edge, at a cell vertex and just inside an
    edge, near the sensor's corners, over the missing lenses, the rest random."""
    cells, cam = bundle.cells, bundle.camera
    s_ip = cam.image_distance_mm * 1.002
    lat = np.array([[6.5, 8.0], [7 + 1 / 3, 9 + 1 / 3], [9.0, 8.4997], [10.0, 9.0]])
    x = np.column_stack([lat, np.ones(len(lat))]) @ cells.model
    near = np.column_stack([x * s_ip / cam.image_distance_mm, np.full(len(x), s_ip)])
    rng = np.random.default_rng(count)
    edges = cam.image_points(np.array([[1.0, -0.9, 2.0], [-1.0, 0.95, -3.0]]))
    fill = cam.image_points(np.column_stack([rng.uniform(-1.0, 1.0, count),
                                             rng.uniform(-0.9, 0.9, count),
                                             rng.uniform(-9.0, 9.0, count)]))
    return np.vstack([near, edges, fill])[:count]


@pytest.mark.parametrize("count, rays, blur", [(1, 37, 0.8), (7, 200, 0.35), (23, 53, 2.0)])
def test_kernel_matches_the_numpy_bundle(queue, count, rays, blur):
    """Every row of every patch element against the float64 twin, within float32
    rounding of each row's peak, with missing lenses under some of the particles."""
    centres = CAM.ideal_microlens_centers().copy()
    centres[8:10, 6:9] = np.nan
    bundle = RayBundle.of(CAM.with_centers(centres), rays=rays, blur_px=blur)
    pts = awkward_points(bundle, count)
    intensity = np.linspace(10.0, 1000.0, count)
    patches = bundle.patches(pts)
    total = int(patches.offset[-1])
    rows = []
    for renderer in (bundle, DeviceRayBundle(bundle, queue)):
        elements, values = renderer.render(pts, intensity, patches)
        rows.append(np.zeros((5, total)))
        rows[-1][:, elements] = values
    want, got = rows
    assert np.isfinite(got).all()
    for k in range(5):
        np.testing.assert_allclose(got[k], want[k], rtol=0,
                                   atol=tol.RAYBUNDLE * np.abs(want[k]).max(), err_msg=k)


def bench_camera(layout: str, cols: int, rows: int):
    """The synthetic optics with the sensor cut to the array (``benchmarks/hexagonal.py``),
    calibrated to its ideal centres."""
    row_px = 16.98 * (ROW if layout == "hexagonal" else 1.0)
    cam = lens_camera(cols, rows, (int(16.98 * cols) + 1, int(row_px * rows) + 1),
                      ml_layout=layout)
    return cam.with_centers(cam.ideal_microlens_centers())


GRID = Grid((32, 24, 24), x=(-1.5, 1.5), y=(-1.5, 1.5), z=(-2.0, 2.0))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm


def test_fit_recovers_out_of_focus_particles_as_on_a_rectangular_array():
    """Started (0.3, -0.3, 1.5) voxels off, six particles 0.9-1.8 mm either side of focus
    (ray traced to the nearest centre, read noise) come back within 0.1 voxel in depth
    and 0.01 laterally on a hexagonal array, as on a rectangular one (measured: at most
    0.094 / 0.006 against 0.104 / 0.006 voxel)."""
    rng = np.random.default_rng(1)
    true = np.column_stack([rng.uniform(-1.0, 1.0, 6), rng.uniform(-0.9, 0.9, 6),
                            [-1.8, -1.3, -0.9, 0.9, 1.3, 1.8]])
    worst = {}
    for layout, lenses in (("hexagonal", (24, 28)), ("rectangular", (24, 24))):
        cam = bench_camera(layout, *lenses)
        img = trace_particles(cam, true, 4000.0, 40_000, seed=3, blur_px=0.8)
        img = img + 20.0 + np.random.default_rng(3).normal(0.0, 1.0, img.shape)
        out = ImageFit(cam, GRID, [img]).fit(0, true + np.array([0.3, -0.3, 1.5]) * VOXEL)
        worst[layout] = (np.abs(out.positions - true) / VOXEL).max(axis=0)
        assert out.intensities == pytest.approx(4000.0, rel=0.1)
    assert worst["hexagonal"][2] < 0.12 and worst["hexagonal"][:2].max() < 0.01
    assert worst["hexagonal"][2] < 1.2 * worst["rectangular"][2]


def test_process_pair_fits_a_hexagonal_cameras_particles(queue):
    """``process_pair`` with the image fit (the default) runs on a hexagonal camera: the
    particle pairs are fitted to both raw images, and 40 particles 0.8-1.8 mm out of focus
    give vectors whose depth error falls to less than half of the same pair's without
    the fit (measured, RMS: 0.60 to 0.05 voxel in depth, 0.09 to 0.005 laterally; the
    axial view's rhombic cells: 0.10 and 0.017)."""
    cam = bench_camera("hexagonal", 24, 28)
    rng = np.random.default_rng(4)
    depth = rng.choice([-1, 1], 40) * rng.uniform(0.8, 1.8, 40)
    pos = np.column_stack([rng.uniform(-1.4, 1.4, (40, 2)), depth])
    shift = np.array([2.3, -1.4, 1.7])
    raws = [simulate_image(cam, p, np.full(40, 2e4), 20000, seed=9 + k, blur_px=1.0,
                           photon_noise=True, queue=queue)
            for k, p in enumerate((pos, pos + shift * VOXEL))]
    proj = Projector(cam, GRID, queue)
    assert proj.camera.ml_layout == "axial"  # the fit gets the projector's axial view
    assert ImageFit(proj.camera, GRID, raws).bundle.cells is not None  # hexagonal cells
    err = {}
    for fit in (None, True):
        piv = process_pair(*raws, proj, image_fit=fit, piv=PIVSettings(windows=(16,))).piv
        assert piv.refinement["pairs"] >= 20
        d = np.stack([piv.u, piv.v, piv.w], -1)[piv.valid] - shift
        err[fit] = np.sqrt(np.mean(d**2, axis=0))
    assert err[True][2] <= 0.5 * err[None][2]
    assert err[True][:2].max() <= 0.05
