"""The error budget's known motions (plenocl/bench/accuracy_section.py): the rotation's
truth at the window centres and its errors."""

from __future__ import annotations

import dataclasses

import numpy as np

from plenocl.bench.accuracy_section import (
    ROTATION,
    SHIFT_VOX,
    UNIFORM,
    budget_errors,
    paper_optics,
)
from plenocl.piv import PIVResult


def result_on(grid, u, v, w) -> PIVResult:
    z, y, x = (np.linspace(10, n - 11, k) for n, k in zip(grid.shape, (5, 3, 4)))
    ones = np.ones((5, 3, 4), bool)
    comps = [np.broadcast_to(c, (5, 3, 4)).astype(float) for c in (u, v, w)]
    return PIVResult(x, y, z, *comps, ones, np.full((5, 3, 4), np.nan), ~ones, ~ones,
                     (32, 32, 32))


def test_the_rotation_moves_particles_in_depth_about_the_lateral_x_axis():
    cam, grid = paper_optics((48, 32))
    pos = np.array([[1.0, 2.0, 0.0], [0.5, 0.0, 8.0], [0.0, -1.0, -5.0]])
    pa, pb = ROTATION.positions(pos)
    np.testing.assert_allclose(pa[:, 0], pos[:, 0])          # x is the axis
    np.testing.assert_allclose(np.hypot(pb[:, 1], pb[:, 2]), np.hypot(pos[:, 1], pos[:, 2]))
    d = pb - pa
    # a point off the axis in y moves in depth, one deep along the axis moves in y
    assert abs(d[0, 2]) > 0.05 and abs(d[0, 1]) < 1e-3
    assert abs(d[1, 1]) > 0.2 and abs(d[1, 2]) < 1e-3
    np.testing.assert_allclose(UNIFORM.positions(pos)[1] - UNIFORM.positions(pos)[0],
                               np.broadcast_to(SHIFT_VOX * np.array(grid.spacing[::-1]),
                                               pos.shape), atol=1e-4)


def test_budget_errors_are_zero_for_the_truth_and_see_a_depth_error():
    cam, grid = paper_optics((48, 32))
    res = result_on(grid, 0.0, 0.0, 0.0)
    truth = ROTATION.displacement(res, grid)
    exact = dataclasses.replace(res, u=truth[0], v=truth[1], w=truth[2])
    e = budget_errors(exact, grid, ROTATION)
    assert e["lateral"] < 1e-9 and e["depth"] < 1e-9 and e["valid"] == 1.0
    off = dataclasses.replace(exact, w=truth[2] + 0.5)
    e = budget_errors(off, grid, ROTATION)
    assert abs(e["depth"] - 0.5) < 1e-9 and e["lateral"] < 1e-9
    assert abs(e["bias"][2] - 0.5) < 1e-9
    uniform = result_on(grid, *SHIFT_VOX)
    assert budget_errors(uniform, grid)["lateral"] < 1e-12
