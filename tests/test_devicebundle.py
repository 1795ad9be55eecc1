"""The image fit's ray bundles on the device (kernels/raybundle.cl,
plenocl/piv/devicebundle.py) against the NumPy renderer (plenocl/optics/raybundle.py):
values and every derivative row on awkward particles, and the fit's positions."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol
from helpers import traced_fit_scene

from plenocl.bench.accuracy_section import paper_optics
from plenocl.optics.raybundle import RayBundle
from plenocl.piv.devicebundle import DeviceRayBundle
from plenocl.piv.imagefit import ImageFit, ImageFitSettings

CAM, GRID = paper_optics((32, 24))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm


def missing_lens_camera():
    """The camera with a 3 x 3 block of lenses missing (NaN centres) near the middle."""
    centres = CAM.ideal_microlens_centers().copy()
    centres[10:13, 14:17] = np.nan
    return CAM.with_centers(centres)


def cell_edge_points(bundle: RayBundle) -> np.ndarray:
    """Image points near focus whose chief ray meets the array on a cell edge, a cell
    corner and just inside an edge (lattice units)."""
    s_ip = CAM.image_distance_mm * 1.002
    lattice = np.array([[10.5, 8.0], [12.5, 9.5], [7.0, 11.4997]])
    x = (lattice - bundle.to_lattice[2]) @ np.linalg.inv(bundle.to_lattice[:2])
    return np.column_stack([x * s_ip / CAM.image_distance_mm, np.full(len(x), s_ip)])


def awkward_points(count: int, bundle: RayBundle) -> np.ndarray:
    """``count`` image points: on cell edges, at the sensor's edges and corner (patches
    cut by the sensor), over the missing lenses, the rest random over the volume."""
    rng = np.random.default_rng(count)
    edges = CAM.image_points(np.array([[2.95, -2.2, 6.0], [-3.0, 0.1, -7.5],
                                       [0.2, 2.25, 9.0], [0.0, 0.0, -4.0]]))
    fill = np.column_stack([rng.uniform(-3, 3, count), rng.uniform(-2.3, 2.3, count),
                            rng.uniform(-9.5, 9.5, count)])
    pts = np.vstack([cell_edge_points(bundle), edges, CAM.image_points(fill)])
    return pts[:count]


def dense(rows: np.ndarray, elements: np.ndarray, total: int) -> np.ndarray:
    out = np.zeros((len(rows), total))
    out[:, elements] = rows
    return out


@pytest.mark.parametrize("count", [1, 6, 37, 130])
@pytest.mark.parametrize("missing", [False, True])
def test_kernel_matches_numpy_renderer(queue, count, missing):
    """Every row (value, d/dX', d/dY', d/ds_i', d/dI) of every patch element against the
    float64 twin, within float32 rounding of each row's peak."""
    bundle = RayBundle.of(missing_lens_camera() if missing else CAM, rays=200)
    pts = awkward_points(count, bundle)
    intensity = np.random.default_rng(1).uniform(10.0, 1000.0, count)
    patches = bundle.patches(pts)
    total = int(patches.offset[-1])
    want = dense(*bundle.render(pts, intensity, patches)[::-1], total)
    got = dense(*DeviceRayBundle(bundle, queue).render(pts, intensity, patches)[::-1], total)
    assert np.isfinite(got).all()
    for k in range(5):
        np.testing.assert_allclose(got[k], want[k], rtol=0,
                                   atol=tol.RAYBUNDLE * np.abs(want[k]).max(), err_msg=k)
    value_only = DeviceRayBundle(bundle, queue).render(pts, intensity, patches, False)
    np.testing.assert_allclose(dense(value_only[1], value_only[0], total)[0], got[0],
                               rtol=tol.ROUNDING, atol=tol.ROUNDING * got[0].max())


def test_kernel_renders_nothing_for_no_particles(queue):
    bundle = RayBundle.of(CAM, rays=64)
    patches = bundle.patches(np.zeros((0, 3)))
    elements, rows = DeviceRayBundle(bundle, queue).render(np.zeros((0, 3)), np.zeros(0),
                                                           patches)
    assert elements.shape == (0,) and rows.shape == (5, 0)


def test_fit_on_device_matches_numpy(queue):
    """The same fit, rendered on the device (float32) and by NumPy (float64): positions
    within a small fraction of the fit's accuracy (a few tenths of a voxel in depth)."""
    start, img = traced_fit_scene(CAM, VOXEL, 9, 1)
    fits = [ImageFit(CAM, GRID, [img], ImageFitSettings(), queue=q).fit(0, start)
            for q in (None, queue)]
    assert np.abs(fits[1].positions - fits[0].positions).max(axis=0) / VOXEL == \
        pytest.approx(np.zeros(3), abs=tol.IMAGEFIT_POSITION_VOXELS)
    assert fits[1].intensities == pytest.approx(fits[0].intensities, rel=1e-3)
