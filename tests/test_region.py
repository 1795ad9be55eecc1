"""A region of interest of the sensor (plenocl.camera.region, Camera.cropped): the lenses
in it where they stand on the whole array, and the optical axis where it crosses the
whole sensor, so that everything seen through an off-centre region is the whole frame's:
pixels, simulated images, projections, grids, reconstructed particles."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import ROTATED, lens_camera
from scipy.spatial import cKDTree

from plenocl import Camera, Grid, Projector, calibrate, reconstruct, simulate_image
from plenocl import simulate_white_image as white_image
from plenocl.peaks import find_particles

ROW = np.sqrt(3) / 2


def _cut(image: np.ndarray, origin, size) -> np.ndarray:
    return image[origin[1]:origin[1] + size[1], origin[0]:origin[0] + size[0]]


def _inside(centres: np.ndarray, origin, size) -> np.ndarray:
    """The lens centres (whole-frame px) that lie in the region (its pixels' edges)."""
    lo = np.asarray(origin) - 0.5
    return ((centres >= lo) & (centres <= lo + size)).all(-1)


CASES = {
    "rectangular": (lens_camera(20, 16), (87, 40), (170, 153)),
    "rotated": (lens_camera(20, 16, **ROTATED), (120, 30), (160, 200)),
    "hexagonal-even-row": (lens_camera(20, 16, (349, 251), ml_layout="hexagonal"),
                           (60, 35), (200, 150)),
    "hexagonal-odd-row": (lens_camera(20, 16, (349, 251), ml_layout="hexagonal"),
                          (60, 20), (200, 150)),
}


@pytest.mark.parametrize("name", CASES)
def test_a_region_keeps_its_lenses_where_they_stand(name):
    """Every lens of the region is a lens of the whole array at the same sensor position
    (1e-9 px), and, for an unturned array, exactly those whose image centre lies in the
    region (a hexagonal region starting on an odd row flips its odd-row shift)."""
    whole, origin, size = CASES[name]
    region = whole.cropped(origin, size)
    mine = region.ideal_microlens_centers().reshape(-1, 2) + origin
    theirs = whole.ideal_microlens_centers().reshape(-1, 2)
    assert cKDTree(theirs).query(mine)[0].max() < 1e-9
    if name != "rotated":
        assert len(mine) == _inside(theirs, origin, size).sum()
    if name == "hexagonal-odd-row":
        assert region.odd_row_shift == -whole.odd_row_shift
    assert region.full_pixels == whole.pixels and region.crop_origin == origin


def test_positions_through_a_region_are_the_whole_frames():
    """A region's pixel is the whole sensor's pixel ``origin`` further on, in sensor mm
    both ways; a region cut from a region keeps the whole sensor's axis; the point at the
    focal plane its centre sees (``field_centre_mm``) images at its centre; the whole
    sensor's region is the camera itself, with the region recorded."""
    whole, origin, size = CASES["rectangular"]
    region = whole.cropped(origin, size)
    px = np.array([[0.0, 0.0], [13.25, 101.5], [169.0, 152.0]])
    np.testing.assert_allclose(region.px_to_mm(px), whole.px_to_mm(px + origin), atol=1e-12)
    np.testing.assert_allclose(region.mm_to_px(region.px_to_mm(px)), px, atol=1e-9)
    inner = region.cropped((10, 20), (120, 100))
    np.testing.assert_allclose(inner.px_to_mm(px), whole.px_to_mm(px + origin + [10, 20]),
                               atol=1e-12)
    centre = np.append(region.field_centre_mm(), 0.0)
    image = region.image_points(centre[None])[0, :2] * region.lens_image_scale
    np.testing.assert_allclose(region.mm_to_px(image), (np.array(size) - 1) / 2, atol=1e-9)
    same = whole.cropped((0, 0), whole.pixels)
    assert same.ml_count == whole.ml_count and same.ml_offset_mm == whole.ml_offset_mm
    np.testing.assert_array_equal(same.ideal_microlens_centers(),
                                  whole.ideal_microlens_centers())
    assert same.crop_origin == (0, 0) and np.all(same.field_centre_mm() == 0)


def test_a_region_is_written_and_read_with_its_whole_sensor(tmp_path):
    """The camera file keeps ``crop_origin`` and ``full_pixels``; a file of a region
    without the whole sensor's size (written before them) warns that positions shift."""
    whole, origin, size = CASES["hexagonal-odd-row"]
    region = whole.cropped(origin, size)
    region.to_toml(tmp_path / "region.toml")
    back = Camera.from_toml(tmp_path / "region.toml")
    assert (back.full_pixels, back.crop_origin, back.ml_count) == (
        region.full_pixels, region.crop_origin, region.ml_count)
    np.testing.assert_allclose(back.ideal_microlens_centers(),
                               region.ideal_microlens_centers(), atol=1e-9)
    doc = region.to_dict()
    del doc["sensor"]["full_pixels"]
    with pytest.warns(UserWarning, match="not the whole sensor's size"):
        Camera.from_dict(doc)


@pytest.mark.parametrize("name", ["rectangular", "hexagonal-odd-row"])
def test_a_simulated_region_is_the_cut_of_the_whole_frame(queue, name):
    """The simulator traces the same rays onto the region's pixels: its image equals the
    whole frame's cut to the region, away from the lenses the region cuts off (their
    light spills a lens image into it)."""
    whole, origin, size = CASES[name]
    region = whole.cropped(origin, size)
    pos = np.array([[-0.3, 0.1, 0.4], [0.2, -0.2, -0.6], [0.05, 0.3, 0.0]])
    pos[:, :2] += region.field_centre_mm()
    full = _cut(simulate_image(whole, pos, 1e4, 4000, queue=queue), origin, size)
    mine = simulate_image(region, pos, 1e4, 4000, queue=queue)
    m = 2 * int(np.ceil(whole.pixels_per_microlens))
    inner = (slice(m, -m), slice(m, -m))
    assert full[inner].sum() > 0.5 * full.sum() > 0
    assert np.abs(mine[inner] - full[inner]).max() <= 1e-3 * full.max()


@pytest.mark.parametrize("name", ["rotated", "hexagonal-even-row", "hexagonal-odd-row"])
def test_a_projection_through_a_region_is_the_cut_of_the_whole_frames(queue, name):
    """The projector of the region's camera gives the whole frame's projection cut to the
    region (float32 rounding), away from the lenses cut off: a hexagonal region that
    starts on an odd row, numbered with the other odd-row shift, too (the axial view
    leans one way whatever the numbering, ``camera.lattice.view_lean``)."""
    whole, origin, size = CASES[name]
    region = whole.cropped(origin, size)
    c = region.field_centre_mm()
    grid = Grid((5, 8, 8), (c[0] - 0.4, c[0] + 0.4), (c[1] - 0.4, c[1] + 0.4), (-0.8, 0.8))
    vol = np.random.default_rng(1).random(grid.shape).astype(np.float32)
    full = _cut(Projector(whole, grid, queue).forward(vol), origin, size)
    mine = Projector(region, grid, queue).forward(vol)
    m = 2 * int(np.ceil(whole.pixels_per_microlens))
    inner = (slice(m, -m), slice(m, -m))
    assert full[inner].max() > 0
    np.testing.assert_allclose(mine[inner], full[inner], atol=2e-5 * full.max(), rtol=1e-4)


def test_particles_seen_through_an_off_centre_region_are_where_they_are(queue):
    """The audit's scene (0.47-0.50 mm off before): a 30 x 20-lens camera, a region of
    its right two thirds (its centre 85 px right of the sensor's: 0.63 mm at M = 1)
    calibrated from its cut of the white image and reconstructed on the grid
    ``Grid.for_camera`` centres on what the region sees: particles found within 0.05 mm
    laterally of where they are (median), most of them found."""
    whole = lens_camera(30, 20)
    origin, size = (170, 0), (340, 340)
    truth = np.column_stack([np.random.default_rng(5).uniform(-1.6, 0.3, 25),
                             np.random.default_rng(6).uniform(-1.0, 1.0, 25),
                             np.random.default_rng(7).uniform(-1.0, 1.0, 25)])
    raw = simulate_image(whole, truth, 2e4, 3000, blur_px=0.8, background=5.0,
                         photon_noise=True, queue=queue)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a region's white image cut at its edges
        region = calibrate(_cut(white_image(whole, queue=queue), origin, size),
                           whole.cropped(origin, size))
    grid = Grid.for_camera(region, z=(-1.5, 1.5))
    offset = 85 * whole.pixel_pitch_mm / whole.lens_image_scale  # the region's centre
    assert np.mean(grid.x) == pytest.approx(-offset) and np.mean(grid.y) == pytest.approx(0)
    vol = reconstruct(_cut(raw, origin, size), Projector(region, grid, queue))
    found = grid.from_index(find_particles(vol, threshold=0.2)[0])
    dist, near = cKDTree(found).query(truth)
    hit = dist < 0.3
    assert hit.mean() >= 0.8
    lateral = np.median(found[near[hit], :2] - truth[hit, :2], axis=0)
    assert np.abs(lateral).max() < 0.05


@pytest.mark.parametrize("layout", ["rectangular", "hexagonal"])
def test_a_regions_lens_count_follows_its_white_image(queue, layout):
    """The region's lenses are counted on the nominal layout; where the real array sits
    off it (0.45 pitch here), the white image shows another count, or a hexagonal
    array's other row first: calibration takes what the image shows, and every centre
    lands on a true one (0.1 px). A whole sensor's camera file that disagrees with its
    image is still refused."""
    if layout == "hexagonal":
        nominal = lens_camera(20, 16, (349, 251), ml_layout="hexagonal")
        true = lens_camera(20, 16, (349, 251), ml_layout="hexagonal",
                           ml_offset_mm=(0.056, 0.05))
    else:
        nominal = lens_camera(20, 16)
        true = lens_camera(20, 16, ml_offset_mm=(0.056, 0.056))
    origin, size = (60, 30), (200, 150)
    white = white_image(true, queue=queue)
    region = nominal.cropped(origin, size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(_cut(white, origin, size), region)
    truth = true.ideal_microlens_centers().reshape(-1, 2)
    seen = _inside(truth, origin, size)
    if layout == "rectangular":
        assert cal.ml_count != region.ml_count
        assert np.prod(cal.ml_count) == seen.sum()
    centres = cal.microlens_centers.reshape(-1, 2)
    ok = np.isfinite(centres).all(1)
    assert ok.mean() > 0.9
    assert cKDTree(truth[seen] - origin).query(centres[ok])[0].max() < 0.1
    # the nominal array moved onto the measured one (the simulator's, the depth range's)
    nominal = cal.ideal_microlens_centers().reshape(-1, 2)
    assert np.abs(nominal[ok] - centres[ok]).max() < 0.1
    with pytest.raises(ValueError, match="correct \\[microlens_array\\] count"):
        calibrate(white, lens_camera(19, 16, (340, 272)) if layout == "rectangular" else
                  lens_camera(19, 16, (349, 251), ml_layout="hexagonal"))


def test_frames_are_cut_to_the_region():
    """A whole frame is cut to the region; the region itself passes as it is; a frame
    that does not hold the region, or an outer region's frame, is refused naming the
    whole sensor."""
    whole, origin, size = CASES["rectangular"]
    region = whole.cropped(origin, size)
    frame = np.arange(whole.pixels[0] * whole.pixels[1], dtype=float).reshape(
        whole.pixels[1], whole.pixels[0])
    np.testing.assert_array_equal(region.fit_image(frame), _cut(frame, origin, size))
    np.testing.assert_array_equal(region.fit_image(_cut(frame, origin, size)),
                                  _cut(frame, origin, size))
    with pytest.raises(ValueError, match=r"of the whole 340 x 272 sensor"):
        region.fit_image(frame[:, :origin[0] + size[0] - 1])
    # the frame of an outer region, given to a region cut from it: cut at the combined
    # origin it would be the wrong pixels, so it is refused
    inner = region.cropped((10, 20), (100, 80))
    with pytest.raises(ValueError, match=r"of the whole 340 x 272 sensor"):
        inner.fit_image(_cut(frame, origin, size))
    np.testing.assert_array_equal(inner.fit_image(frame),
                                  _cut(frame, (origin[0] + 10, origin[1] + 20), (100, 80)))


def test_a_region_off_the_axis_resolves_the_depths_of_one_on_it():
    """The depth range's light criterion centres a particle's blur disc on what the
    region's centre sees, not on the axis: a region that holds no lens on the axis (the
    right half) resolves the depths a region of its size centred on the axis does (it
    resolved none before), and its grid is made and checked."""
    from plenocl.optics import resolved_depth_range

    whole = lens_camera(30, 20)
    right, middle = whole.cropped((255, 0), (255, 340)), whole.cropped((127, 0), (255, 340))
    assert right.ml_count == middle.ml_count
    near, far = resolved_depth_range(right)
    assert (near, far) == pytest.approx(resolved_depth_range(middle), abs=1e-9)
    assert near < -5 and far > 5
    grid = Grid.for_camera(right, z=(-2.0, 2.0))
    assert grid.x[1] < 0 < -grid.x[0]  # the right half of the sensor sees x < 0


def test_a_camera_file_counting_only_the_regions_lenses_warns(queue):
    """A camera file written the old way, its count the region's lenses, cropped off
    centre: calibration takes the count the white image shows and says to crop the
    whole sensor's camera."""
    whole = lens_camera(30, 20)
    origin, size = (170, 0), (340, 340)
    doc = whole.to_dict()
    doc["microlens_array"]["count"] = [20, 20]
    old = Camera.from_dict(doc).cropped(origin, size)
    white = _cut(white_image(whole, queue=queue), origin, size)
    with pytest.warns(UserWarning, match="crop the camera of the whole sensor"):
        cal = calibrate(white, old)
    assert cal.ml_count == whole.cropped(origin, size).ml_count


def _perturbed(whole: Camera, seed: int = 4) -> Camera:
    """``whole`` calibrated with its ideal centres moved up to 0.4 px and two lenses
    missing (NaN)."""
    rng = np.random.default_rng(seed)
    centres = whole.ideal_microlens_centers() + rng.uniform(-0.4, 0.4, (*whole.ml_count[::-1], 2))
    centres[5, 7] = centres[9, 3] = np.nan
    return whole.with_centers(centres)


def _expected_centres(calibrated: Camera, region: Camera, origin) -> np.ndarray:
    """The whole camera's centres of the region's lenses, each lens found by where its
    ideal centre stands on the whole sensor, less ``origin``."""
    at = region.ideal_microlens_centers().reshape(-1, 2) + origin
    dist, index = cKDTree(calibrated.ideal_microlens_centers().reshape(-1, 2)).query(at)
    assert dist.max() < 1e-9
    mine = calibrated.microlens_centers.reshape(-1, 2)[index] - origin
    return mine.reshape(*region.ml_count[::-1], 2)


@pytest.mark.parametrize("name", CASES)
def test_a_calibrated_camera_keeps_its_centres_through_a_region(name):
    """A calibrated whole sensor's region keeps its lenses' measured centres to the last
    bit, less the region's origin, numbered as the region numbers them (a hexagonal
    region from an odd row, a turned array), NaN kept; a region cut from that region
    holds the whole sensor's centres less both origins; the whole sensor's region keeps
    them all. Before, cropping a calibrated camera was refused."""
    whole, origin, size = CASES[name]
    calibrated = _perturbed(whole)
    region = calibrated.cropped(origin, size)
    assert region.calibrated and region.ml_count == whole.cropped(origin, size).ml_count
    expected = _expected_centres(calibrated, region, origin)
    np.testing.assert_array_equal(region.microlens_centers, expected)
    assert np.isnan(expected).all(-1).any()  # a missing lens lies in the region
    inner = region.cropped((10, 20), (120, 100))
    both = (origin[0] + 10, origin[1] + 20)
    np.testing.assert_array_equal(inner.microlens_centers,
                                  _expected_centres(calibrated, inner, both))
    same = calibrated.cropped((0, 0), whole.pixels)
    np.testing.assert_array_equal(same.microlens_centers, calibrated.microlens_centers)


@pytest.mark.parametrize("name", ["rectangular", "hexagonal-even-row", "hexagonal-odd-row"])
def test_a_regions_centres_are_imported_from_the_whole_sensors_file(tmp_path, name):
    """A centres CSV of the whole sensor (whole-array numbering, whole-sensor pixels)
    imported onto the region's camera gives the camera imported on the whole sensor and
    cropped, to the last bit (before: refused, its lenses outside the region's array);
    so does the region's own CSV (the region's numbering and pixels), and LFIT's file of
    the whole sensor."""
    from scipy.io import savemat

    from plenocl.calibration import import_centers
    from plenocl.io.centres import write_centers_csv

    whole, origin, size = CASES[name]
    calibrated = _perturbed(whole)
    write_centers_csv(tmp_path / "whole.csv", calibrated.microlens_centers)
    with pytest.warns(UserWarning, match="2 of 320 microlenses have no centre"):
        expected = import_centers(tmp_path / "whole.csv", whole).cropped(origin, size)
    write_centers_csv(tmp_path / "region.csv", expected.microlens_centers)
    cal = np.empty((1, 1), dtype=object)
    cal[0, 0] = np.nan_to_num(calibrated.microlens_centers + 1.0, nan=0.0)
    savemat(tmp_path / "whole_calData.mat", {"calData": cal})
    for file in ("whole.csv", "region.csv", "whole_calData.mat"):
        with pytest.warns(UserWarning, match="have no centre"):
            got = import_centers(tmp_path / file, whole.cropped(origin, size))
        assert got.calibrated and got.ml_count == expected.ml_count
        assert got.crop_origin == origin and got.full_pixels == whole.pixels
        if file.endswith(".mat"):  # LFIT's pixels count from 1
            np.testing.assert_allclose(got.microlens_centers, expected.microlens_centers,
                                       atol=1e-12)
        else:
            np.testing.assert_array_equal(got.microlens_centers, expected.microlens_centers)


def test_a_centres_file_that_fits_a_region_neither_way_is_refused(tmp_path):
    """x and y swapped in the whole sensor's file, or the region's own file counted from
    another origin: refused, naming both readings and the fix."""
    from plenocl.calibration import import_centers
    from plenocl.io.centres import write_centers_csv

    whole, origin, size = CASES["rectangular"]
    calibrated = _perturbed(whole)
    region = whole.cropped(origin, size)
    write_centers_csv(tmp_path / "swapped.csv", calibrated.microlens_centers[..., ::-1])
    own = calibrated.cropped(origin, size).microlens_centers
    write_centers_csv(tmp_path / "moved.csv", own + [30.0, 0.0])
    for file in ("swapped.csv", "moved.csv"):
        with pytest.raises(ValueError, match="neither as the whole sensor's centres") as info:
            import_centers(tmp_path / file, region)
        assert "nor as the region's own" in str(info.value)
        assert "import them onto the whole sensor's camera and crop it" in str(info.value)


def test_the_cli_imports_a_whole_sensors_centres_through_a_crop(tmp_path, capsys):
    """``plenocl calibrate --centres whole.csv --crop ...`` writes the region's camera with
    the region's centres, as importing on the whole sensor and cropping; a calibrated
    whole sensor's camera given ``--crop`` is cropped with its centres (it was refused
    as calibrated on another region)."""
    from plenocl.cli.main import main
    from plenocl.io.centres import write_centers_csv

    whole, origin, size = CASES["hexagonal-odd-row"]
    calibrated = _perturbed(whole)
    whole.to_toml(tmp_path / "cam.toml")
    calibrated.to_toml(tmp_path / "cal.toml")
    write_centers_csv(tmp_path / "whole.csv", calibrated.microlens_centers)
    crop = ["--crop", *map(str, origin), *map(str, size)]
    for camera in ("cam.toml", "cal.toml"):
        assert main(["calibrate", "--centres", str(tmp_path / "whole.csv"), "--camera",
                     str(tmp_path / camera), *crop, "--out", str(tmp_path / "region.toml")]
                    ) == 0, capsys.readouterr().err
        got = Camera.from_toml(tmp_path / "region.toml")
        assert got.crop_origin == origin and got.pixels == size
        np.testing.assert_array_equal(got.microlens_centers,
                                      calibrated.cropped(origin, size).microlens_centers)

