"""The projector's device-free weighting model (plenocl/projection/model.py): built from a
camera and a grid without OpenCL, it agrees with the NumPy reference's model."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import lens_camera

from plenocl import Grid, Projector
from plenocl.optics.ownership import lens_owner
from plenocl.projection.model import WeightingModel
from plenocl.reference.weights import ApertureGrid, lens_index_map

GRID = Grid((5, 7, 9), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.5, 1.5))


def test_the_coefficients_meet_the_array_plane_where_the_reference_does(small_camera):
    """Voxel ``(ix, iy)`` of depth ``iz`` through sample ``(i, j)`` lands at lens index
    ``G (ix, iy) + o + H (i - c, j - c)``: the reference's ray through the image point."""
    model = WeightingModel(small_camera, GRID)
    ap = ApertureGrid.for_camera(small_camera)
    lmap = lens_index_map(small_camera)
    i, j = ap.samples()
    u, v = (i - ap.center) * ap.step, (j - ap.center) * ap.step
    for iz, iy, ix in [(0, 0, 0), (2, 3, 4), (4, 6, 8)]:
        xyz = [GRID.axis_centers("x")[ix], GRID.axis_centers("y")[iy],
               GRID.axis_centers("z")[iz]]
        xp, yp, sip = small_camera.image_points(xyz)[0]
        alpha = sip / small_camera.image_distance_mm
        want = np.stack(lmap(u * (1 - 1 / alpha) + xp / alpha, v * (1 - 1 / alpha) + yp / alpha))
        row = model.coef[iz]
        g, o, h = row[0:4].reshape(2, 2), row[4:6], row[6:10].reshape(2, 2)
        got = (g @ [ix, iy])[:, None] + o[:, None] + h @ np.stack([i - ap.center,
                                                                   j - ap.center])
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_the_path_and_tables_follow_the_camera(small_camera):
    ideal = WeightingModel(small_camera, GRID)
    assert ideal.path == "separable"
    assert ideal.n_samples == len(ideal.pixel_offsets) == len(ideal.aperture.samples()[0])
    rnd, frac = ideal.lens_tables
    centres = small_camera.microlens_centers.reshape(-1, 2)
    np.testing.assert_allclose(rnd + frac, centres, atol=1e-4)
    assert ideal.present.all() and ideal.colour_stride >= 2
    with pytest.warns(UserWarning, match="general path"):
        rotated = WeightingModel(lens_camera(12, 10, ml_rotation_deg=1.0), GRID)
    assert rotated.path == "general"


def test_the_model_refuses_geometry_that_cannot_image(small_camera):
    with pytest.raises(ValueError, match="no real image"):
        WeightingModel(small_camera, Grid((3, 3, 3), x=(-1, 1), y=(-1, 1), z=(-1e4, 1)))
    with pytest.raises(ValueError, match="field of view"):
        WeightingModel(small_camera, Grid((3, 3, 3), x=(50, 51), y=(50, 51), z=(-1, 1)))


def test_every_lens_owns_its_own_centre(small_camera):
    """The one ownership rule (plenocl/optics/ownership.py): the pixel at a lens's image
    centre belongs to that lens."""
    owner = lens_owner(small_camera)
    centres = np.rint(small_camera.microlens_centers).astype(int)
    cols = small_camera.ml_count[0]
    rows, ks = np.mgrid[0:centres.shape[0], 0:centres.shape[1]]
    np.testing.assert_array_equal(owner[centres[..., 1], centres[..., 0]], rows * cols + ks)


def test_a_projector_takes_a_prebuilt_model(small_camera, queue):
    model = WeightingModel(small_camera, GRID, oversample=1.0)
    proj = Projector(small_camera, GRID, queue, model=model)
    assert proj.model is model and proj.path == model.path
    assert proj.n_samples == model.n_samples
    assert proj.refined(2).model.oversample == 1.0
    with pytest.raises(ValueError, match="another camera or grid"):
        Projector(small_camera, GRID.refined(2), queue, model=model)
