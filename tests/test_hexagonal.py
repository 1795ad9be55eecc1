"""Hexagonal microlens arrays (issue 29; docs/design.md §2): the camera's layout, the
simulator's kernel against its NumPy twin and against an independent nearest-centre ray
trace, and the lens cells a white image lights."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import lens_camera, vendor_white_image
from scipy.spatial import cKDTree

from plenocl import Camera, reference
from plenocl.calibration import find_centers
from plenocl.reference.simulate import _cell_points
from plenocl.simulate import Simulator, centre_shift_px, simulate_image, simulate_white_image

ROW = np.sqrt(3) / 2


def hex_camera(cols: int = 12, rows: int = 12, **changes) -> Camera:
    """A hexagonal test camera: ``cols x rows`` lenses of ~17 px, rows 0.866 pitch apart."""
    return lens_camera(cols, rows, (17 * cols + 9, int(17 * rows * ROW) + 17),
                       ml_layout="hexagonal", **changes)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_every_inner_lens_has_six_neighbours_one_pitch_away(shift):
    cam = hex_camera(ml_odd_row_shift=shift, ml_rotation_deg=3.0)
    pos = cam.microlens_positions_mm().reshape(-1, 2)
    dist, _ = cKDTree(pos).query(pos, k=7)
    inner = np.hypot(*(pos - pos.mean(0)).T) < 0.4
    np.testing.assert_allclose(dist[inner, 1:], cam.ml_pitch_mm, rtol=1e-12)
    assert cam.ml_row_pitch_mm == pytest.approx(cam.ml_pitch_mm * ROW)
    odd = cam.microlens_positions_mm()[1, 0] - cam.microlens_positions_mm()[0, 0]
    turn = np.radians(3.0)
    along = odd @ [np.cos(turn), np.sin(turn)]
    assert along == pytest.approx(shift * cam.ml_pitch_mm)


def test_a_hexagonal_camera_file_round_trips_and_refuses_bad_layouts(tmp_path):
    cam = hex_camera(ml_odd_row_shift=-0.5)
    cam.to_toml(tmp_path / "hex.toml")
    back = Camera.from_toml(tmp_path / "hex.toml")
    assert (back.ml_layout, back.odd_row_shift) == ("hexagonal", -0.5)
    np.testing.assert_array_equal(back.microlens_centers, cam.microlens_centers)
    assert "layout" not in lens_camera().to_dict()["microlens_array"]
    with pytest.raises(ValueError, match="layout must be one of"):
        lens_camera(ml_layout="hex")
    doc = cam.to_dict()
    doc["microlens_array"]["layout"] = "axial"  # the projector's view, never a file's
    with pytest.raises(ValueError, match="layout must be one of"):
        Camera.from_dict(doc)
    with pytest.raises(ValueError, match="odd_row_shift must be one of"):
        lens_camera(ml_odd_row_shift=0.5)
    with pytest.raises(ValueError, match="odd_row_shift must be one of"):
        hex_camera(ml_odd_row_shift=0.25)


def test_cell_points_fill_the_hexagon_uniformly():
    cam = hex_camera()
    rng = np.random.default_rng(1)
    a, b = _cell_points(cam, rng.random(400_000), rng.random(400_000))
    p = cam.ml_pitch_mm
    # inside the pointy-top hexagon: |a| <= p/2 and |b| <= (p - |a|)/sqrt(3)
    assert np.abs(a).max() <= p / 2 + 1e-12
    assert (np.abs(b) <= (p - np.abs(a)) / np.sqrt(3) + 1e-12).all()
    # uniform: each of the hexagon's 6 triangles and its inner circle hold their area's share
    sector = np.floor((np.degrees(np.arctan2(b, a)) + 360) % 360 / 60)
    assert np.bincount(sector.astype(int), minlength=6) / len(a) == pytest.approx(
        np.full(6, 1 / 6), abs=0.003)
    inner = np.pi * (p / 2) ** 2 / (p * p * ROW)  # the inscribed circle's share of the area
    assert np.mean(np.hypot(a, b) < p / 2) == pytest.approx(inner, abs=0.003)


def test_kernel_matches_reference_ray_for_ray(queue):
    cam = hex_camera(ml_rotation_deg=1.5, ml_offset_mm=(0.01, -0.02))
    pos = np.array([[0.1, 0.05, 0.0], [-0.3, 0.2, 1.5], [0.2, -0.1, -2.0], [0.6, 0.4, 0.7]])
    inten = np.array([1000.0, 500.0, 2000.0, 750.0])
    a = Simulator(cam, queue).trace(pos, inten, 7001, seed=11, blur_px=0.5)
    b = reference.trace_particles(cam, pos, inten, 7001, seed=11, blur_px=0.5)
    assert a.sum() == pytest.approx(b.sum(), rel=1e-5)
    # only rays within float32 rounding of a cell edge may move: a handful of pixels
    assert np.count_nonzero(np.abs(a - b) > 1e-3) <= 10


def test_white_images_match_the_reference(queue):
    cam = hex_camera(ml_odd_row_shift=-0.5)
    for stop in (16.0, cam.f_number):  # stopped down, and at full aperture
        img = simulate_white_image(cam, stop_f_number=stop, rays_per_lens=800, seed=3,
                                   queue=queue)
        ref = reference.trace_white(cam, stop, 800, 3, 1000.0, 0.8)
        assert np.corrcoef(img.ravel(), ref.ravel())[0, 1] > 0.9999


def _nearest_centre_trace(cam: Camera, point, rays: int, seed: int) -> np.ndarray:
    """Independent exact trace: aperture point, thin main lens, the array plane, the lens
    whose centre is nearest (a k-d tree over the array's centres), the sensor."""
    rng = np.random.default_rng(seed)
    r = cam.aperture_diameter_mm / 2 * np.sqrt(rng.random(rays))
    t = 2 * np.pi * rng.random(rays)
    ap = np.stack([r * np.cos(t), r * np.sin(t)], -1)
    s_o = cam.object_distance_mm + point[2]
    slope = (ap - np.asarray(point[:2])) / s_o - ap / cam.focal_length_mm
    mla = ap + slope * cam.image_distance_mm
    centres = cam.microlens_positions_mm().reshape(-1, 2)
    dist, k = cKDTree(centres).query(mla)
    # a ray beyond the array's outer cells is lost (a cell is at most p/sqrt(3) round)
    ok = dist <= cam.ml_pitch_mm / np.sqrt(3)
    sensor = centres[k] + slope * cam.ml_focal_length_mm
    px = np.floor(sensor / cam.pixel_pitch_mm + np.array(cam.pixels) / 2).astype(int)
    ok &= np.all((px >= 0) & (px < np.array(cam.pixels)), axis=1)
    img = np.zeros(cam.pixels[::-1])
    np.add.at(img, (px[ok, 1], px[ok, 0]), 1.0 / rays)
    return img


@pytest.mark.parametrize("z", [-2.5, 0.0, 1.0])
def test_particle_rays_enter_the_lens_whose_centre_is_nearest(queue, z):
    cam = hex_camera(ml_rotation_deg=2.0)
    point = np.array([0.17, -0.09, z])
    img, again = (simulate_image(cam, point[None], 3e5, 300_000, seed=s, queue=queue) / 3e5
                  for s in (5, 7))
    ref = _nearest_centre_trace(cam, point, 300_000, seed=6)
    assert img.sum() == pytest.approx(ref.sum(), abs=0.01)
    # the light placed differently: no more than between two seeds of the simulator
    assert np.abs(img - ref).sum() < 1.1 * np.abs(img - again).sum()  # 0.031-0.039


# ---- calibration ------------------------------------------------------------------------
def sensor_camera(cols: int = 20, rows: int = 18, **changes) -> Camera:
    """A hexagonal camera whose sensor the array fills as a real one does: the even rows'
    outer centres half a pitch inside its edges."""
    return lens_camera(cols, rows, (int(16.98 * cols) + 1, int(16.98 * rows * ROW) + 1),
                       ml_layout="hexagonal", **changes)


def nominal(cam: Camera) -> Camera:
    """What the user knows: the camera file without the array's rotation and offset."""
    return dataclasses.replace(cam, ml_rotation_deg=0.0, ml_offset_mm=(0.0, 0.0),
                               microlens_centers=None)


def centre_errors(fit, truth, cam: Camera) -> tuple[float, float]:
    """Share of the lenses whose true centre lies on the sensor that were found, and the
    RMS distance (px) of the found centres from the truth."""
    err = np.hypot(*(fit.centers - truth).transpose(2, 0, 1))
    on = ((truth >= 0) & (truth <= np.array(cam.pixels) - 1)).all(-1)
    return float(np.isfinite(err[on]).mean()), float(np.sqrt(np.nanmean(err**2)))


HEX_CASES = {  # name: (the true array, the white image)
    "clean": (dict(), dict()),
    "rotated+2-shifted-noisy": (dict(ml_rotation_deg=2.0, ml_offset_mm=(0.04, -0.03)),
                                dict(photon_noise=True, read_noise=2.0, bit_depth=12)),
    "odd-rows-left-rotated-1": (dict(ml_odd_row_shift=-0.5, ml_rotation_deg=-1.0),
                                dict(photon_noise=True)),
}


@pytest.mark.parametrize("case", HEX_CASES)
def test_stopped_down_hexagonal_white_images_are_calibrated(queue, case):
    """Every lens found, its centre within 0.05 px RMS of the truth (0.004-0.006 px), and
    the array's rotation measured."""
    layout, image = HEX_CASES[case]
    cam = sensor_camera(**layout)
    white = simulate_white_image(cam, seed=3, queue=queue, **image)
    fit = find_centers(white, nominal(cam))
    found, rms = centre_errors(fit, cam.ideal_microlens_centers(), cam)
    assert found == 1.0 and rms <= 0.05
    assert fit.rotation_deg == pytest.approx(cam.ml_rotation_deg, abs=0.01)


def test_hexagonal_lenses_off_the_lattice_keep_their_offsets(queue):
    """Small spots (f/16, 0.3 px blur), 12-bit, noise, lenses 0.1 px (per axis) off the
    lattice: the combined centres keep the offsets (0.029 px RMS; the lattice model alone
    is off by the lenses' scatter)."""
    cam = sensor_camera(ml_rotation_deg=0.3)
    rng = np.random.default_rng(4)
    per_px = centre_shift_px(cam, np.ones(2))[0]
    shift = rng.normal(0.0, 0.1 / per_px, (*cam.ml_count[::-1], 2))
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    white = simulate_white_image(cam, blur_px=0.3, photon_noise=True, read_noise=3.0,
                                 bit_depth=12, intensity=1e4, rays_per_lens=20000, seed=17,
                                 lens_shift_mm=shift, queue=queue)
    found, rms = centre_errors(find_centers(white, nominal(cam)), truth, cam)
    model = centre_errors(find_centers(white, nominal(cam), method="fit"), truth, cam)[1]
    assert found == 1.0 and rms <= 0.05 and rms < 0.5 * model


def test_full_aperture_hexagonal_white_images_are_calibrated(queue):
    """Disks filling their (hexagonal) lenses at the main lens's own f-number, rotated,
    50 % vignetting falloff across the sensor, photon and read noise: recognised, at
    least 97 % of the lenses on the sensor found, within 0.05 px RMS."""
    cam = sensor_camera(ml_rotation_deg=1.0, ml_offset_mm=(0.02, 0.01))
    white = vendor_white_image(cam, queue)
    fit = find_centers(white, nominal(cam))
    found, rms = centre_errors(fit, cam.ideal_microlens_centers(), cam)
    assert fit.aperture == "full" and found >= 0.97 and rms <= 0.05


def test_a_wrong_hexagonal_count_or_stagger_is_refused(queue):
    cam = sensor_camera()
    white = simulate_white_image(cam, seed=3, queue=queue)
    with pytest.raises(ValueError, match="20 x 18 microlens images .* has 20 x 17"):
        find_centers(white, dataclasses.replace(nominal(cam), ml_count=(20, 17),
                                                microlens_centers=None))
    with pytest.raises(ValueError, match="set \\[microlens_array\\] odd_row_shift = 0.5"):
        find_centers(white, dataclasses.replace(nominal(cam), ml_odd_row_shift=-0.5,
                                                microlens_centers=None))


def test_every_stage_takes_a_hexagonal_camera(queue):
    """Every stage takes a hexagonal camera: the light field and the pixels' lens cells
    (tests/test_hex_lightfield.py) and the image fit's ray bundle, which takes the axial
    view (the projector's camera, which ``process_pair`` gives the fit) as that camera:
    the same hexagonal cells (``tests/test_hex_imagefit.py``), not the view's rhombic
    ones. The light field refuses the axial view, and the view is never a camera file."""
    from plenocl import LightField
    from plenocl.optics.ownership import lens_owner
    from plenocl.optics.raybundle import RayBundle

    cam = sensor_camera(8, 8)
    with pytest.raises(ValueError, match="the hexagonal camera itself, not its axial view"):
        LightField(np.ones(cam.pixels[::-1]), cam.on_lens_lattice(), queue=queue)
    assert (lens_owner(cam) >= 0).mean() > 0.9
    lf = LightField(np.ones(cam.pixels[::-1]), cam.with_centers(cam.ideal_microlens_centers()),
                    queue=queue)
    assert lf.shape == (8, 8) and np.nanmax(np.abs(lf.views - 1)) < 1e-6
    own, view = RayBundle.of(cam), RayBundle.of(cam.on_lens_lattice())
    assert own.cells is not None and view.cells is not None
    np.testing.assert_array_equal(own.cells.model, view.cells.model)
    np.testing.assert_array_equal(own.lenses, view.lenses)
    with pytest.raises(ValueError, match="axial view .* not a camera file"):
        cam.on_lens_lattice().to_dict()


# ---- reconstruction ---------------------------------------------------------------------
def _matches_reference(cam: Camera, grid, proj) -> None:
    """``proj`` agrees with the NumPy reference voxel by voxel, sends no voxel more light
    than it has, and is adjoint."""
    from helpers import assert_adjoint, assert_close_to_peak
    from tolerances import FOOTPRINT_TOTAL, WEIGHTS

    from plenocl.reference.weights import voxel_weights

    n = cam.pixels[0] * cam.pixels[1]
    for vox in [(2, 3, 4), (0, 5, 1), (4, 1, 7), (2, 0, 0), (4, 6, 8)]:
        ref = np.zeros(n)
        idx, w = voxel_weights(cam, grid, *vox)
        ref[idx] = w
        onehot = np.zeros(grid.shape, np.float32)
        onehot[vox] = 1.0
        fwd = proj.forward(onehot).ravel()
        assert_close_to_peak(fwd, ref, WEIGHTS, vox)
        np.testing.assert_allclose(fwd.sum(), ref.sum(), rtol=FOOTPRINT_TOTAL)
        assert fwd.sum() <= 1.0 + 1e-5
    assert_adjoint(proj)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_a_hexagonal_array_projects_separably_in_its_rows_frame(queue, shift):
    """A hexagonal camera projects through its axial view (the lenses on the leaning
    lattice ``q e1 + r e2``, NaN where the parallelogram has no lens). On a grid along
    its rows (here turned 1°) the lens map is triangular and the aperture is sampled
    along the lattice's two steps, so the separable kernels apply (docs/design.md §5.3):
    they agree with the NumPy reference voxel by voxel, are adjoint, and send no voxel
    more light than it has."""
    from plenocl import Grid, Projector

    cam = sensor_camera(12, 12, ml_rotation_deg=1.0, ml_odd_row_shift=shift)
    cam = cam.with_centers(cam.ideal_microlens_centers())
    grid = Grid((5, 7, 9), x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-4.0, 4.0), rotation_deg=1.0)
    proj = Projector(cam, grid, queue)
    assert proj.path == "separable" and proj.camera.ml_layout == "axial"
    # 12 + 5 columns of padding across 12 rows (6 for -0.5: the view always steps by
    # (+1/2, √3/2) from row to row, camera.lattice.view_lean)
    assert proj.camera.ml_count == (17 + (shift < 0), 12)
    assert proj.aperture.shear == pytest.approx(0.5)
    assert proj.aperture.squeeze == pytest.approx(ROW)
    _matches_reference(cam, grid, proj)


def test_the_rhombic_aperture_grid_samples_the_disc_along_the_lattice():
    """The aperture of a hexagonal lattice (:meth:`ApertureGrid.for_lattice`): exactly
    the rhombic lattice points inside the circle, each column contiguous, its ranges
    those of the samples (asymmetric), the outermost columns or rows holding samples,
    one sample per ``t step²`` of the aperture."""
    from plenocl.projection.weighting import ApertureGrid

    cam = sensor_camera(12, 12)
    for shift in (0.5, -0.5):
        ap = ApertureGrid.for_lattice(cam, 1.25, 0.0, shift, ROW)
        i, j = ap.samples()
        a, b = i - ap.center, j - ap.center
        uv = ap.frame_uv()
        np.testing.assert_allclose(uv, np.column_stack([a + shift * b, ROW * b]) * ap.step)
        assert np.all((uv**2).sum(1) <= ap.radius**2)
        k = np.arange(-ap.n, ap.n + 1)  # every lattice point near the disc, not only n x n
        aa, bb = np.meshgrid(k, k, indexing="ij")
        inside = ((aa + shift * bb) ** 2 + (ROW * bb) ** 2) * ap.step**2 <= ap.radius**2
        assert inside.sum() == len(i)
        lo, hi = ap.column_ranges()
        assert np.array_equal(np.repeat(np.arange(ap.n), hi - lo + 1), i)
        assert np.array_equal(j, np.concatenate([np.arange(x, y + 1) for x, y in zip(lo, hi)]))
        outer = (hi[0] >= lo[0]) or np.any(j == 0)  # the grid is no wider than the disc
        assert outer and np.any(lo + hi != ap.n - 1)
        area = np.pi * ap.radius**2 / (ROW * ap.step**2)
        assert abs(len(i) - area) < 0.05 * area


def test_the_aperture_lattice_refuses_bad_steps_and_a_foreign_lens_map():
    """A rhombic aperture grid needs a finite shear and a positive squeeze, and the depth
    coefficients refuse one built for another lens map (its ``H`` would not be
    diagonal: silently zeroing the term would give wrong weights)."""
    from plenocl import Grid
    from plenocl.projection.weighting import ApertureGrid, depth_coefficients, lens_index_map

    cam = sensor_camera(12, 12)
    for shear, squeeze in ((0.5, 0.0), (0.5, -1.0), (float("nan"), ROW), (0.5, float("inf"))):
        with pytest.raises(ValueError, match="finite shear and a positive squeeze"):
            ApertureGrid.for_lattice(cam, 1.25, 0.0, shear, squeeze)
    grid = Grid((5, 7, 9), x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-4.0, 4.0))
    lens_map = lens_index_map(cam)
    foreign = ApertureGrid.for_lattice(cam, 1.25, 0.0, -0.5, ROW)  # the other stagger
    assert lens_map.aperture_lattice()[0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="does not belong to this lens map"):
        depth_coefficients(cam.on_lens_lattice(), grid, lens_map, foreign)


def test_hexagonal_projector_variants_agree(queue):
    """On the rhombic aperture's asymmetric columns, the GPU-style layout (one element
    per work-item, per-column lens-row stage), the element forms of the lens-column
    stage, the light field split into many column chunks, and the unfactorised kernels
    all give the default's projection."""
    from test_stress import _scratch_for_chunks

    from plenocl import Grid, Projector

    cam = sensor_camera(12, 12, ml_rotation_deg=1.0)
    cam = cam.with_centers(cam.ideal_microlens_centers())
    grid = Grid((5, 7, 9), x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-4.0, 4.0), rotation_deg=1.0)
    rng = np.random.default_rng(4)
    vol = rng.random(grid.shape).astype(np.float32)
    ref = Projector(cam, grid, queue)
    img = rng.random(ref.image_shape).astype(np.float32)
    others = [Projector(cam, grid, queue, vector_width=1, segment=1),
              Projector(cam, grid, queue, gather_forward=True),
              Projector(cam, grid, queue, scratch_bytes=_scratch_for_chunks(ref, 1.0)),
              Projector(cam, grid, queue, method="direct")]
    assert len(others[2].plan.columns) > 3
    close = dict(rtol=1e-5, atol=1e-6)
    for other in others:
        np.testing.assert_allclose(other.forward(vol), ref.forward(vol), **close)
        np.testing.assert_allclose(other.back(img), ref.back(img), **close)


def test_a_hexagonal_array_across_a_sensor_axis_grid(queue):
    """A grid in the sensor's axes across a 1° hexagonal array is projected through its
    rows' frame and resampled (as a rotated rectangular array, docs/design.md §5.1);
    ``general="exact"`` keeps the general kernels, which agree with the reference."""
    from plenocl import Grid, Projector

    cam = sensor_camera(12, 12, ml_rotation_deg=1.0)
    cam = cam.with_centers(cam.ideal_microlens_centers())
    grid = Grid((5, 7, 9), x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-4.0, 4.0))
    assert Projector(cam, grid, queue).path == "resampled"
    exact = Projector(cam, grid, queue, general="exact")
    assert exact.path == "general" and exact.aperture.shear == 0
    _matches_reference(cam, grid, exact)


def _particle_errors(cam: Camera, queue, seed: int) -> tuple[np.ndarray, int]:
    """Per matched particle (x, y, z) errors (voxels) of ``reconstruct()``'s default on
    12 ray-traced particles (1 px blur, photon noise), and how many were matched."""
    from plenocl import Grid, Projector
    from plenocl.metrics import matched_errors
    from plenocl.reconstruction import reconstruct

    grid = Grid((32, 24, 24), x=(-1.5, 1.5), y=(-1.5, 1.5), z=(-2.0, 2.0))
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-1.0, 1.0, (12, 2)), rng.uniform(-1.6, 1.6, 12)])
    img = simulate_image(cam, pos, np.full(12, 2e4), 20000, seed=3, blur_px=1.0,
                         photon_noise=True, queue=queue)
    d = matched_errors(reconstruct(img, Projector(cam, grid, queue)), grid, pos,
                       lateral=1.5, depth=4.0)
    return d, len(d)


def test_hexagonal_particles_reconstruct_as_rectangular_ones_do(queue):
    """Particles ray traced through exact hexagonal cells (24 x 28 lenses) reconstruct
    through the axial view about as well as through a rectangular array of 24 x 24
    lenses of the same pitch on the same grid (two scenes: lateral 0.10 / depth 0.97
    voxel, 22 of 24, against 0.10 / 1.33, 23 of 24)."""
    hexagonal = sensor_camera(24, 28)
    rectangular = lens_camera(24, 24)
    stats = {}
    for name, cam in (("hex", hexagonal), ("rect", rectangular)):
        runs = [_particle_errors(cam.with_centers(cam.ideal_microlens_centers()), queue, s)
                for s in (11, 12)]
        d = np.vstack([r[0] for r in runs])
        stats[name] = (np.sqrt(np.mean(d[:, :2] ** 2)), np.sqrt(np.mean(d[:, 2] ** 2)),
                       sum(r[1] for r in runs))
    print(stats)
    assert stats["hex"][0] <= 0.15 and stats["hex"][1] <= 1.1 * stats["rect"][1]
    assert stats["hex"][2] >= 20


def test_hexagonal_centres_travel_as_csv(tmp_path, queue):
    """A hexagonal camera calibrated from its white image writes its centres as a
    centres CSV (lens column and row, the (rows, cols) of ``microlens_centers``) and an
    import gives the same camera, to the last bit."""
    from plenocl.calibration import calibrate, import_centers
    from plenocl.io.centres import write_centers_csv

    cam = sensor_camera(ml_rotation_deg=0.5)
    calibrated = calibrate(simulate_white_image(cam, seed=5, queue=queue), nominal(cam))
    write_centers_csv(tmp_path / "c.csv", calibrated.microlens_centers)
    back = import_centers(tmp_path / "c.csv", nominal(cam))
    np.testing.assert_array_equal(back.microlens_centers, calibrated.microlens_centers)
    assert back.ml_layout == "hexagonal"


def test_large_hexagonal_disks_are_calibrated_to_the_sensors_edge(queue):
    """A vendor-style image of few large lenses (65 px, 720 x 720 px, 11 x 12 hexagonal
    lenses) at full aperture: the disks at the array's edge, with neighbours on one side
    only, are left out of the grid model (their centroids were 2-4 px off), the lenses
    whose centre lies on the sensor are all found, those whose disk the edge cuts from
    the model, within 0.05 px RMS (0.012); a dead lens stays missing."""
    pitch_px = 65.0
    cam = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (11, 12), 0.125 * 1.005 / pitch_px, (720, 720),
                 ml_layout="hexagonal")
    dead = np.zeros((12, 11), bool)
    dead[5, 4] = True
    white = simulate_white_image(cam, stop_f_number=cam.f_number, photon_noise=True,
                                 intensity=1e5, rays_per_lens=200_000, missing=dead, seed=2,
                                 queue=queue)
    fit = find_centers(white, cam)
    truth = cam.ideal_microlens_centers()
    found, rms = centre_errors(fit, truth, cam)
    assert fit.aperture == "full" and rms <= 0.05
    assert np.array_equal(~fit.found, dead) and found == pytest.approx(131 / 132)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_an_array_that_overfills_the_sensor_takes_either_odd_row_shift(queue, shift):
    """A hexagonal array larger than the sensor, cut with 0.7 pitch of array beyond the
    even rows' outer centres on both sides: its odd rows show one lens more than the
    count, so either labelling holds (the lens beyond the count is not used); every
    centre found lies on a true one (0.05 px)."""
    big = sensor_camera(30, 30)
    white = simulate_white_image(big, seed=6, queue=queue)
    truth = big.ideal_microlens_centers().reshape(-1, 2)
    p, row = 16.98, 16.98 * ROW
    c0 = int(np.ceil(truth[:, 0].min() + 5.3 * p))  # 0.7 pitch before lens 6 of row 0
    r0 = int(np.ceil(truth[:, 1].min() + 5.3 * row))
    width, height = int(17 * p + 1.4 * p), int(15 * row + 1.4 * row)
    crop = white[r0:r0 + height, c0:c0 + width]
    cam = lens_camera(18, 16, (width, height), ml_layout="hexagonal",
                      ml_odd_row_shift=shift)
    fit = find_centers(crop, cam)
    found = fit.centers[fit.found]
    near, _ = cKDTree(truth - [c0, r0]).query(found)
    assert fit.found[0::2].all() and np.sqrt(np.mean(near**2)) < 0.05


def test_lfit_calibration_files_are_read(tmp_path, queue):
    """LFIT's ``*_calData.mat`` (the cell array calData: centres rows x columns x (x, y),
    1-based pixels, then the centre lists and the counts) imports as its centres less
    one pixel, a lens LFIT left at 0 missing; another lens count is refused naming both."""
    from scipy.io import savemat

    from plenocl.calibration import import_centers

    cam = sensor_camera(12, 10)
    truth = cam.ideal_microlens_centers()
    points = truth + 1.0
    points[3, 4] = 0.0
    cal = np.empty((1, 5), dtype=object)
    cal[0, :] = [points, points[..., 0].ravel(), points[..., 1].ravel(), 12.0, 10.0]
    savemat(tmp_path / "run_calData.mat", {"calData": cal})
    with pytest.warns(UserWarning, match="1 of 120 microlenses have no centre"):
        back = import_centers(tmp_path / "run_calData.mat", nominal(cam))
    missing = np.zeros((10, 12), bool)
    missing[3, 4] = True
    assert np.array_equal(~np.isfinite(back.microlens_centers).all(-1), missing)
    np.testing.assert_allclose(back.microlens_centers[~missing], truth[~missing], atol=1e-12)
    with pytest.raises(ValueError, match="holds 12 x 10 lens centres .* camera file has 12 x 9"):
        import_centers(tmp_path / "run_calData.mat",
                       dataclasses.replace(nominal(cam), ml_count=(12, 9),
                                           microlens_centers=None))


@pytest.mark.parametrize("method", ["factorised", "direct"])
def test_one_array_numbered_from_either_row_projects_alike(queue, method):
    """The same lenses numbered from another row (a row fewer, so the other odd-row
    shift, as a region of interest that starts on an odd row is) give one projection
    (float32 rounding) on the pixels of the lenses both hold: the axial view's rhombus
    leans one way whatever the numbering. Before, 5.6-30 % of the peak apart."""
    from plenocl import Grid, Projector

    a = lens_camera(20, 16, (349, 251), ml_layout="hexagonal")
    b = lens_camera(20, 15, (349, 251), ml_layout="hexagonal", ml_odd_row_shift=-0.5,
                    ml_offset_mm=(0.125 / 2, 0.125 * ROW / 2))
    np.testing.assert_allclose(a.ideal_microlens_centers()[1:], b.ideal_microlens_centers(),
                               atol=1e-9)
    grid = Grid((5, 8, 8), (-0.4, 0.4), (-0.4, 0.4), (-0.8, 0.8))
    vol = np.random.default_rng(3).random(grid.shape).astype(np.float32)
    pa, pb = (Projector(c, grid, queue, method=method).forward(vol) for c in (a, b))
    rows = slice(40, None)  # away from the row A holds and B does not
    np.testing.assert_allclose(pb[rows], pa[rows], atol=2e-6 * pa.max())
