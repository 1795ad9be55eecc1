"""A grid is checked against the camera's optics before any work (issue 44, finding 4):
the depth range the camera resolves and its field of view (plenocl.optics.depthrange),
refused in the API, the CLI and the batch with the fix in the camera's terms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plenocl import Camera, Grid
from plenocl.bench.objective import thick_camera
from plenocl.cli.main import main
from plenocl.io import write_tiff
from plenocl.optics.depthrange import (
    LIGHT_SHARE,
    VIEW_LENSES,
    check_grid,
    field_of_view_mm,
    resolved_depth_range,
)
from plenocl.projection.model import WeightingModel
from plenocl.reference.weights import voxel_weights

#: A light-limited camera: 8 x 8 lenses, too few to catch the blur of the resolution limit.
SMALL = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (8, 8), 0.0074, (136, 136))
HEXAGONAL = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (24, 26), 0.0074, (420, 400),
                   ml_layout="hexagonal")


def _thin_depth(cam: Camera, inv_alpha: float) -> float:
    """Depth whose image lies at s_i' = s_i / (1/α) (docs/design.md §2, by hand)."""
    s_ip = cam.image_distance_mm / inv_alpha
    f = cam.focal_length_mm
    return f * s_ip / (s_ip - f) - cam.object_distance_mm


def _resolved_by_hand(cam: Camera) -> tuple[float, float]:
    """A thin lens, square array on the axis: |1 - 1/α| at most the tighter of 2 lenses
    per pixel's pupil footprint (p_px s_i / f_ml) and a blur disc of which half covers
    the W x W array (W sqrt(8/π) wide, when it is wider than the array's diagonal)."""
    footprint = cam.pixel_pitch_mm * cam.image_distance_mm / cam.ml_focal_length_mm
    width = cam.ml_count[0] * cam.ml_pitch_mm
    light = width * math.sqrt(8 / math.pi)
    assert light > math.sqrt(2) * width  # the array lies inside the disc
    c = min(VIEW_LENSES * cam.ml_pitch_mm / footprint, light / cam.aperture_diameter_mm)
    return _thin_depth(cam, 1 - c), _thin_depth(cam, 1 + c)


@pytest.mark.parametrize("cam", [Camera.synthetic_850(), SMALL], ids=["synthetic", "small"])
def test_the_resolved_range_is_the_thin_lens_geometry_by_hand(cam):
    near, far = resolved_depth_range(cam)
    want = _resolved_by_hand(cam)
    assert (near, far) == pytest.approx(want, abs=2e-3), (near, far, want)
    assert cam.focal_length_mm - cam.object_distance_mm < near < 0 < far


def _on_axis_share(cam: Camera, blur_mm: float) -> float:
    """Share of a uniform blur disc centred on the axis that falls on the array (random
    points: independent of the module's own quadrature)."""
    rng = np.random.default_rng(0)
    r, t = blur_mm / 2 * np.sqrt(rng.random(200_000)), rng.random(200_000) * 2 * math.pi
    pos = cam.microlens_positions_mm().reshape(-1, 2)
    half = np.array([cam.ml_pitch_mm, cam.ml_row_pitch_mm]) / 2
    lo, hi = pos.min(0) - half, pos.max(0) + half
    x, y = r * np.cos(t), r * np.sin(t)
    return float(((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])).mean())


@pytest.mark.parametrize("cam", [Camera.synthetic_850(), Camera.paper_16mp(), SMALL,
                                 thick_camera(), HEXAGONAL],
                         ids=["synthetic", "paper", "small", "thick", "hexagonal"])
def test_at_the_range_ends_the_blur_reaches_the_tighter_limit(cam):
    """Through the camera's own forward model (alpha(z): pupils included), a point at either
    end blurs over 2 lenses per pixel's view or keeps half its light on the array, and
    stays within both limits."""
    n_u = cam.exit_pupil_diameter_mm / cam.pixel_pupil_footprint_mm  # px per lens image
    for z in resolved_depth_range(cam):
        blur = cam.exit_pupil_diameter_mm * abs(1 - 1 / float(cam.alpha(z)))
        views = blur / cam.ml_pitch_mm / n_u
        share = _on_axis_share(cam, blur)
        assert views <= VIEW_LENSES + 1e-6 and share >= LIGHT_SHARE - 3e-3, (z, views, share)
        assert views == pytest.approx(VIEW_LENSES, rel=1e-6) or share == pytest.approx(
            LIGHT_SHARE, abs=3e-3), (z, views, share)


def test_the_weighting_model_keeps_half_the_light_at_a_light_limited_end():
    """The criterion agrees with the projector's weighting: an on-axis voxel at either end
    of a light-limited camera's range sends about half its light to the sensor (the share
    below which a reconstruction leaves voxels out), all of it at the focal plane."""
    near, far = resolved_depth_range(SMALL)
    for z, want in ((near, LIGHT_SHARE), (far, LIGHT_SHARE), (0.0, 1.0)):
        voxel = Grid((1, 1, 1), x=(-1e-3, 1e-3), y=(-1e-3, 1e-3), z=(z - 1e-3, z + 1e-3))
        _, weights = voxel_weights(SMALL, voxel, 0, 0, 0)
        assert float(weights.sum()) == pytest.approx(want, abs=0.03), z


@pytest.mark.parametrize("z", [0.0, -4.0, 7.0])
def test_the_field_of_view_maps_onto_the_array_edges(z):
    """The field's corners, imaged by the main lens (image_points) and carried to the
    array along the central ray (X'/α), land on the array's outer edges."""
    cam = Camera.synthetic_850()
    fov = field_of_view_mm(cam, z)
    corners = np.array([[fov[0, 0], fov[1, 0], z], [fov[0, 1], fov[1, 1], z]])
    img = cam.image_points(corners)
    on_array = img[:, :2] / (img[:, 2:] / cam.image_distance_mm)
    half = cam.ml_count[0] * cam.ml_pitch_mm / 2
    assert np.allclose(np.abs(on_array), half, rtol=1e-9)
    if z == 0.0:  # the array over the magnification
        assert np.allclose(fov, [[-half, half], [-half, half]])


def _grid(**kw) -> Grid:
    args = {"shape": (4, 8, 8), "x": (-1.0, 1.0), "y": (-1.0, 1.0), "z": (-2.0, 2.0), **kw}
    return Grid(**args)


def _range_text(cam: Camera) -> str:
    near, far = resolved_depth_range(cam)
    return f"this camera resolves z in [{near:.2f}, {far:.2f}] mm"


@pytest.mark.parametrize("grid, message", [
    (_grid(z=(200.0, 210.0)), "reaches beyond the depths the camera resolves"),
    (_grid(z=(-2.0, 25.0)), "reaches beyond the depths the camera resolves"),
    (_grid(z=(-20.0, 0.0)), "reaches beyond the depths the camera resolves"),
    (_grid(z=(-60.0, -55.0)), "where the main lens forms no real image"),
])
def test_a_depth_the_camera_does_not_resolve_is_refused_with_its_range(grid, message):
    cam = Camera.synthetic_850()
    for build in (check_grid, WeightingModel):  # the model: what every projector builds
        with pytest.raises(ValueError, match=message) as err:
            build(cam, grid)
        assert _range_text(cam) in str(err.value)
    with pytest.raises(ValueError, match=message):
        Grid.for_camera(cam, grid.z)


def test_a_grid_outside_the_field_of_view_is_refused_with_the_field():
    cam = Camera.synthetic_850()
    grid = _grid(x=(10.0, 11.0))
    with pytest.raises(ValueError, match="entirely outside the camera's field of view") as err:
        WeightingModel(cam, grid)
    fov = field_of_view_mm(cam, grid.z[0])
    assert f"x in [{fov[0, 0]:.2f}, {fov[0, 1]:.2f}]" in str(err.value)


@pytest.mark.parametrize("cam, grid", [
    (Camera.paper_16mp(), Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5),
                               z=(-10.0, 10.0))),  # the boundary-layer demo
    (Camera.synthetic_850(), _grid(x=(-1.5, 1.5), z=(-2.5, 2.5), rotation_deg=20.0)),
    (thick_camera(), _grid(z=(-2.0, 2.0))),
    (HEXAGONAL, _grid(x=(-0.6, 0.6), y=(-0.5, 0.5), z=(-4.0, 4.0), rotation_deg=1.0)),
], ids=["paper-demo", "rotated", "thick", "hexagonal"])
def test_the_grids_the_camera_resolves_pass(cam, grid):
    check_grid(cam, grid)
    near, far = resolved_depth_range(cam)
    whole = Grid.for_camera(cam, (near + 1e-6, min(far, 1e6) - 1e-6),
                            depth_voxel_mm=(min(far, 1e6) - near) / 8)
    assert whole.z[0] > near and whole.shape[0] == 8


def test_plenocl_grid_refuses_before_writing_and_names_the_range(tmp_path, capsys):
    out = tmp_path / "g.toml"
    for z in (("-60", "-55"), ("200", "210")):
        assert main(["grid", "--camera", "synthetic", "--z", *z, "--out", str(out)]) == 2
        assert _range_text(Camera.synthetic_850()) in capsys.readouterr().err
        assert not out.exists() and list(tmp_path.iterdir()) == []
    assert main(["grid", "--camera", "synthetic", "--z", "-2", "2", "--out", str(out)]) == 0
    assert "the camera resolves z in [-14.45, 20.33] mm" in capsys.readouterr().out
    check_grid(Camera.synthetic_850(), Grid.from_toml(out))


BATCH = """
[camera]
preset = "synthetic"
[grid]
{grid}
[images]
folder = "raw"
pattern = "frame_*.tif"
pairing = "sequence"
dt_s = 1e-3
[output]
folder = "results"
"""


@pytest.mark.parametrize("grid", ["z_mm = [200.0, 210.0]", 'file = "far.toml"'])
def test_a_batch_refuses_the_grid_before_any_pair(tmp_path, capsys, grid):
    (tmp_path / "raw").mkdir()
    for k in range(4):
        write_tiff(tmp_path / "raw" / f"frame_{k:03d}.tif", np.zeros((850, 850), np.uint16))
    _grid(z=(200.0, 210.0)).to_toml(tmp_path / "far.toml")
    (tmp_path / "experiment.toml").write_text(BATCH.format(grid=grid))
    assert main(["run", str(tmp_path / "experiment.toml")]) == 2
    err = capsys.readouterr().err
    assert _range_text(Camera.synthetic_850()) in err and err.count("resolves z in") == 1
    assert not (tmp_path / "results").exists()  # nothing made, not one pair tried


def test_points_in_the_field_of_view_are_those_inside_its_box_at_their_depth():
    """``in_field_of_view`` (every point at once, the array's box found once) agrees with
    ``field_of_view_mm`` taken point by point, near and far of the focal plane."""
    from plenocl.optics.depthrange import field_of_view_mm, in_field_of_view

    cam = Camera.paper_16mp()
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-30, 30, 300), rng.uniform(-20, 20, 300),
                           rng.uniform(-10, 10, 300)])
    want = []
    for x, y, z in pts:
        (x0, x1), (y0, y1) = field_of_view_mm(cam, float(z))
        want.append(x0 <= x <= x1 and y0 <= y <= y1)
    got = in_field_of_view(cam, pts)
    assert 0.2 < got.mean() < 0.95
    np.testing.assert_array_equal(got, want)
