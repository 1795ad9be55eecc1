"""The field-size benchmark's bookkeeping (plenocl/bench/fieldsize.py): matching found
positions to the truth and splitting errors by distance from the axis and by depth."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl.bench.fieldsize import (
    MATCH,
    RADII_MM,
    ZONES_MM,
    SizeSplit,
    Stage,
    matched,
    off_axis_ratio,
    pooled,
    split_table,
)


def test_each_true_position_takes_its_nearest_found_one_within_the_match_ellipsoid():
    truth = np.array([[10.0, 10.0, 10.0], [20.0, 20.0, 20.0], [30.0, 30.0, 30.0]])
    found = np.array([[20.5, 20.0, 22.0], [10.2, 9.9, 10.5], [30.0, 31.5, 30.0]])
    it, ifound = matched(found, truth)
    assert it.tolist() == [0, 1] and ifound.tolist() == [1, 0]  # the third is 1.5 off in y
    assert MATCH[1] < 1.5
    assert matched(np.zeros((0, 3)), truth)[0].size == 0


def test_errors_split_by_radius_and_depth_zone_into_their_own_bins():
    rng = np.random.default_rng(2)
    r = rng.uniform(0, 30, 3000)
    phi = rng.uniform(0, 2 * np.pi, 3000)
    z = rng.uniform(-10, 10, 3000)
    where = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    err = np.zeros((3000, 3))
    err[:, 0] = r / 10           # lateral error grows with the radius
    err[:, 2] = np.abs(z) < 2    # depth error 1 in the focal zone only
    st = Stage("test", where, err)
    rows = st.by_radius()
    assert len(rows) == len(RADII_MM)
    lateral = [row[0] for row in rows]
    assert np.all(np.diff(lateral) > 0)
    assert rows[0][0] == pytest.approx(np.sqrt(np.mean((r[r < 5] / 10) ** 2) / 2))
    zones = st.by_zone()
    assert len(zones) == len(ZONES_MM)
    assert zones[0][1] == pytest.approx(1.0) and zones[1][1] == zones[2][1] == 0.0
    assert sum(n for *_, n in zones) == 3000
    assert off_axis_ratio(st)[0] == pytest.approx(rows[4][0] / rows[0][0])
    split = SizeSplit((10, 8), (4, 5, 6), 3000, [st], [1.0] * 6, [0.9] * 6, 1.0)
    text = split_table(split)
    assert "10 x 8 lenses" in text and text.count("\n") == 4
    assert Stage("few", where[:2], err[:2]).rms()[2] == 2
    assert np.isnan(Stage("few", where[:2], err[:2]).rms()[0])


def test_pooled_scenes_take_each_bins_rms_over_all_their_entries():
    rng = np.random.default_rng(5)

    def scene(scale: float, n: int) -> SizeSplit:
        where = np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(-10, 10, n)])
        st = Stage("vectors", where, rng.normal(0, scale, (n, 3)))
        return SizeSplit((10, 8), (4, 5, 6), n, [st], [1.0 + scale] * 6, [scale] * 6, 2.0)

    one, two = scene(0.1, 400), scene(0.3, 1200)
    both = pooled([one, two])
    assert both.particles == 1600 and both.seconds == 4.0
    assert both.peaks_per_particle == pytest.approx([1.2] * 6)
    err = np.concatenate([one.stages[0].error, two.stages[0].error])
    lat, dep, n = both.stages[0].rms()
    assert n == 1600 and dep == pytest.approx(np.sqrt(np.mean(err[:, 2] ** 2)))
    # weighted by entries, not the mean of the two scenes' RMS
    assert dep != pytest.approx((one.stages[0].rms()[1] + two.stages[0].rms()[1]) / 2, rel=1e-3)
    with pytest.raises(ValueError, match="at least one"):
        pooled([])


def test_the_sight_frame_puts_an_error_along_the_line_of_sight_in_depth_alone():
    """An error along each entry's line of sight is all "depth" in the sight frame, and
    one across it all "lateral", though off the axis the first shows in x and y too."""
    from plenocl import Camera, Grid
    from plenocl.bench.fieldsize import sight_stage
    from plenocl.optics.sightline import line_of_sight

    camera = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (40, 30), 0.0074, (700, 530))
    grid = Grid((20, 30, 40), x=(10.0, 30.0), y=(-5.0, 10.0), z=(-4.0, 4.0))
    dz, dy, dx = grid.spacing
    where = np.array([[20.0, 5.0, 1.0], [12.0, -3.0, -2.0], [0.0, 0.0, 0.0]])
    line = line_of_sight(camera, where)
    along = Stage("vectors", where, 0.5 * line / np.array([dx, dy, dz]))
    assert np.abs(along.error[:2, :2]).max() > 0.05
    turned = sight_stage(along, camera, grid)
    np.testing.assert_allclose(turned.error[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(turned.error[:, 2], 0.5 / dz)
    across = np.cross(line, [0.0, 0.0, 1.0]) + [[0, 0, 0], [0, 0, 0], [1.0, 0, 0]]
    turned = sight_stage(Stage("vectors", where, across / np.array([dx, dy, dz])), camera,
                         grid)
    np.testing.assert_allclose(turned.error[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.hypot(*turned.error[:, :2].T),
                               np.linalg.norm(across, axis=1) / ((dx + dy) / 2))
