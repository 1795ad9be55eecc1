"""Light field (docs/design.md §2, §4): per-pixel (x, y, u, v), perspective views and their
parallax, refocusing (kernel against reference, depth of best focus), the CLI."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import tolerances as tol
from helpers import lens_camera

from plenocl import Camera
from plenocl.calibration import calibrate
from plenocl.cli.calibrate import add_refocus_parser
from plenocl.lightfield import LightField, pixel_coordinates, plaid_uv
from plenocl.reference.refocus import refocus_views
from plenocl.simulate import simulate_image, simulate_white_image

ZS = np.arange(-3.0, 3.01, 0.5)


def _camera(cols=24, rows=20, **layout) -> Camera:
    """M = 1, f/2, ~17 px per lens; ideal centres marked calibrated."""
    cam = lens_camera(cols, rows, (int(cols * 16.98) + 1, int(rows * 16.98) + 1), **layout)
    return cam.with_centers(cam.ideal_microlens_centers())


@pytest.fixture(scope="module")
def cam() -> Camera:
    return _camera()


def _particle_image(cam, points, queue, rays=20000):
    pts = np.atleast_2d(points)
    return simulate_image(cam, pts, 1e5, rays, seed=1, queue=queue)


def test_pixel_coordinates_follow_design(cam):
    pc = pixel_coordinates(cam)
    kx, ky = 7, 5
    c = cam.microlens_centers[ky, kx]
    col, row = int(np.rint(c[0])), int(np.rint(c[1]))
    assert (pc.kx[row, col], pc.ky[row, col]) == (kx, ky)
    footprint = cam.pixel_pitch_mm * cam.image_distance_mm / cam.ml_focal_length_mm
    # u = -d s_i / f_ml, d the pixel's offset from the centre in mm
    assert pc.u_mm[row, col] == pytest.approx(-(col - c[0]) * footprint, abs=1e-9)
    assert pc.u_mm[row, col + 3] - pc.u_mm[row, col] == pytest.approx(-3 * footprint)
    assert pc.v_mm[row + 2, col] - pc.v_mm[row, col] == pytest.approx(-2 * footprint)
    xk = cam.microlens_positions_mm()[ky, kx]
    assert (pc.x_mm[row, col], pc.y_mm[row, col]) == pytest.approx(tuple(xk), abs=1e-9)
    # corners between four lens images see outside the aperture
    corner = np.rint(cam.microlens_centers[ky, kx] + 8.4).astype(int)
    assert not pc.valid[corner[1], corner[0]] and pc.valid[row, col]


def test_uncalibrated_camera_warns(queue):
    cam = lens_camera(12, 10)
    with pytest.warns(UserWarning, match="not calibrated"):
        LightField(np.zeros(cam.pixels[::-1]), cam, queue=queue)


@pytest.mark.parametrize("z", [-2.0, 0.0, 2.0])
def test_particle_is_sharpest_at_its_depth(cam, queue, z):
    img = _particle_image(cam, [0.031, -0.022, z], queue)
    stack = LightField(img, cam, queue=queue).focal_stack(ZS, supersample=2)
    flat = stack.reshape(len(ZS), -1)
    assert ZS[flat.max(1).argmax()] == z  # the peak
    assert ZS[flat.var(1).argmax()] == z  # the variance
    assert np.isfinite(stack).all()


def test_refocused_particle_lands_where_geometry_puts_it(cam, queue):
    point = np.array([0.2, -0.15, 1.5])
    lf = LightField(_particle_image(cam, point, queue), cam, queue=queue)
    img = lf.refocus(z_mm=point[2], supersample=2)
    pos = lf.output_positions_mm(supersample=2)
    w = np.clip(img - 0.2 * img.max(), 0, None)
    found = (w[..., None] * pos).sum((0, 1)) / w.sum()
    xp = cam.image_points(point[None])[0]
    expected = xp[:2] / cam.alpha(point[2])  # ξ = X'/α on the array plane
    assert found == pytest.approx(expected, abs=0.35 * cam.ml_pitch_mm)


def _view_centroid_slopes(lf: LightField, blocks) -> list[float]:
    """Per block of lenses: slope of the particle's kx centroid over the central-v views."""
    iv = len(lf.v) // 2
    slopes = []
    for rows, cols in blocks:
        us, ks = [], []
        for iu, u in enumerate(lf.u):
            profile = np.nan_to_num(lf.views[iv, iu])[rows][:, cols].sum(0)
            if profile.sum() > 0:
                us.append(u)
                ks.append((profile * cols).sum() / profile.sum())
        slopes.append(np.polyfit(us, ks, 1)[0])
    return slopes


@pytest.mark.parametrize("z", [-2.0, 2.0])
def test_perspective_views_show_the_predicted_parallax(cam, queue, z):
    # a view at aperture u sees the point at array-plane x = X'/α + (1 - 1/α) u
    expected = (1 - 1 / cam.alpha(z)) / cam.ml_pitch_mm  # lenses per mm of u
    # one particle in the middle of each of 4 x 2 blocks of lenses, at 8 sub-lens phases
    # (a view locates a point only to its lens: the phases average the staircase out)
    xs = np.array([1.125, 0.375, -0.375, -1.125])
    pts = [[x + cam.ml_pitch_mm * (2 * i + j) / 8, y, z]
           for j, y in enumerate([0.625, -0.625]) for i, x in enumerate(xs)]
    lf = LightField(_particle_image(cam, pts, queue), cam, queue=queue)
    col_bands = np.array_split(np.arange(lf.shape[1]), 4)
    row_bands = np.array_split(np.arange(lf.shape[0]), 2)
    slopes = _view_centroid_slopes(lf, [(r, c) for r in row_bands for c in col_bands])
    assert np.mean(slopes) == pytest.approx(expected, rel=0.03)  # measured: -1.0 %, -1.8 %
    assert np.all(np.abs(np.array(slopes) / expected - 1) < 0.15)


def test_view_is_the_plaid_sample(cam, queue):
    lf = LightField(_particle_image(cam, [0.0, 0.0, 0.0], queue, rays=2000), cam, queue=queue)
    assert lf.views.shape == (len(lf.v), len(lf.u), 20, 24)
    assert np.array_equal(lf.view(lf.u[3], lf.v[5]), lf.views[5, 3], equal_nan=True)
    assert lf.lf.shape == (20, 24, len(lf.v), len(lf.u))
    assert np.all(np.isnan(lf.views[0, 0]))  # the corner of the plaid grid is outside
    with pytest.raises(ValueError, match="outside the aperture"):
        lf.view(20.0, 0.0)
    assert np.allclose(plaid_uv(cam), -plaid_uv(cam)[::-1])


def test_refocus_at_alpha_one_is_the_mean_over_the_aperture(cam, queue):
    """Unshifted views: each lens's mean over the aperture, smoothed by the quadratic
    B-spline's weights at zero offset (1/8, 3/4, 1/8 per axis), as every plane is."""
    from scipy.ndimage import correlate

    rng = np.random.default_rng(3)
    img = rng.uniform(0, 100, cam.pixels[::-1]).astype(np.float32)
    lf = LightField(img, cam, queue=queue)
    mean = np.nanmean(lf.views.reshape(-1, *lf.shape), axis=0)
    taps = np.array([0.125, 0.75, 0.125])
    expected = correlate(mean, np.outer(taps, taps), mode="nearest")
    np.testing.assert_allclose(lf.refocus(alpha=1.0)[1:-1, 1:-1], expected[1:-1, 1:-1],
                               rtol=tol.REFOCUS_UNSHIFTED)


@pytest.mark.parametrize("z_true", [0.8, -0.9, 1.3])
def test_a_focal_stack_finds_known_depths_near_focus_without_a_pull_to_zero(cam, queue,
                                                                           z_true):
    """Particles near the focal plane, where the bias was worst: sharpness (peak and
    variance) peaks within 0.25 mm of the true depth. Bilinear sampling left the z = 0
    plane alone unsmoothed, and these stacks peaked at exactly 0 for 0.8 and -0.9 mm."""
    zs = np.round(np.arange(-2.0, 2.01, 0.1), 2)
    pts = np.array([[x, y, z_true] for x in (-0.8, 0.0, 0.8) for y in (-0.6, 0.6)])
    img = simulate_image(cam, pts, 1e5, 20000, seed=4, queue=queue)
    stack = LightField(img, cam, queue=queue).focal_stack(zs)  # one pixel per lens
    flat = stack.reshape(len(zs), -1)
    for found in (zs[flat.max(1).argmax()], zs[flat.var(1).argmax()]):
        assert abs(found - z_true) <= 0.25, (found, z_true)


@pytest.mark.parametrize("supersample", [1, 3])
def test_kernel_matches_reference_on_awkward_sizes(cam, queue, supersample):
    rng = np.random.default_rng(7)
    lf = LightField(np.zeros(cam.pixels[::-1], np.float32), cam, queue=queue)
    nuv, ny, nx = 7, 13, 17  # odd sizes, not multiples of any work-group size
    views = rng.uniform(0, 10, (nuv, ny, nx)).astype(np.float32)
    views[rng.random(views.shape) < 0.1] = np.nan  # missing lenses / outside the aperture
    views[:, :2, :3] = np.nan  # a dead region: zero output, no NaN
    lf.views = views.reshape(1, nuv, ny, nx)  # the device copy is made anew
    shifts = rng.uniform(-2.5, 2.5, (3, nuv, 2))
    shifts[0] = 0.0
    got = lf.shift_and_add(shifts, supersample)
    ref = refocus_views(views, shifts, supersample)
    assert got.shape == (3, ny * supersample, nx * supersample)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, ref, rtol=tol.REFOCUS, atol=tol.REFOCUS_FLOOR)


def test_focal_stack_equals_single_refocus(cam, queue):
    lf = LightField(_particle_image(cam, [0.1, 0.1, 1.0], queue, rays=4000), cam, queue=queue)
    stack = lf.focal_stack([-1.0, 1.0])
    np.testing.assert_allclose(stack[1], lf.refocus(z_mm=1.0), rtol=tol.ROUNDING)
    np.testing.assert_allclose(stack[0], lf.refocus(alpha=float(cam.alpha(-1.0))),
                               rtol=tol.ROUNDING)
    for bad in (dict(), dict(alpha=1.0, z_mm=0.0)):
        with pytest.raises(ValueError, match="exactly one"):
            lf.refocus(**bad)
    with pytest.raises(ValueError, match="alpha"):
        lf.refocus(alpha=-1.0)
    with pytest.raises(ValueError, match="supersample"):
        lf.refocus(alpha=1.0, supersample=0)


def test_bad_raw_image_is_rejected(cam):
    with pytest.raises(ValueError, match="rows"):
        LightField(np.zeros((10, 10)), cam)
    with pytest.raises(ValueError, match="NaN"):
        LightField(np.full(cam.pixels[::-1], np.nan), cam)


def test_calibrated_rotated_camera_end_to_end(queue, tmp_path):
    """White image of a rotated, shifted array → calibrate → refocus finds the depth."""
    true = lens_camera(24, 20, pixels=(409, 341), ml_rotation_deg=1.5,
                       ml_offset_mm=(0.02, -0.015))
    nominal = lens_camera(24, 20, pixels=(409, 341))
    white = simulate_white_image(true, photon_noise=True, seed=2, queue=queue)
    cal = calibrate(white, nominal)
    raw = _particle_image(true, [0.05, 0.03, -1.5], queue)
    stack = LightField(raw, cal, queue=queue).focal_stack(ZS)
    assert ZS[stack.reshape(len(ZS), -1).max(1).argmax()] == -1.5
    # the same through the command line
    from plenocl.io import write_tiff

    cal.to_toml(tmp_path / "cal.toml")
    write_tiff(tmp_path / "raw.tif", raw)
    parser = argparse.ArgumentParser()
    add_refocus_parser(parser.add_subparsers())
    args = parser.parse_args(["refocus", str(tmp_path / "raw.tif"), "--camera",
                              str(tmp_path / "cal.toml"), "--z", "-1.5", "0", "1.5",
                              "--out", str(tmp_path / "stack.tif")])
    args.device = queue
    assert args.func(args) == 0
    import tifffile

    saved = tifffile.imread(tmp_path / "stack.tif")
    np.testing.assert_allclose(saved[0], stack[list(ZS).index(-1.5)],
                               rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)
    from plenocl.io.files import read_tiff_metadata

    meta = read_tiff_metadata(tmp_path / "stack.tif")  # each page's depth is recorded
    assert meta["z_mm"] == [-1.5, 0.0, 1.5] and len(meta["alpha"]) == 3


@pytest.mark.parametrize("layout, aspect", [("rectangular", 1.0), ("hexagonal", 0.866)])
def test_a_focal_stack_file_holds_its_pixels_aspect(tmp_path, queue, layout, aspect):
    """A hexagonal array's refocused rows are 0.866 as tall as its columns are wide: the
    TIFF said nothing, and viewers stretched the stack by 15 %; its resolution tags and
    metadata give the pixel's size now."""
    import tifffile
    from helpers import lens_camera

    from plenocl.cli.main import main
    from plenocl.io.files import read_tiff_metadata

    cam = lens_camera(8, 7, ml_layout=layout)
    cam.to_toml(tmp_path / "cam.toml")
    np.save(tmp_path / "raw.npy", np.random.default_rng(0).random(cam.pixels[::-1]))
    assert main(["refocus", str(tmp_path / "raw.npy"), "--camera", str(tmp_path / "cam.toml"),
                 "--z", "0", "--out", str(tmp_path / "stack.tif")]) == 0
    rows, cols = read_tiff_metadata(tmp_path / "stack.tif")["pixel_mm"]
    assert rows / cols == pytest.approx(aspect, abs=2e-3)
    assert cols == pytest.approx(cam.ml_pitch_mm, rel=1e-3)
    with tifffile.TiffFile(tmp_path / "stack.tif") as tif:
        tags = tif.pages[0].tags
        x_res, y_res = (tags[name].value for name in ("XResolution", "YResolution"))
    assert (x_res[0] / x_res[1]) / (y_res[0] / y_res[1]) == pytest.approx(aspect, abs=2e-3)
