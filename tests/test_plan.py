"""The projector's work plan and the weighting tables, in plain NumPy (no device)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import lens_camera

from plenocl import Grid
from plenocl.camera.lattice import lattice_fit, lattice_residual
from plenocl.projection.plan import SampleColumns, column_chunks, depth_chunks, make_plan, runs
from plenocl.projection.weighting import (
    ApertureGrid,
    depth_coefficients,
    lens_index_map,
)

GRID = Grid((9, 13, 17), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.5, 1.5))


@pytest.mark.parametrize("shape, max_alloc, scratch", [
    ((9, 13, 17), 2**30, 2**25),          # everything in one piece
    ((9, 130, 170), 4 * 204 * 170, 2**25),  # depth slabs: one slice per buffer
    ((9, 13, 17), 2**30, 2**14),          # several aperture-column chunks
])
def test_plan_covers_everything_once_and_fits(small_camera, shape, max_alloc, scratch):
    grid = Grid(shape, x=GRID.x, y=GRID.y, z=GRID.z)
    ap = ApertureGrid.for_camera(small_camera)
    nkxp = 16
    plan = make_plan(grid, small_camera, ap, nkxp, max_alloc, scratch, "factorised")
    # slabs and column chunks tile their ranges without gaps or overlaps
    assert plan.slabs[0][0] == 0 and plan.slabs[-1][1] == shape[0]
    assert all(a[1] == b[0] for a, b in zip(plan.slabs, plan.slabs[1:]))
    assert all(4 * (b - a) * shape[1] * shape[2] <= max_alloc for a, b in plan.slabs)
    assert len(plan.slabs) > 1 or max_alloc > 4 * grid.size
    assert len(plan.columns) > 1 or scratch > 2**20
    assert plan.columns[0][0] == 0 and plan.columns[-1][1] == ap.n
    assert all(a[1] == b[0] for a, b in zip(plan.columns, plan.columns[1:]))
    # every chunk's light field and intermediate fit the scratch bound
    cols = SampleColumns.of(ap)
    row = 4 * small_camera.ml_count[1] * nkxp
    for i0, i1 in plan.columns:
        s0, s1 = cols.sample_range(i0, i1)
        assert (s1 - s0) * row <= min(max_alloc, scratch)
        assert plan.zchunk * (i1 - i0) * 4 * shape[1] * nkxp <= min(max_alloc, scratch)


def test_sample_columns_index_the_aperture_samples(small_camera):
    ap = ApertureGrid.for_camera(small_camera)
    i, _ = ap.samples()
    cols = SampleColumns.of(ap)
    for c in range(ap.n):
        s0, s1 = cols.sample_range(c, c + 1)
        np.testing.assert_array_equal(np.flatnonzero(i == c), np.arange(s0, s1))
    assert cols.sample_range(0, ap.n) == (0, len(i))


def test_plans_that_cannot_fit_are_refused(small_camera):
    ap = ApertureGrid.for_camera(small_camera)
    w, h = small_camera.pixels
    with pytest.raises(MemoryError, match="image needs"):
        make_plan(GRID, small_camera, ap, 16, 4 * w * h - 1, 2**20, "factorised")
    with pytest.raises(MemoryError, match="aperture column"):
        column_chunks(np.array([10, 50, 10]), 8, 40)


def test_runs_and_depth_chunks():
    mask = np.array([0, 1, 1, 0, 1, 1, 1, 1, 0, 1], bool)
    assert runs(mask) == [(1, 3), (4, 8), (9, 10)]
    assert runs(np.zeros(4, bool)) == []
    chunks = list(depth_chunks(2, 10, mask, 3))
    assert chunks == [(2, 1), (4, 3), (7, 1), (9, 1)]
    covered = [z for zc, n in chunks for z in range(zc, zc + n)]
    assert covered == [z for z in range(2, 10) if mask[z]]


def test_one_lattice_fit_recovers_an_affine_layout():
    ky, kx = np.mgrid[0:7, 0:9]
    m = np.array([[17.1, 0.3], [-0.2, 16.9], [40.0, 30.0]])
    centres = np.stack([kx, ky, np.ones_like(kx)], -1) @ m
    centres[2, 3] = np.nan  # a missing lens is ignored
    np.testing.assert_allclose(lattice_fit(centres), m, atol=1e-9)
    assert lattice_residual(centres, m) < 1e-9
    with pytest.raises(ValueError, match="too few"):
        lattice_fit(np.full((3, 3, 2), np.nan))
    line = np.zeros((1, 5, 2))
    line[0, :, 0] = np.arange(5)
    with pytest.raises(ValueError, match="collinear"):
        lattice_fit(line)


def test_lens_index_map_inverts_the_layout(small_camera):
    """Each lens's own array-plane position maps back to its integer index."""
    rotated = lens_camera(ml_rotation_deg=1.0)
    for cam in (small_camera, rotated):
        lmap = lens_index_map(cam)
        pos = cam.px_to_mm(cam.microlens_centers) / (
            1 + cam.ml_focal_length_mm / cam.image_distance_mm)
        kx, ky = lmap(pos[..., 0], pos[..., 1])
        rows, cols = np.mgrid[0:10, 0:12]
        np.testing.assert_allclose(kx, cols, atol=1e-6)
        np.testing.assert_allclose(ky, rows, atol=1e-6)
    assert lens_index_map(small_camera).axis_aligned
    assert not lens_index_map(rotated).axis_aligned


def test_depth_coefficients_hold_the_inverse(small_camera):
    coef = depth_coefficients(small_camera, GRID, lens_index_map(small_camera),
                              ApertureGrid.for_camera(small_camera))
    g, ginv = coef[:, 0:4].reshape(-1, 2, 2), coef[:, 10:14].reshape(-1, 2, 2)
    np.testing.assert_allclose(g @ ginv, np.broadcast_to(np.eye(2), g.shape), atol=1e-12)
    np.testing.assert_allclose(coef[:, 14:16], np.abs(ginv).sum(axis=2))
