"""A time-resolved experiment through ``plenocl run`` (``[tracking]``, docs/batch.md):
the tracks and their binned field on disk and in ``tracks.zarr``, resume, and the
errors of bad experiment files and recordings."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import plenocl
from plenocl.batch import load_experiment
from plenocl.cli.main import main
from plenocl.io import write_tiff
from plenocl.io.tomlfile import read_toml
from plenocl.ptv import Tracks

INTERVAL_S = 1e-3
EXPERIMENT = f"""
[camera]
file = "camera.toml"
[grid]
file = "grid.toml"
[images]
folder = "raw"
pattern = "frame_*.tif"
[tracking]
frame_interval_s = {INTERVAL_S}
[output]
folder = "results"
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Six frames 1 ms apart at the paper's optics on 24 x 16 lenses (0.15 particles per
    microlens moving uniformly by SHIFT_VOX voxels per frame), as TIFF files with their
    camera, grid and experiment files; the grid's voxel (x, y, z mm). Simulated and run on
    the default device, as ``plenocl run`` uses it (the kernels' own tests cover every
    device)."""
    from plenocl.bench.accuracy_section import UNIFORM, paper_optics
    from plenocl.bench.tracking_section import simulate_series

    d = tmp_path_factory.mktemp("tracking")
    cam, grid = paper_optics((24, 16))
    series = simulate_series(cam, grid, 0.15, 6, 11, None, UNIFORM)
    (d / "raw").mkdir()
    for k, frame in enumerate(series.frames):
        write_tiff(d / "raw" / f"frame_{k:03d}.tif", frame.astype(np.float32))
    cam.to_toml(d / "camera.toml")
    grid.to_toml(d / "grid.toml")
    (d / "experiment.toml").write_text(EXPERIMENT)
    return d, np.asarray(grid.spacing[::-1])


def _logged(lines: list[str]):
    return lambda message: lines.append(str(message))


def test_a_tracked_run_writes_tracks_and_field_that_follow_the_motion(recording):
    """The tracks' steps and the binned field give the simulated shift: per tracked
    particle a step errs by about 0.02 voxel laterally and 0.4 in depth (docs/design.md
    §7.3), so the median of the run's ~150 steps lies within 0.05 / 0.2 voxel."""
    from plenocl.bench.accuracy_section import SHIFT_VOX

    d, voxel = recording
    summary = plenocl.run(d / "experiment.toml", queue=None, log=_logged([]))
    out = d / "results"
    assert summary.processed == ["tracks", "field"] and summary.exit_status() == 0
    tracks = Tracks.load(out / "tracks.npz")
    assert summary.tracks == len(tracks.positions) >= 20 and tracks.dt == INTERVAL_S
    steps = tracks.displacements() / voxel
    error = np.abs(np.nanmedian(steps, axis=(0, 1)) - SHIFT_VOX)
    assert np.all(error <= [0.05, 0.05, 0.2]), error
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(out / "tracks.zarr")
    assert ds.position.dims == ("track", "frame", "axis") and list(ds.axis.values) == list("xyz")
    np.testing.assert_allclose(ds.time.values, np.arange(6) * INTERVAL_S)
    assert {"time", "field_first_frame"} <= set(ds.coords)
    assert list(ds.frame.values) == list(range(6))
    np.testing.assert_allclose(ds.position.values, tracks.positions, rtol=1e-6)
    np.testing.assert_allclose(ds.velocity_sigma.values, tracks.velocity_sigma * 1e-3,
                               rtol=1e-6)
    assert ds.velocity.attrs["units"] == "m/s" and ds.intensity.dims == ("track", "frame")
    assert ds.u.dims == ("field_time", "z", "y", "x") and ds.sizes["field_time"] == 1
    true_velocity = SHIFT_VOX * voxel * 1e-3 / INTERVAL_S  # m/s
    valid = ds.valid.values
    assert valid.sum() >= 5
    for comp, truth, tol in zip("uvw", true_velocity, voxel * np.array([0.05, 0.05, 0.2])):
        assert float(np.median(ds[comp].values[valid])) == pytest.approx(truth, abs=tol)
    assert np.all(ds.u_sigma.values[valid] > 0)
    header = (out / "tracks.vtu").read_bytes()[:2000].decode(errors="ignore")
    assert f'NumberOfCells="{np.sum(tracks.lengths >= 2)}"' in header
    assert 'Name="velocity_m_per_s"' in header  # m/s, as the store's
    used = read_toml(out / "experiment_used.toml")
    assert used["tracking"]["frame_interval_s"] == INTERVAL_S
    assert used["tracking"]["min_length"] == 4 and "iterations" in used["reconstruction"]
    saved = json.loads((out / "summary.json").read_text())
    assert saved["frames"] == 6
    assert saved["dropped_particles"] == summary.dropped_particles == tracks.dropped
    assert saved["figures"] == [str(out / "figures" / "tracks.png")]
    assert (out / "figures" / "tracks.png").read_bytes()[:4] == b"\x89PNG"


def test_a_rerun_skips_the_finished_work_and_a_changed_setting_redoes_it(recording,
                                                                          capsys):
    d, _ = recording
    out = d / "results"
    if not (out / "tracks.npz").is_file():  # run alone
        plenocl.run(d / "experiment.toml", log=_logged([]))
    marks = [out / "tracks.npz", out / "tracks.vtu", out / "tracks.zarr" / "zarr.json"]
    before = [p.stat().st_mtime_ns for p in marks]
    lines: list[str] = []
    again = plenocl.run(d / "experiment.toml", log=_logged(lines))
    assert again.skipped == ["tracks", "field"] and again.processed == []
    assert any("[tracks] done earlier" in line for line in lines)
    assert [p.stat().st_mtime_ns for p in marks] == before
    assert main(["run", str(d / "experiment.toml")]) == 0  # the command line too
    assert [p.stat().st_mtime_ns for p in marks] == before
    old = Tracks.load(out / "tracks.npz")
    # the binned field's options alone: the field is binned again, the tracks kept
    (d / "field_only.toml").write_text(EXPERIMENT.replace(
        "[output]", "field_window = [16, 12, 12]\n[output]"))
    field_only = plenocl.run(d / "field_only.toml", log=_logged([]))
    assert field_only.skipped == ["tracks"] and field_only.processed == ["field"]
    assert (out / "tracks.npz").stat().st_mtime_ns == before[0]
    assert (out / "tracks.zarr" / "zarr.json").stat().st_mtime_ns != before[2]
    (d / "changed.toml").write_text(EXPERIMENT.replace(
        "[output]", "refits = 0\nfield_window = [16, 8, 8]\nfield_steps = 2\n[output]"))
    lines.clear()
    changed = plenocl.run(d / "changed.toml", log=_logged(lines))
    assert changed.processed == ["tracks", "field"]
    assert any("configuration changed (settings.tracking)" in line for line in lines)
    new = Tracks.load(out / "tracks.npz")
    assert not np.array_equal(new.measured, old.measured, equal_nan=True)
    xr = pytest.importorskip("xarray")
    field = xr.open_zarr(out / "tracks.zarr")  # windows of 8 voxels, 4 apart, on 16 x 23
    assert (field.sizes["y"], field.sizes["x"]) == (3, 4)
    assert list(field.field_first_frame.values) == [0, 2, 4]  # 5 steps, 2 per field
    assert list(field.field_last_frame.values) == [2, 4, 5]
    np.testing.assert_allclose(field.field_time.values, np.array([1, 3, 4.5]) * INTERVAL_S)


@pytest.mark.parametrize("name, entry", [("FIT_METHOD", "fit"),
                                         ("RECONSTRUCTION_METHOD", "reconstruction_method")])
def test_a_changed_method_tracks_again(recording, monkeypatch, name, entry):
    """The image fit's method (``plenocl.piv.imagefit.METHOD``) or the reconstruction's
    (``plenocl.reconstruction.METHOD``) changed with the same settings: the rerun tracks
    again and names why, never keeping tracks an earlier method made (nor does a batch
    keep such fields: the refinement's method holds the fit's, and the record the
    reconstruction's). The other methods in the key: the next test."""
    import plenocl.batch.tracking as tracking_module
    from plenocl.piv import imagefit, refinement

    assert imagefit.METHOD in refinement.METHOD
    d, _ = recording
    plenocl.run(d / "experiment.toml", log=_logged([]))  # its own tracks, whatever ran
    monkeypatch.setattr(tracking_module, name, f"a later {entry}")
    lines: list[str] = []
    again = plenocl.run(d / "experiment.toml", log=_logged(lines))
    assert again.processed == ["tracks", "field"] and again.skipped == []
    assert any(f"configuration changed ({entry}):" in line for line in lines), lines


def test_the_keys_follow_every_method_the_tracks_and_field_come_from(recording, tmp_path,
                                                                    monkeypatch):
    """The tracks' key names the correlation's method that predicts the first step
    (``plenocl.piv.direct.METHOD``) and the tracker's (``plenocl.pipeline.track.METHOD``);
    the field stage's key the tracker's and the refinement's (its window means,
    ``plenocl.piv.refinement.METHOD``), so a changed one tracks or bins again (the
    previous test: a changed key reruns its stages)."""
    import plenocl.batch.tracking as tracking_module
    from plenocl.batch.prepare import run_camera, run_grid, write_used_config

    d, _ = recording
    exp = load_experiment(d / "experiment.toml")
    camera = run_camera(exp, None, lambda _: None)
    write_used_config(exp, tmp_path, camera, run_grid(exp, camera), exp.tracking.record())
    frames = tracking_module.frame_series(exp, exp.tracking)

    def keys():
        return (json.dumps(tracking_module._config(exp, frames, tmp_path, exp.tracking)),
                json.dumps(tracking_module._field_key(tmp_path, exp.tracking)))

    before = keys()
    for name, tracks, field in (("CORRELATION_METHOD", True, False),
                                ("TRACK_METHOD", True, True),
                                ("REFINEMENT_METHOD", False, True),
                                ("FIELD_METHOD", False, True)):
        with monkeypatch.context() as patch:
            patch.setattr(tracking_module, name, "a later method")
            after = keys()
        assert (after[0] != before[0], after[1] != before[1]) == (tracks, field), name


def test_the_tracking_key_names_the_lens_weights(recording):
    """The tracks' key names the lens weights of their volumes when the file leaves them
    to plenocl's default, as the pairs' records do: a changed default tracks again."""
    from plenocl.projection.projector import DEFAULT_LENS_WEIGHTS

    d, _ = recording
    exp = load_experiment(d / "experiment.toml")
    assert exp.pair.reconstruction.lens_weights == DEFAULT_LENS_WEIGHTS
    assert exp.tracking.record()["reconstruction"]["lens_weights"] == DEFAULT_LENS_WEIGHTS
    assert exp.tracking.settings.reconstruction.lens_weights == DEFAULT_LENS_WEIGHTS


@pytest.mark.parametrize("edit, message", [
    ("[tracking]\nframes = 3\n", r"unknown key\(s\) \['frames'\] in \[tracking\]|"
                                 r"\[tracking\]: unknown key\(s\) \['frames'\]"),
    ("[tracking]\nwindow = 4\n", "TrackSettings.window must be an odd number"),
    ("[tracking]\nenabled = 1\n", "enabled must be true or false"),
    ("[tracking]\nfield_window = [16, 8]\n", "field_window must be a positive number"),
    ("[tracking]\nfield_steps = -1\n", "field_steps must be an integer >= 0"),
    ("[images]\npairing = \"ab\"\n", r"pairing = 'ab' does not apply.*enabled = false"),
    ("[images]\ndt_s = 1e-3\n", r"dt_s is the time between a pair's exposures.*"
                                "frame_interval_s"),
    ("[mte]\ncycles = 1\n", r"\[mte\] belongs to the pair chain"),
    ("[piv]\nensemble = true\n", r"\[piv\] ensemble belongs to the pair chain"),
    ("[output]\nformats = [\"csv\"]\n", r"\[output\] formats and vti \(\.csv\) are the copies"),
])
def test_bad_tracking_experiments_are_refused_before_any_work(tmp_path, edit, message):
    section, line = edit.split("\n", 1)
    text = EXPERIMENT.replace(f"{section}\n", f"{section}\n{line}") if section in EXPERIMENT \
        else EXPERIMENT + edit
    (tmp_path / "e.toml").write_text(text)
    with pytest.raises(ValueError, match=message):
        load_experiment(tmp_path / "e.toml")


def test_the_frame_interval_is_needed_and_checked_in_seconds(tmp_path):
    for old, new, message in (
            (f"frame_interval_s = {INTERVAL_S}\n", "", "frame_interval_s must be the time"),
            (f"frame_interval_s = {INTERVAL_S}", "frame_interval_s = 250",
             r"frame_interval_s = 250 s .*force_dt = true"),
            (f"frame_interval_s = {INTERVAL_S}", "frame_interval_s = 0",  # not pair wording
             r"frame_interval_s must be the time between successive frames in seconds, a "
             r"positive number \(e.g. 1e-3\), got 0$")):
        (tmp_path / "e.toml").write_text(EXPERIMENT.replace(old, new))
        with pytest.raises(ValueError, match=message):
            load_experiment(tmp_path / "e.toml")
    (tmp_path / "e.toml").write_text(EXPERIMENT.replace("[tracking]\n", "[tracking]\n"
                                                        "enabled = false\n"))
    with pytest.raises(ValueError, match="dt_s must be"):  # the pairs then need their dt
        load_experiment(tmp_path / "e.toml")


def _copy(recording, tmp_path):
    d, _ = recording
    tmp_path.mkdir(exist_ok=True)
    for name in ("camera.toml", "grid.toml", "experiment.toml"):
        shutil.copy(d / name, tmp_path / name)
    shutil.copytree(d / "raw", tmp_path / "raw")
    return tmp_path


@pytest.mark.parametrize("damage, message", [
    (lambda raw: (raw / "frame_002.tif").unlink(),
     r"frame_002.tif missing in .*restore the frame"),
    (lambda raw: [(raw / f"frame_00{k}.tif").unlink() for k in (3, 4, 5)],
     r"3 frame\(s\) .* min_length = 4 frames"),
    (lambda raw: (raw / "frame_003.tif").write_bytes(b"not a tiff"),
     r"cannot read .*frame_003.tif.*replace frame_003.tif"),
    (lambda raw: write_tiff(raw / "frame_004.tif", np.zeros((274, 400), np.float32)),
     r"frame_004.tif is 400 x 274 px .*does not match the camera's sensor"),
    (lambda raw: (raw / "frame_004.tif").rename(raw / "frame_last.tif"),
     r"frame_last.tif has no frame number: tracking orders the frames .*narrow \[images\] "
     "pattern"),
])
def test_bad_recordings_are_named_with_the_fix_and_nothing_is_written(recording, tmp_path,
                                                                      damage, message):
    d = _copy(recording, tmp_path)
    damage(d / "raw")
    with pytest.raises(ValueError, match=message):
        plenocl.run(d / "experiment.toml", log=_logged([]))
    assert not (d / "results" / "tracks.npz").exists()


def test_on_dask_the_tracking_is_one_task_and_gives_the_serial_tracks(recording, tmp_path):
    """The tracks of a Dask worker's process and of this one, bit for bit; the FFT route
    of the first step's correlation pinned (measured, each process times it itself, and
    under another test process's load the two may differ at float32 rounding)."""
    d = _copy(recording, tmp_path / "in")
    with open(d / "experiment.toml", "a") as exp:
        exp.write('[piv]\nfft = "fftw"\n')
    serial = plenocl.run(d / "experiment.toml", tmp_path / "serial", log=_logged([]))
    dask = plenocl.run(d / "experiment.toml", tmp_path / "dask", workers=1, log=_logged([]))
    assert dask.processed == serial.processed == ["tracks", "field"] and dask.workers == 1
    want, got = (Tracks.load(tmp_path / name / "tracks.npz") for name in ("serial", "dask"))
    for name in ("positions", "velocities", "measured_sigma", "intensities"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_a_run_stopped_while_writing_the_store_leaves_none_and_goes_on(recording, tmp_path,
                                                                        monkeypatch):
    """Ctrl-C while the store is written: the tracks stay, no store or half of one; the
    rerun removes the leftover, skips the tracking and writes the store."""
    import plenocl.io.zarrstore as zarrstore

    d, _ = recording

    def stopped(partial, path):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(zarrstore, "finish_store", stopped)
        with pytest.raises(KeyboardInterrupt):
            plenocl.run(d / "experiment.toml", tmp_path, log=_logged([]))
    assert (tmp_path / "tracks.npz").is_file() and (tmp_path / "tracks.zarr.partial").is_dir()
    assert not (tmp_path / "tracks.zarr").exists()
    lines: list[str] = []
    again = plenocl.run(d / "experiment.toml", tmp_path, log=_logged(lines))
    assert again.skipped == ["tracks"] and again.processed == ["field"]
    assert any("removed tracks.zarr.partial" in line for line in lines)
    assert (tmp_path / "tracks.zarr" / "zarr.json").is_file()
    assert not (tmp_path / "tracks.zarr.partial").exists()
