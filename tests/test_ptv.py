"""Particle tracking through time (docs/design.md §7.3): linking, track smoothing, and
plenocl.track on a simulated recording at the paper's optics."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from vtkfiles import read_appended

import plenocl
from plenocl.ptv import Tracks, link, smooth

SEARCH = (1.0, 1.0, 3.0)
NOISE = (0.05, 0.05, 0.3)


def _series(n=150, frames=8, detect=1.0, seed=0, velocity=(1.5, -0.7, 0.4)):
    """True tracks, and per frame the detected particles (shuffled, noisy) with their
    true identities."""
    rng = np.random.default_rng(seed)
    p0 = rng.uniform(0, 40, (n, 3))
    truth = p0[:, None, :] + np.arange(frames)[None, :, None] * np.asarray(velocity)
    points, ids = [], []
    for k in range(frames):
        who = rng.permutation(np.flatnonzero(rng.random(n) < detect))
        points.append(truth[who, k] + rng.normal(0, NOISE, (len(who), 3)))
        ids.append(who)
    return truth, points, ids


def _identities(table, ids):
    return [{int(ids[k][j]) for k, j in enumerate(row) if j >= 0} for row in table]


@pytest.mark.parametrize("detect, gap", [(1.0, 0), (0.8, 1), (0.8, 0)])
def test_links_follow_each_particle_and_use_every_particle_once(detect, gap):
    truth, points, ids = _series(detect=detect, seed=int(10 * detect) + gap)
    v = np.array([1.5, -0.7, 0.4])
    table = link(points, SEARCH, first_step=lambda p: np.tile(v, (len(p), 1)), gap=gap)
    for k, pts in enumerate(points):  # a partition of every frame's particles
        assert sorted(table[table[:, k] >= 0, k]) == list(range(len(pts)))
    pure = [len(who) == 1 for who in _identities(table, ids)]  # tracks that never swap
    assert np.mean(pure) >= (1.0 if detect == 1.0 else 0.98)
    lengths = (table >= 0).sum(axis=1)
    if detect == 1.0:  # (a rare pair of close predictions may split a track)
        assert np.sum(lengths == len(points)) >= 0.97 * len(truth)
    elif gap:  # a particle lost in one frame keeps its track
        assert np.mean(lengths >= 4) > 0.75
        assert np.any((table[:, 1:-1] < 0) & (table[:, :-2] >= 0) & (table[:, 2:] >= 0))
    else:
        assert not np.any((table[:, 1:-1] < 0) & (table[:, :-2] >= 0) & (table[:, 2:] >= 0))


def test_crossing_particles_keep_their_tracks_by_their_history():
    """Two particles crossing 0.6 apart: nearest neighbours without the tracks' own
    straight-line predictions would swap them."""
    t = np.arange(8.0)
    a = np.column_stack([t - 3.5, np.zeros(8), np.zeros(8)])
    b = np.column_stack([3.5 - t, np.full(8, 0.6), np.zeros(8)])
    points = [np.array([a[k], b[k]]) for k in range(8)]
    first = lambda p: np.array([[1.0, 0, 0], [-1.0, 0, 0]])[: len(p)]  # noqa: E731
    table = link(points, SEARCH, first_step=first)
    assert table.shape == (2, 8) and np.all(table[0] == 0) and np.all(table[1] == 1)
    still = link(points, SEARCH)  # no prediction in the first step: the pairing by
    assert still.shape[0] > 2 or np.any(still[0] != 0)  # position alone breaks them


def test_smoothing_recovers_a_polynomial_track_exactly_and_its_derivatives():
    t = np.arange(9.0)
    pos = np.stack([2 + 0.5 * t - 0.1 * t**2, -t, 3 + 0.02 * t**2], axis=1)[None]
    fit = smooth(pos, np.full(pos.shape, 0.1), dt=0.5, window=5, degree=2)
    np.testing.assert_allclose(fit.positions, pos, atol=1e-10)
    velocity = np.stack([0.5 - 0.2 * t, -np.ones(9), 0.04 * t], axis=1) / 0.5
    np.testing.assert_allclose(fit.velocities[0], velocity, atol=1e-9)
    np.testing.assert_allclose(fit.accelerations[0], np.tile([-0.8, 0, 0.16], (9, 1)),
                               atol=1e-9)


def test_smoothing_lowers_the_noise_and_states_it():
    """A line with noise: the smoothed steps err less than the measured ones, and the
    velocity's stated deviation matches its scatter."""
    rng = np.random.default_rng(3)
    n, f, sigma = 4000, 8, np.array(NOISE)
    truth = np.arange(f)[None, :, None] * np.array([1.0, 2.0, -0.5]) + np.zeros((n, 1, 3))
    measured = truth + rng.normal(0, sigma, (n, f, 3))
    fit = smooth(measured, np.broadcast_to(sigma, measured.shape), dt=1.0, window=7,
                 degree=1)
    raw = np.std(np.diff(measured, axis=1) - np.diff(truth, axis=1), axis=(0, 1))
    smoothed = np.std(np.diff(fit.positions, axis=1) - np.diff(truth, axis=1), axis=(0, 1))
    assert np.all(smoothed < 0.6 * raw)
    scatter = np.std(fit.velocities[:, 3] - [1.0, 2.0, -0.5], axis=0)
    np.testing.assert_allclose(fit.velocity_sigma[:, 3].mean(axis=0), scatter, rtol=0.1)


def test_smoothing_spans_gaps_and_leaves_lone_particles_without_velocity():
    pos = np.full((2, 6, 3), np.nan)
    pos[0] = np.arange(6.0)[:, None] * [1.0, 0.0, 2.0]
    pos[0, 2] = np.nan
    pos[1, 3] = [1.0, 2.0, 3.0]
    fit = smooth(pos, np.ones(pos.shape), dt=1.0, window=3, degree=1)
    assert np.all(np.isnan(fit.positions[0, 2])) and np.isnan(fit.velocities[1, 3]).all()
    np.testing.assert_allclose(fit.velocities[0, [0, 1, 3, 4, 5]], [[1, 0, 2]] * 5)
    np.testing.assert_allclose(fit.positions[1, 3], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("bad", [dict(window=4), dict(window=1), dict(degree=4)])
def test_smoothing_refuses_bad_windows_and_degrees(bad):
    with pytest.raises(ValueError, match="window|degree"):
        smooth(np.zeros((1, 5, 3)), np.ones((1, 5, 3)), 1.0, **{"window": 5, "degree": 1,
                                                                **bad})


def test_tracks_keep_long_tracks_and_give_steps():
    measured = np.full((3, 5, 3), np.nan)
    measured[0] = np.arange(5.0)[:, None]
    measured[1, :2] = 1.0
    measured[2, 1:] = np.arange(4.0)[:, None] * 2
    tracks = Tracks.from_measured(measured, np.ones(measured.shape), np.ones((3, 5)), 0.1,
                                  window=3, degree=1)
    assert list(tracks.lengths) == [5, 2, 4]
    long = tracks.longer_than(4)
    assert len(long.positions) == 2 and long.dt == 0.1
    np.testing.assert_allclose(long.displacements()[0], np.ones((4, 3)))
    np.testing.assert_allclose(long.velocities[1, 1:], np.full((4, 3), 20.0))


@pytest.fixture(scope="module")
def recording(queue):
    """Six frames at the paper's optics on 24 x 16 lenses, 0.15 particles per microlens
    moving uniformly, and the camera's projector."""
    from plenocl.bench.accuracy_section import UNIFORM, paper_optics
    from plenocl.bench.tracking_section import simulate_series

    cam, grid = paper_optics((24, 16))
    series = simulate_series(cam, grid, 0.15, 6, 11, queue, UNIFORM)
    return series, grid, plenocl.Projector(cam, grid, queue)


@pytest.fixture(scope="module")
def one_camera(recording):
    """The recording tracked by its camera, and the progress calls it made."""
    series, _, proj = recording
    calls = []
    tracks = plenocl.track(series.frames, proj, dt=1e-3,
                           progress=lambda done, total: calls.append((done, total)))
    return tracks, calls


def test_track_follows_particles_and_smoothing_beats_each_frame(recording, one_camera):
    """plenocl.track on ray-traced frames: most particles tracked, few ghosts, lateral
    steps within 0.1 voxel, and the smoothed tracks' depth steps better than the
    measured positions'; its progress reported step by step."""
    from plenocl.bench.tracking_section import track_errors

    series, grid, proj = recording
    tracks, calls = one_camera
    total = 6 * (1 + plenocl.TrackSettings().refits)  # each frame, then each refit
    assert calls == [(k, total) for k in range(1, total + 1)]
    assert tracks.positions.shape[1:] == (6, 3) and tracks.dt == 1e-3
    assert np.all(tracks.lengths >= 4)
    row = track_errors(tracks, series.truth, grid, 1.0)
    assert row["tracked"] >= 0.6 and row["ghosts"] <= 0.2
    smoothed, measured = row["smoothed"], row["measured"]
    assert smoothed["lateral"] <= 0.1 and smoothed["depth"] < 0.8 * measured["depth"]
    speed = np.nanmedian(tracks.velocities, axis=(0, 1)) * 1e-3
    np.testing.assert_allclose(speed, np.array([2.3, -1.4, 1.7]) * grid.spacing[::-1],
                               atol=0.2 * 0.133)


@pytest.mark.one_device
def test_track_with_two_cameras_sees_the_steps_sharper_in_depth(recording, one_camera, queue):
    """plenocl.track with two cameras 25 degrees apart (docs/design.md §6.7) on the same
    particles, each camera's frames ray traced: one joint volume per frame, its particles
    fitted to both cameras' images; as many particles tracked as by one camera, the
    measured depth steps (and those in the focal zone) sharper than the one camera's, and
    the smoothed ones no worse; a camera short of a frame is refused by name. (In the
    focal zone two cameras measure the depth steps within 0.22 voxel, one camera within
    0.41 since its fit damps along each line of sight, 0.71 before.)"""
    from plenocl.bench.accuracy_section import paper_optics
    from plenocl.bench.tracking_section import track_errors
    from plenocl.camera import Pose

    series, grid, _ = recording
    cam, _ = paper_optics((24, 16))
    projs = [plenocl.Projector(cam.with_pose(Pose((0.0, turn, 0.0), (0.0, 0.0, 0.0))), grid,
                               queue) for turn in (-12.5, 12.5)]
    frames = [[plenocl.simulate_image(p.camera, series.truth[:, k], 2e4, seed=500 + 10 * j + k,
                                      rays_per_particle=2000, blur_px=0.8, photon_noise=True,
                                      background=20.0, read_noise=3.0, queue=queue)
               for k in range(6)] for j, p in enumerate(projs)]
    two = track_errors(plenocl.track(frames, projs, dt=1e-3), series.truth, grid, 1.0)
    one = track_errors(one_camera[0], series.truth, grid, 1.0)
    assert two["tracked"] >= max(0.6, one["tracked"] - 0.05) and two["ghosts"] <= 0.2
    assert two["measured"]["depth"] < 0.7 * one["measured"]["depth"], (two, one)
    assert two["measured"]["focal_depth"] < 0.6 * one["measured"]["focal_depth"], (two, one)
    assert two["smoothed"]["depth"] <= one["smoothed"]["depth"]
    assert two["smoothed"]["lateral"] <= 0.1
    with pytest.raises(ValueError, match="camera 2 has 5 frames but camera 1 has 6"):
        plenocl.track([frames[0], frames[1][:5]], projs, dt=1.0)
    with pytest.raises(ValueError, match="one sequence of frames per projector"):
        plenocl.track([frames[0]], projs, dt=1.0)


def test_track_refuses_bad_recordings(recording):
    series, _, proj = recording
    frames = series.frames
    with pytest.raises(ValueError, match="at least 4 frames"):
        plenocl.track(frames[:3], proj, dt=1.0)
    with pytest.raises(ValueError, match="frame 2 is"):
        plenocl.track(frames[:2] + [frames[2][:-1]] + frames[3:], proj, dt=1.0)
    # a frame's pixels checked before the first is reconstructed, naming the frame
    blank, holed = np.zeros_like(frames[4]), np.array(frames[4], float)
    holed[3, 5] = np.nan
    for bad, message in ((blank, "frame 4 is blank"), (holed, "frame 4 contains 1 NaN")):
        def reconstructed(*args, **kwargs):
            raise AssertionError("a frame was reconstructed before the bad one was named")

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(importlib.import_module("plenocl.pipeline.track"),
                          "run_reconstruction", reconstructed)
            with pytest.raises(ValueError, match=message):
                plenocl.track(frames[:4] + [bad] + frames[5:], proj, dt=1.0)
    for dt in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="dt"):
            plenocl.track(frames, proj, dt=dt)
    for bad in (dict(gap=-1), dict(window=4), dict(min_length=1), dict(search=(1, 1))):
        with pytest.raises(ValueError, match="TrackSettings"):
            plenocl.TrackSettings(**bad)
    with pytest.raises(TypeError, match="unknown keyword"):
        plenocl.track(frames, proj, dt=1.0, windows=5)


def test_track_warns_when_frames_are_not_consecutive(recording):
    series, _, proj = recording
    shuffled = [series.frames[k] for k in (0, 5, 1, 4, 2, 3)]
    with pytest.warns(UserWarning, match="found a partner"):
        plenocl.track(shuffled, proj, dt=1.0, min_length=2, refits=0)


def _grid_tracks(field, n=4000, frames=6, noise=0.01, seed=1):
    """Tracks of particles moved each frame by ``field(positions)`` (mm), in a 10 x 6 x
    8 mm grid of 50 x 30 x 40 voxels."""
    grid = plenocl.Grid((40, 30, 50), x=(-5, 5), y=(-3, 3), z=(-4, 4))
    rng = np.random.default_rng(seed)
    pos = [np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-3, 3, n),
                            rng.uniform(-4, 4, n)])]
    for _ in range(frames - 1):
        pos.append(pos[-1] + field(pos[-1]))
    truth = np.stack(pos, axis=1)
    measured = truth + rng.normal(0, noise, truth.shape)
    tracks = Tracks.from_measured(measured, np.full(truth.shape, noise), np.ones((n, frames)),
                                  1.0, window=5, degree=2)
    return grid, tracks


def test_binned_tracks_give_the_field_and_its_uncertainty():
    """A linear shear: each window's vector is the field at its centre (the samples
    moved there along the local gradient), its stated sigma the scatter over the
    windows."""
    from plenocl import bin_tracks

    shear = lambda p: np.column_stack([0.2 + 0.02 * p[:, 1], np.full(len(p), -0.1),  # noqa: E731
                                       0.05 + 0.01 * p[:, 0]])
    grid, tracks = _grid_tracks(shear)
    res = bin_tracks(tracks, grid, window=(16, 12, 20), step=(8, 6, 10))
    assert res.u.shape == (4, 4, 4) and res.valid.all() and res.window == (16, 12, 20)
    assert res.step == (8, 6, 10)
    x, y, z = res.positions_mm(grid.spacing, (grid.z[0] + 0.1, grid.y[0] + 0.1,
                                              grid.x[0] + 0.1))
    vox = np.array(grid.spacing[::-1])
    expected_u = (0.2 + 0.02 * y)[None, :, None] / vox[0]
    expected_w = (0.05 + 0.01 * x)[None, None, :] / vox[2]
    np.testing.assert_allclose(res.u, np.broadcast_to(expected_u, res.u.shape), atol=0.01)
    np.testing.assert_allclose(res.w, np.broadcast_to(expected_w, res.w.shape), atol=0.01)
    np.testing.assert_allclose(res.v, -0.1 / vox[1], atol=0.01)
    error = res.v + 0.1 / vox[1]
    assert 0.5 < np.std(error) / np.mean(res.sigma_v) < 2.0


def test_binning_counts_only_the_chosen_frames_and_leaves_sparse_windows_empty():
    from plenocl import bin_tracks

    grid, tracks = _grid_tracks(lambda p: np.tile([0.1, 0.0, 0.0], (len(p), 1)), n=60)
    every = bin_tracks(tracks, grid, window=(16, 12, 20), min_samples=3)
    one = bin_tracks(tracks, grid, window=(16, 12, 20), frames=[2], min_samples=3)
    assert every.refinement["samples"] == 5 * 60 and one.refinement["samples"] == 60
    assert one.valid.sum() < every.valid.sum()
    assert np.all(np.isnan(one.u[~one.valid])) and np.all(one.masked == ~one.valid)
    with pytest.raises(ValueError, match="must be positive and fit the grid"):
        bin_tracks(tracks, grid, window=(64, 12, 20))


def test_tracks_files_round_trip_and_open_as_poly_lines(tmp_path):
    """.npz holds every array (read back equal); .vtu holds one poly-line cell per track
    of two or more positions, with its velocity, speed, frame and track per point."""
    measured = np.full((3, 5, 3), np.nan)
    measured[0] = np.arange(5.0)[:, None] * [1.0, 0.5, -0.2]
    measured[1, 1:4] = [2.0, 1.0, 0.0]
    measured[2, 2] = 1.0  # a lone particle: no line
    tracks = Tracks.from_measured(measured, np.full(measured.shape, 0.1), np.ones((3, 5)),
                                  0.01, window=3, degree=1)
    back = Tracks.load(tracks.save(tmp_path / "t.npz"))
    for name in ("positions", "measured", "velocities", "velocity_sigma", "intensities"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tracks, name))
    assert back.dt == 0.01
    raw = tracks.save(tmp_path / "t.vtu").read_bytes()
    header = raw[:raw.index(b"<AppendedData")].decode()  # then pyevtk's raw binary arrays
    assert 'NumberOfPoints="8" NumberOfCells="2"' in header
    for name in ("velocity", "speed", "frame", "track"):
        assert f'Name="{name}"' in header
    raw = tracks.save(tmp_path / "s.vtu", seconds=True).read_bytes()  # dt in seconds: m/s
    header = raw[:raw.index(b"<AppendedData")].decode()
    for name in ("velocity_m_per_s", "speed_m_per_s", "frame", "track"):
        assert f'Name="{name}"' in header
    assert 'Name="velocity"' not in header
    # a run's frames numbered from 100: the lines' frame is the number, as the store's
    _, arrays = read_appended(tracks.save(tmp_path / "n.vtu", frames=range(100, 105)))
    np.testing.assert_array_equal(arrays["frame"][0], [100, 101, 102, 103, 104, 101, 102, 103])
    _, arrays = read_appended(tmp_path / "t.vtu")
    np.testing.assert_array_equal(arrays["frame"][0], [0, 1, 2, 3, 4, 1, 2, 3])
    with pytest.raises(ValueError, match="frames names 3 frame number"):
        tracks.save(tmp_path / "x.vtu", frames=[1, 2, 3])
    with pytest.raises(ValueError, match="not a plenocl tracks file"):
        np.savez(tmp_path / "other.npz", x=np.zeros(3))
        Tracks.load(tmp_path / "other.npz")
    with pytest.raises(ValueError, match=r"\.npz or \.vtu"):
        tracks.save(tmp_path / "t.csv")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["n.vtu", "other.npz", "s.vtu",
                                                          "t.npz", "t.vtu"]


def test_the_tracks_figure_is_written(tmp_path):
    from plenocl.plot.tracks import plot_tracks

    grid, tracks = _grid_tracks(lambda p: np.tile([0.1, 0.0, 0.05], (len(p), 1)), n=30)
    plot_tracks(tmp_path / "tracks.png", tracks)
    assert (tmp_path / "tracks.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tracking_demo_writes_its_files_and_beats_the_pair_in_depth(tmp_path, capsys):
    """plenocl demo tracking (5 frames of the small boundary layer): the tracks, their
    ParaView lines, the figure, the binned field and a summary whose binned field errs
    less in depth than the pair chain on the same frames."""
    import json

    from plenocl.cli import main

    assert main(["demo", "tracking", "--out", str(tmp_path), "--frames", "5"]) == 0
    assert "binned field" in capsys.readouterr().out
    for name in ("tracks.npz", "tracks.vtu", "fig_tracks.png", "field_tracks.npz"):
        assert (tmp_path / name).stat().st_size > 0
    s = json.loads((tmp_path / "summary.json").read_text())
    tracked, pair = s["field_tracks"], s["field_pair"]
    assert s["particles_per_step"]["tracked"] > 0.3 and tracked["valid"] > 0.8
    assert tracked["depth_voxels"] < 0.7 * pair["depth_voxels"]
    assert tracked["lateral_u_inf"] < 0.05
    assert len(Tracks.load(tmp_path / "tracks.npz").positions) == s["tracks"]
    # the binned field at its windows' places on the grid (it was written from 0 mm)
    from plenocl.demo.boundary_layer import scenario
    from plenocl.vectorfield import read_npz

    grid = scenario("small").grid
    _, arrays = read_npz(tmp_path / "field_tracks.npz")
    for name, (lo, hi) in (("x_mm", grid.x), ("y_mm", grid.y), ("z_mm", grid.z)):
        centres = np.asarray(arrays[name])
        assert lo < centres.min() and centres.max() < hi, (name, centres, lo, hi)
        assert abs(centres.min() - lo - (hi - centres.max())) < 0.5 * np.ptp(centres) / max(
            len(centres) - 1, 1), name  # about centred on the grid
