"""A rerun after a change of the tables tests/test_rerun.py leaves out (issue 44): the
particle refinement (the kept volumes correlated again), a frame correction (the pair
redone) and the grid (refused, then redone with ``redo``); each checks the stored data
against a run of the changed experiment into a fresh folder."""

from __future__ import annotations

import numpy as np
import pytest
from test_rerun import (  # noqa: F401  (the fixtures)
    PAIR,
    VOLUMES,
    _edit,
    _fresh,
    _record_matches_the_run,
    _rerun,
    done,
    frames,
)

import plenocl
from plenocl.io import write_tiff
from plenocl.io.fieldformat import read_field


def _same_field(folder, fresh):
    got, want = read_field(folder / PAIR), read_field(fresh / "pairs" / "pair_00000.npz")
    for key in ("displacement", "valid", "velocity"):
        np.testing.assert_array_equal(got[key], want[key])


def test_a_changed_particles_table_correlates_the_kept_volumes_again(done, monkeypatch,  # noqa: F811
                                                                     tmp_path_factory):
    volumes = (done / VOLUMES).read_bytes()
    _edit(done, "[particles]\nenabled = false", "[particles]\nenabled = true")
    s, said = _rerun(done, monkeypatch)
    assert s.processed == [0] and s.redone == [0]
    assert any("particles.enabled changed" in m and "kept volumes" in m for m in said), said
    assert (done / VOLUMES).read_bytes() == volumes
    _same_field(done, _fresh(done, tmp_path_factory))
    _record_matches_the_run(done)


def test_a_dark_frame_added_redoes_the_pair(done, tmp_path_factory):  # noqa: F811
    write_tiff(done / "dark.tif", np.full((408, 408), 40, np.uint16))
    _edit(done, 'pattern = "frame_*.tif"', 'pattern = "frame_*.tif"\ndark = "dark.tif"')
    s, said = _rerun(done)
    assert s.processed == [0] and s.redone == [0]
    assert any("images.dark changed" in m and "redoing" in m for m in said), said
    _same_field(done, _fresh(done, tmp_path_factory))
    _record_matches_the_run(done)


def test_another_grid_is_refused_then_redone_with_redo(done, tmp_path_factory):  # noqa: F811
    field = (done / PAIR).read_bytes()
    grid = plenocl.Grid.from_toml(done / "grid.toml")
    plenocl.Grid(grid.shape, grid.x, grid.y, (-1.4, 1.4), grid.rotation_deg).to_toml(
        done / "grid.toml")
    with pytest.raises(ValueError, match="pair 0: the grid changed since it was made"):
        plenocl.run(done / "experiment.toml", progress=False, log=lambda _: None)
    assert (done / PAIR).read_bytes() == field
    s = plenocl.run(done / "experiment.toml", progress=False, log=lambda _: None, redo=True)
    assert s.processed == [0] and s.redone == [0]
    _same_field(done, _fresh(done, tmp_path_factory))
    _record_matches_the_run(done)
