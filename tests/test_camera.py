"""Camera optics, TOML files, validation; Grid geometry."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import lens_camera

from plenocl import Camera, Grid


def test_thin_lens_relations_hold_at_every_depth():
    cam = Camera.paper_16mp()
    f, M = cam.focal_length_mm, cam.magnification
    assert cam.image_distance_mm / cam.object_distance_mm == pytest.approx(M)
    z = np.linspace(-10, 10, 21)
    s_o, s_i = cam.object_distance_mm + z, cam.image_distance_at(z)
    np.testing.assert_allclose(1 / s_o + 1 / s_i, 1 / f, rtol=1e-12)
    assert cam.alpha(0.0) == pytest.approx(1.0)
    # +z is away from the camera: the image moves towards the lens (alpha < 1)
    assert np.all(np.diff(cam.alpha(z)) < 0)


def test_image_is_inverted_and_scaled_by_magnification():
    cam = Camera.synthetic_850()
    pts = cam.image_points([[1.0, -0.5, 0.0]])
    np.testing.assert_allclose(pts[0, :2], [-cam.magnification, 0.5 * cam.magnification])


def test_ideal_centres_follow_ck_equals_xk_times_one_plus_fml_over_si():
    cam = Camera.synthetic_850()
    ck_mm = cam.px_to_mm(cam.microlens_centers)
    xk = cam.microlens_positions_mm()
    np.testing.assert_allclose(ck_mm, xk * (1 + cam.ml_focal_length_mm / cam.image_distance_mm))
    np.testing.assert_allclose(cam.mm_to_px(cam.px_to_mm([[3.0, 7.0]])), [[3.0, 7.0]])


def test_pixel_centre_convention():
    cam = Camera.synthetic_850()
    w, h = cam.pixels
    p = cam.pixel_pitch_mm
    np.testing.assert_allclose(cam.px_to_mm([0, 0]), [(0.5 - w / 2) * p, (0.5 - h / 2) * p])


@pytest.mark.parametrize("preset", [Camera.paper_16mp, Camera.synthetic_850])
def test_presets_match_the_paper(preset):
    cam = preset()
    assert 16.5 < cam.pixels_per_microlens < 17.5
    assert 0.95 < cam.microlens_image_fill <= 1.0


def test_toml_round_trip_with_calibrated_centres(tmp_path):
    cam = lens_camera(ml_rotation_deg=0.5)
    rng = np.random.default_rng(1)
    centres = cam.ideal_microlens_centers() + rng.normal(0, 0.2, (10, 12, 2))
    centres[3, 4] = np.nan
    cal = cam.with_centers(centres)
    cal.to_toml(tmp_path / "cam.toml")
    back = Camera.from_toml(tmp_path / "cam.toml")
    assert back.calibrated and back.ml_rotation_deg == 0.5
    np.testing.assert_array_equal(back.microlens_centers, cal.microlens_centers)
    # an uncalibrated camera writes no centres and reads back the ideal ones
    cam.to_toml(tmp_path / "plain.toml")
    assert "calibration" not in (tmp_path / "plain.toml").read_text()
    np.testing.assert_allclose(Camera.from_toml(tmp_path / "plain.toml").microlens_centers,
                               cam.ideal_microlens_centers())


def test_contract_keys_are_read(tmp_path):
    (tmp_path / "c.toml").write_text(
        "[main_lens]\nfocal_length_mm = 50.0\nf_number = 2.42\nmagnification = 0.66\n"
        "[microlens_array]\npitch_mm = 0.125\nfocal_length_mm = 0.5\ncount = [289, 193]\n"
        "[sensor]\npixel_pitch_mm = 0.0074\npixels = [4904, 3280]\n")
    cam = Camera.from_toml(tmp_path / "c.toml")
    assert cam.ml_count == (289, 193) and cam.pixels == (4904, 3280)
    assert cam.microlens_centers.shape == (193, 289, 2)


@pytest.mark.parametrize("kwargs, message", [
    (dict(focal_length_mm=-50.0), "focal_length_mm must be a positive"),
    (dict(f_number=float("nan")), "f_number must be a positive"),
    (dict(ml_count=(60, 50)), "larger than the sensor"),
    (dict(ml_count=(0, 50)), "positive integers"),
    (dict(pixel_pitch_mm=0.1), "pixels per microlens"),
])
def test_bad_cameras_are_rejected_with_the_fix(kwargs, message):
    base = dict(focal_length_mm=50.0, f_number=2.0, magnification=1.0, ml_pitch_mm=0.125,
                ml_focal_length_mm=0.5, ml_count=(50, 50), pixel_pitch_mm=0.0074,
                pixels=(850, 850))
    with pytest.raises(ValueError, match=message):
        Camera(**{**base, **kwargs})


def test_f_number_mismatch_warns_with_percentage():
    with pytest.warns(UserWarning, match=r"overlap by \d+\.\d%"):
        Camera(50.0, 1.4, 1.0, 0.125, 0.5, (50, 50), 0.0074, (850, 850))
    with pytest.warns(UserWarning, match=r"underfill"):
        Camera(50.0, 4.0, 1.0, 0.125, 0.5, (50, 50), 0.0074, (850, 850))


@pytest.mark.parametrize("edit, message", [
    (("rotation_deg = 0.0", "rotaton_deg = 0.5"), r"unknown key\(s\) \['rotaton_deg'\] in "
                                                   r"\[microlens_array\]"),
    (("[sensor]", "[sensor]\nbit_depth = 12"), r"unknown key\(s\) \['bit_depth'\] in \[sensor\]"),
    (("[sensor]", "[lens]\nx = 1\n[sensor]"), r"unknown section\(s\) \['lens'\]"),
])
def test_unknown_camera_keys_are_refused_by_name(tmp_path, edit, message):
    """A misspelt optional key used to be ignored silently (the array then 0.5° off)."""
    Camera.synthetic_850().to_toml(tmp_path / "c.toml")
    text = (tmp_path / "c.toml").read_text()
    assert edit[0] in text
    (tmp_path / "c.toml").write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(ValueError, match=message):
        Camera.from_toml(tmp_path / "c.toml")


def test_missing_key_and_impossible_depth_errors(tmp_path):
    (tmp_path / "bad.toml").write_text("[main_lens]\nfocal_length_mm = 50.0\n")
    with pytest.raises(ValueError, match="lacks the key"):
        Camera.from_toml(tmp_path / "bad.toml")
    with pytest.raises(ValueError, match="no real image"):
        Camera.synthetic_850().image_distance_at(-60.0)
    with pytest.raises(ValueError, match="shape"):
        Camera.synthetic_850().with_centers(np.zeros((3, 3, 2)))


def test_grid_geometry_and_round_trip(tmp_path):
    g = Grid((4, 5, 6), x=(-3, 3), y=(-2.5, 2.5), z=(-1, 3))
    assert g.spacing == (1.0, 1.0, 1.0) and g.size == 120
    np.testing.assert_allclose(g.axis_centers("x"), np.arange(6) - 2.5)
    c = g.centers()
    assert c.shape == (120, 3)
    np.testing.assert_allclose(c[7], [g.axis_centers("x")[1], g.axis_centers("y")[1], -0.5])
    np.testing.assert_allclose(g.to_index(c)[7], [1, 1, 0])
    g.to_toml(tmp_path / "g.toml")
    assert Grid.from_toml(tmp_path / "g.toml") == g


@pytest.mark.parametrize("kwargs", [dict(shape=(0, 2, 2)), dict(shape=(2, 2)),
                                    dict(x=(1, -1)), dict(z=(0, float("inf")))])
def test_bad_grids_are_rejected(kwargs):
    base = dict(shape=(2, 2, 2), x=(-1, 1), y=(-1, 1), z=(-1, 1))
    with pytest.raises(ValueError, match="grid"):
        Grid(**{**base, **kwargs})


def test_grid_for_camera_uses_one_microlens_per_voxel_and_half_the_depth_resolution():
    cam = Camera.synthetic_850()
    g = Grid.for_camera(cam, z=(-2.5, 2.5))
    assert g.spacing[2] == pytest.approx(cam.ml_pitch_mm / cam.magnification)
    # p_ml N_w / M² = 0.125 mm x 4 / 1 = 0.5 mm: depth voxels of 0.25 mm
    assert cam.depth_resolution_mm == pytest.approx(0.5)
    assert g.shape == (20, 50, 50)


def test_depth_resolution_is_where_the_blur_reaches_one_microlens():
    cam = Camera.paper_16mp()
    dz = cam.depth_resolution_mm
    s_ip = cam.image_distance_at(dz / 2)
    blur = cam.aperture_diameter_mm * abs(s_ip - cam.image_distance_mm) / s_ip
    assert blur == pytest.approx(cam.ml_pitch_mm / 2, rel=0.05)  # half-range: half a lens
