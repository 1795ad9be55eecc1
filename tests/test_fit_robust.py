"""One bad particle never ends a run (issue 44): the fit to the raw images
(plenocl/piv/imagefit.py) and the particle refinement (plenocl/piv/refinement.py) started
from bad positions (outside the grid, far in depth, NaN, on the grid's faces) drop those
particles, count them and fit the rest; plenocl.track with a diverging particle returns
its tracks and counts it."""

from __future__ import annotations

import dataclasses
import importlib
import json

import numpy as np
import pytest

import plenocl
from plenocl.bench.accuracy_section import paper_optics
from plenocl.io import write_tiff
from plenocl.piv import piv3d
from plenocl.piv.imagefit import (
    GRID_MARGIN_VOXELS,
    PRIOR_VOXELS,
    ImageFit,
    ImageFitSettings,
    RefinedPeaks,
)
from plenocl.piv.refinement import pair_particles, refine_with_particles
from plenocl.ptv import Tracks
from plenocl.reference.simulate import trace_particles

CAM, GRID = paper_optics((32, 24))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm
#: Starts no fit can keep: NaN, infinite, 66 mm in front of a 20 mm deep grid (beyond
#: the camera's focal length: the depth that raised in issue 44), far behind it, and
#: laterally outside it and its margin.
BAD_STARTS = np.array([[np.nan, 0.0, 0.0], [0.0, 0.0, np.inf], [0.1, 0.2, -76.0],
                       [0.0, 0.0, 65.0], [GRID.x[1] + 1.0, 0.0, 0.0],
                       [0.0, GRID.y[0] - 1.0, 3.0]])


def _inside(points: np.ndarray, grid=GRID) -> np.ndarray:
    """Finite and inside ``grid`` or within the fit's margin of its faces."""
    index = grid.to_index(np.nan_to_num(points, nan=1e9, posinf=1e9, neginf=-1e9))
    margin = np.asarray(GRID_MARGIN_VOXELS)
    high = np.asarray(grid.shape[::-1]) - 0.5 + margin
    return np.all(np.isfinite(points), axis=1) & np.all(
        (index >= -0.5 - margin) & (index <= high), axis=1)


def _check_kept(out, n: int) -> None:
    """Every row either kept (finite, inside the grid or its margin) or dropped (NaN),
    and counted."""
    assert out.positions.shape == (n, 3) and out.kept.shape == (n,)
    assert np.all(_inside(out.positions[out.kept]))
    assert np.all(np.isfinite(out.sigma[out.kept])) and np.all(out.intensities[out.kept] >= 0)
    assert np.all(np.isnan(out.positions[~out.kept]))
    assert out.dropped == n - np.count_nonzero(out.kept)


@pytest.fixture(scope="module")
def scene():
    """Six ray-traced particles 4-8 mm from the focal plane (test_imagefit.py's) and
    their starts 1.5 voxels off in depth (0.3 laterally)."""
    rng = np.random.default_rng(1)
    true = np.column_stack([rng.uniform(-1.5, 1.5, 6), rng.uniform(-1.2, 1.2, 6),
                            [-8.0, -6.0, -4.0, 4.0, 6.0, 8.0]])
    img = trace_particles(CAM, true, 4000.0, 40_000, seed=3, blur_px=0.8)
    img = img + 20.0 + np.random.default_rng(3).normal(0.0, 1.0, img.shape)
    return true + np.array([0.3, -0.3, 1.5]) * VOXEL, img


def _good_fit_errors(out, true: np.ndarray, rows) -> np.ndarray:
    return np.abs(out.positions[rows] - true) / VOXEL


def test_bad_starts_are_dropped_and_counted_and_the_rest_converge(scene):
    """Bad starts mixed between good ones: no exception, exactly the bad ones dropped,
    the good ones fitted as well as without them (the fit of test_imagefit.py)."""
    start, img = scene
    true = start - np.array([0.3, -0.3, 1.5]) * VOXEL
    fit = ImageFit(CAM, GRID, [img], ImageFitSettings(rays=400))
    mixed = np.insert(start, [1, 2, 2, 4, 5, 6], BAD_STARTS, axis=0)
    good = _inside(mixed)
    assert np.count_nonzero(~good) == len(BAD_STARTS)
    out = fit.fit(0, mixed)
    _check_kept(out, len(mixed))
    np.testing.assert_array_equal(out.kept, good)
    assert out.dropped == len(BAD_STARTS)
    err = _good_fit_errors(out, true, good)
    assert err[:, 2].max() < 0.4 and err[:, :2].max() < 0.15, err
    alone = fit.fit(0, start)  # the bad starts did not disturb the good fits
    assert alone.dropped == 0
    np.testing.assert_allclose(out.positions[good], alone.positions, atol=1e-9)


def test_only_bad_starts_give_no_particles_and_no_error(scene):
    _, img = scene
    fit = ImageFit(CAM, GRID, [img])
    out = fit.fit(0, BAD_STARTS)
    assert out.dropped == len(BAD_STARTS) and not out.kept.any()
    _check_kept(out, len(BAD_STARTS))
    index = fit.refine(0, GRID.to_index(np.nan_to_num(BAD_STARTS, nan=1e3, posinf=1e3)))
    assert np.all(np.isnan(index))


def test_particles_on_the_grid_faces_stay_inside_or_are_dropped(scene):
    """Starts on every face of the grid (and its corners), where the image pulls some
    out: each one kept inside the grid's margin or dropped, never beyond it."""
    _, img = scene
    lo = np.array([GRID.x[0], GRID.y[0], GRID.z[0]])
    hi = np.array([GRID.x[1], GRID.y[1], GRID.z[1]])
    centre = (lo + hi) / 2
    faces = []
    for axis in range(3):
        for end in (lo, hi):
            p = centre.copy()
            p[axis] = end[axis]
            faces.append(p)
    faces += [lo, hi, np.array([lo[0], hi[1], lo[2]])]
    out = ImageFit(CAM, GRID, [img], ImageFitSettings(iterations=6)).fit(0, np.array(faces))
    _check_kept(out, len(faces))


def test_particles_fitted_beyond_the_margin_are_dropped():
    """Particles 8 voxels behind the grid's far face, started just inside its margin
    (4 voxels): the image pulls them out of it, and each is dropped."""
    rng = np.random.default_rng(3)
    true = np.column_stack([rng.uniform(-1.0, 1.0, 4), rng.uniform(-1.0, 1.0, 4),
                            np.full(4, GRID.z[1] + 8 * VOXEL[2])])
    img = trace_particles(CAM, true, 4000.0, 40_000, seed=1, blur_px=0.8) + 20.0
    start = true.copy()
    start[:, 2] = GRID.z[1] + (GRID_MARGIN_VOXELS[2] - 0.2) * VOXEL[2]
    fit = ImageFit(CAM, GRID, [img], ImageFitSettings(iterations=8))
    assert fit.inside(start).all()
    out = fit.fit(0, start)
    _check_kept(out, 4)
    assert out.dropped == 4  # the fit follows the image out


def test_a_matrix_the_solver_refuses_drops_only_its_particle(scene, monkeypatch):
    """NumPy's stacked solver refuses a whole stack for one singular matrix: the fit
    then solves particle by particle (the same steps) and drops only the particle whose
    own matrix is refused (here forced: the first one solved alone)."""
    start, img = scene
    fit = ImageFit(CAM, GRID, [img])
    plain = fit.fit(0, start)
    solve, alone = np.linalg.solve, []

    def refusing(a, b):
        if len(a) > 1:
            raise np.linalg.LinAlgError("Singular matrix")
        alone.append(1)
        if len(alone) == 1:
            raise np.linalg.LinAlgError("Singular matrix")
        return solve(a, b)

    monkeypatch.setattr(np.linalg, "solve", refusing)
    out = fit.fit(0, start)
    _check_kept(out, len(start))
    assert out.dropped == 1 and not out.kept[0]
    true = start - np.array([0.3, -0.3, 1.5]) * VOXEL
    err = _good_fit_errors(out, true[1:], out.kept)
    assert err[:, 2].max() < 0.4 and err[:, :2].max() < 0.15, err
    # the others barely move (the dropped particle has left their model image)
    assert np.all(np.abs(out.positions[1:] - plain.positions[1:]) / VOXEL < 0.1)


def test_device_fit_drops_the_same_bad_starts(scene, queue):
    start, img = scene
    mixed = np.vstack([start, BAD_STARTS])
    out = ImageFit(CAM, GRID, [img], ImageFitSettings(chunk=4), queue=queue).fit(0, mixed)
    _check_kept(out, len(mixed))
    np.testing.assert_array_equal(out.kept, np.arange(len(mixed)) < len(start))


class _DroppingFit:
    """A stand-in for :class:`ImageFit` in the pairing: the peaks as they are, except
    every ``every``-th of each exposure's, which the fit dropped (NaN)."""

    def __init__(self, every: int) -> None:
        self.every, self.dropped = every, 0

    def refine_pair(self, peaks_a: np.ndarray, peaks_b: np.ndarray):
        out = []
        for peaks in (peaks_a, peaks_b):
            peaks = np.array(peaks, float)
            peaks[:: self.every] = np.nan
            self.dropped += len(peaks[:: self.every])
            out.append(RefinedPeaks(peaks, np.where(np.isnan(peaks), np.nan, 0.02)))
        return tuple(out)


def _volumes(seed: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two 32^3 volumes of 60 Gaussian particles shifted (1.5, -1, 0.5) voxels."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(4, 28, (60, 3))
    z, y, x = np.mgrid[:32, :32, :32].astype(float)

    def render(points):
        vol = np.zeros((32, 32, 32))
        for px, py, pz in points:
            vol += np.exp(-((x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2) / 1.5)
        return vol.astype(np.float32)

    shift = np.array([1.5, -1.0, 0.5])
    return render(pos), render(pos + shift), shift


def test_refinement_leaves_out_and_counts_the_particles_the_fit_dropped():
    a, b, shift = _volumes()
    field = piv3d(a, b, windows=(16,))
    fit = _DroppingFit(every=5)
    pairs = pair_particles(a, b, field, fit=fit)
    assert pairs.dropped == fit.dropped > 0
    assert np.all(np.isfinite(pairs.midpoints)) and np.all(np.isfinite(pairs.displacements))
    assert len(pairs.displacements) >= 0.6 * 60
    np.testing.assert_allclose(np.median(pairs.displacements, axis=0), shift, atol=0.1)
    # each pair's uncertainty: its two fits' (0.02 voxel each) in quadrature, or with the
    # prior where a peak paired only after the fit
    fitted = np.isclose(pairs.sigma, np.hypot(0.02, 0.02)).all(axis=1)
    assert fitted.mean() > 0.5
    assert np.all(pairs.sigma[~fitted] >= PRIOR_VOXELS[0])
    refined = refine_with_particles(field, a, b, fit=_DroppingFit(every=5))
    assert refined.refinement["dropped"] == fit.dropped
    assert refine_with_particles(field, a, b).refinement["dropped"] == 0


def test_tracks_keep_the_dropped_count_through_a_file(tmp_path):
    n, f = 3, 5
    measured = np.cumsum(np.ones((n, f, 3)), axis=1)
    tracks = Tracks.from_measured(measured, np.full((n, f, 3), 0.1), np.ones((n, f)), 0.5,
                                  window=3, degree=1)
    tracks = dataclasses.replace(tracks, dropped=7)
    back = Tracks.load(tracks.save(tmp_path / "t.npz"))
    assert back.dropped == 7 and back.longer_than(2).dropped == 7
    older = tmp_path / "old.npz"  # a file written before the count existed
    with np.load(tmp_path / "t.npz") as data:
        np.savez(older, **{k: data[k] for k in data.files if k != "dropped"})
    assert Tracks.load(older).dropped == 0


@pytest.fixture(scope="module")
def recording(queue):
    """Five frames at the paper's optics on 18 x 12 lenses, 0.2 particles per microlens
    moving uniformly, and the camera's projector."""
    from plenocl.bench.accuracy_section import UNIFORM
    from plenocl.bench.tracking_section import simulate_series

    cam, grid = paper_optics((18, 12))
    series = simulate_series(cam, grid, 0.2, 5, 7, queue, UNIFORM, rays=1000)
    return series, grid, plenocl.Projector(cam, grid, queue)


def test_track_with_a_diverging_particle_returns_tracks_and_counts_it(recording,
                                                                      monkeypatch):
    """Issue 44: a smoothed track 66 mm in front of the grid (where the camera's depth
    check raised inside the refit) and a NaN one; plus a peak outside the grid in every
    frame. The tracks come back (all but the two made to diverge, of the same recording
    tracked as it is), every measured position inside the grid, the bad particles
    counted."""
    track_module = importlib.import_module("plenocl.pipeline.track")  # not the function
    series, grid, proj = recording
    frames = len(series.frames)
    quick = plenocl.ReconstructionSettings(supersample=1, iterations=10)
    plain = len(plenocl.track(series.frames, proj, dt=1e-3, reconstruction=quick).positions)
    real_peaks, real_smooth = track_module.find_particles, track_module.smooth_tracks
    calls = []

    def peaks_and_a_bad_one(vol, *args, **kwargs):
        peaks, values = real_peaks(vol, *args, **kwargs)
        far = np.array([[vol.shape[2] / 2, vol.shape[1] / 2, -400.0]])  # 73 mm in front
        return np.vstack([peaks, far]), np.append(values, values.max(initial=1.0))

    def diverging(measured, *args, **kwargs):
        tracks = real_smooth(measured, *args, **kwargs)
        if not calls:  # the first smoothing feeds the refit
            positions = tracks.positions.copy()
            positions[0, np.isfinite(measured[0, :, 0])] = [0.0, 0.0, -76.0]
            positions[1, np.isfinite(measured[1, :, 0])] = np.nan
            tracks = dataclasses.replace(tracks, positions=positions)
        calls.append(1)
        return tracks

    monkeypatch.setattr(track_module, "find_particles", peaks_and_a_bad_one)
    monkeypatch.setattr(track_module, "smooth_tracks", diverging)
    tracks = plenocl.track(series.frames, proj, dt=1e-3, reconstruction=quick)
    assert plain >= 4 and len(tracks.positions) >= plain - 2
    assert np.all(tracks.lengths >= 4)
    seen = np.all(np.isfinite(tracks.measured), axis=2)
    assert np.all(_inside(tracks.measured[seen], grid))
    assert np.all(np.isfinite(tracks.positions[seen]))
    # the far peak of every frame, and the two diverged tracks' frames in the refit
    assert tracks.dropped >= frames + 2 * 4


BATCH = """
[camera]
preset = "synthetic"
[grid]
z_mm = [-2.0, 2.0]
fraction = 0.5
[images]
folder = "raw"
pattern = "frame_*.tif"
pairing = "sequence"
dt_s = 1e-3
[reconstruction]
iterations = 10
[piv]
windows = [8]
[output]
folder = "results"
"""


def test_a_batch_run_reports_the_particles_each_pair_dropped(tmp_path, monkeypatch):
    """The count a pair's fit dropped (here forced: 3 for every pair) reaches the run's
    summary, ``summary.json`` and its last line."""
    worker = importlib.import_module("plenocl.batch.worker")
    real = worker.process_pair

    def dropping(*args, **kwargs):
        pair = real(*args, **kwargs)
        pair.piv.refinement["dropped"] = 3
        return pair

    monkeypatch.setattr(worker, "process_pair", dropping)
    (tmp_path / "raw").mkdir()
    cam = plenocl.Camera.synthetic_850()
    pos, inten = plenocl.random_particles(((-1.2, 1.2), (-1.2, 1.2), (-1.5, 1.5)), count=80,
                                          seed=2, intensity=3e4)
    for j, sign in enumerate((-0.5, 0.5)):
        img = plenocl.simulate_image(cam, pos + sign * np.array([0.2, 0.0, 0.0]), inten,
                                     1000, seed=j, read_noise=2.0, bit_depth=16)
        write_tiff(tmp_path / "raw" / f"frame_{j:03d}.tif", img)
    (tmp_path / "experiment.toml").write_text(BATCH)
    lines = []
    summary = plenocl.run(tmp_path / "experiment.toml", log=lines.append, progress=False)
    assert summary.processed == [0] and summary.dropped_particles == {0: 3}
    saved = json.loads((tmp_path / "results" / "summary.json").read_text())
    assert saved["dropped_particles"] == {"0": 3}
    assert "3 particle(s) dropped by the image fit in 1 pair(s)" in lines[-1]
