"""The image fit's ray bundles on the device (kernels/raybundle.cl,
plenocl/piv/devicebundle.py) against the NumPy renderer (plenocl/optics/raybundle.py):
values and every derivative row on awkward particles, and the fit's positions."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import pytest
import tolerances as tol
from helpers import traced_fit_scene

from plenocl.bench.accuracy_section import paper_optics
from plenocl.opencl.build import kernel_dir
from plenocl.optics.raybundle import RayBundle, _spread
from plenocl.piv.devicebundle import DeviceRayBundle, _spread_constants
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


@pytest.mark.parametrize(("rays", "blur"), [(16, 0.1), (37, 0.35), (37, 2.0)])
def test_kernel_matches_numpy_on_awkward_bundles(queue, rays, blur):
    """Ray counts that are multiples of nothing, a blur narrow enough for the kernel's
    exp-per-edge form (blur 0.1) and a wide one: every row against the float64 twin on
    one particle and on particles at cell edges, sensor edges and strong defocus."""
    bundle = RayBundle.of(CAM, rays=rays, blur_px=blur)
    for count in (1, 9):
        pts = awkward_points(count, bundle)
        intensity = np.linspace(50.0, 500.0, count)
        patches = bundle.patches(pts)
        total = int(patches.offset[-1])
        want = dense(*bundle.render(pts, intensity, patches)[::-1], total)
        got = dense(*DeviceRayBundle(bundle, queue).render(pts, intensity, patches)[::-1],
                    total)
        for k in range(5):
            np.testing.assert_allclose(got[k], want[k], rtol=0,
                                       atol=tol.RAYBUNDLE * np.abs(want[k]).max(),
                                       err_msg=f"{count} particles, row {k}")


def test_rows_per_item_renders_the_same(queue):
    """render_rows' work-items of one row (the GPU form), of 3 rows (bands cut by the
    patch's end) and of a whole patch (the CPU form) add the same terms in the same
    order: the same rows bit for bit. The patches differ in height: the range's bands
    are the tallest patch's, and an item past its own patch's end writes nothing."""
    bundle = RayBundle.of(CAM, rays=53)
    pts = awkward_points(11, bundle)
    patches = bundle.patches(pts)
    assert len(np.unique(patches.height)) > 1
    renderer = DeviceRayBundle(bundle, queue)
    got = []
    for rows in (1, 3, 0):
        renderer.rows_per_item = rows
        got.append(renderer.render(pts, np.full(len(pts), 100.0), patches))
    for elements, rows in got[1:]:
        np.testing.assert_array_equal(elements, got[0][0])
        np.testing.assert_array_equal(rows, got[0][1])


def spread_probe(queue):
    """A kernel that calls raybundle.cl's pl_spread on given landing points."""
    source = ('#include "raybundle.cl"\n'
              "__kernel void spread_probe(__global const float *x, float delta, float4 gauss,"
              " __global float *g, __global float *dg, __global float *near)\n"
              "{ int i = get_global_id(0);"
              " near[i] = pl_spread(x[i], delta, gauss, g + 5 * i, dg + 5 * i); }\n")
    program = cl.Program(queue.context, source).build([f"-I{kernel_dir()}"])
    return cl.Kernel(program, "spread_probe")


@pytest.mark.parametrize("blur", [0.1, 0.3, 0.8, 2.5])
def test_spread_matches_float64(queue, blur):
    """pl_spread's pixel shares (its erf from the edge's exp, its edges' exps from two)
    against raybundle._spread in float64 at the same float32 landing points: within a
    few float32 roundings; ties (half-integer points) round to even as np.rint."""
    x = np.concatenate([np.random.default_rng(5).uniform(-3.0, 1500.0, 4000),
                        np.arange(-2.5, 6.0, 0.5), [0.0, 1e-7, -1e-7, 1023.4999]])
    x = x.astype(np.float32)
    n = len(x)
    g, dg, near = (cl_array.empty(queue, size, np.float32) for size in (5 * n, 5 * n, n))
    spread_probe(queue)(queue, (n,), None, cl_array.to_device(queue, x).data,
                        *_spread_constants(blur), g.data, dg.data, near.data)
    want_near = np.rint(x.astype(np.float64))
    want_g, want_dg = _spread(want_near, x.astype(np.float64), blur)
    np.testing.assert_array_equal(near.get(), want_near)
    np.testing.assert_allclose(g.get().reshape(n, 5), want_g, rtol=0, atol=1e-6)
    np.testing.assert_allclose(dg.get().reshape(n, 5), want_dg, rtol=0, atol=2e-6 / blur)
