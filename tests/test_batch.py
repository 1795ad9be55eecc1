"""A configured, resumable batch of image pairs (plenocl run experiment.toml)."""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest

import plenocl
from plenocl import Camera, random_particles, simulate_image
from plenocl.batch import load_experiment
from plenocl.cli.main import main
from plenocl.io import write_tiff
from plenocl.io.tomlfile import read_toml
from plenocl.plot import SUMMARY_FIGURES
from plenocl.vectorfield import read_npz

EXPERIMENT = """
[camera]
preset = "synthetic"
[grid]
z_mm = [-2.0, 2.0]
fraction = 0.6
[images]
folder = "raw"
pattern = "frame_*.tif"
pairing = "sequence"
dt_s = 1e-3
[reconstruction]
iterations = 20
[output]
folder = "results"
"""


@pytest.fixture(scope="module")
def experiment(tmp_path_factory, queue):
    """Three pairs moved 0.25 mm along x (0.25 m/s over 1 ms), the last one's second
    image corrupt."""
    d = tmp_path_factory.mktemp("exp")
    (d / "raw").mkdir()
    cam = Camera.synthetic_850()
    pos, inten = random_particles(((-1.6, 1.6), (-1.6, 1.6), (-1.8, 1.8)), count=300,
                                  seed=5, intensity=3e4)
    shift = np.array([0.25, 0.0, 0.0])
    for k in range(3):
        for j, sign in enumerate((-0.5, 0.5)):
            img = simulate_image(cam, pos + sign * shift, inten, 3000, seed=10 * k + j,
                                 read_noise=2.0, bit_depth=16, queue=queue)
            write_tiff(d / "raw" / f"frame_{2 * k + j:03d}.tif", img)
    (d / "raw" / "frame_005.tif").write_bytes(b"not a tiff")
    (d / "experiment.toml").write_text(EXPERIMENT)
    return d


@pytest.mark.one_device
def test_run_processes_pairs_skips_finished_ones_and_reports_failures(experiment, capsys):
    assert main(["run", str(experiment / "experiment.toml")]) == 1  # one pair failed
    out = experiment / "results"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["processed"] == [0, 1] and list(summary["failed"]) == ["2"]
    assert "frame_005.tif" in summary["failed"]["2"]
    res, arrays = read_npz(out / "pairs" / "pair_00000.npz")
    assert np.median(arrays["velocity"][0][res.valid]) == pytest.approx(0.25, rel=0.1)
    used = read_toml(out / "experiment_used.toml")
    assert used["run"]["plenocl_version"] == plenocl.__version__
    assert used["reconstruction"]["iterations"] == 20 and used["images"]["dt_s"] == 1e-3
    # the run's summary figures (tests/test_plot.py checks what they draw)
    assert sorted(p.name for p in (out / "figures").iterdir()) == sorted(SUMMARY_FIGURES)
    assert sorted(summary["figures"]) == sorted(str(out / "figures" / n) for n in SUMMARY_FIGURES)
    # a rerun redoes nothing that was finished
    summary2 = plenocl.run(experiment / "experiment.toml")
    assert summary2.skipped == [0, 1] and summary2.processed == [] and 2 in summary2.failed


@pytest.mark.parametrize("change, message", [
    ("[camera]\npreset = 'synthetic'\nlens = 3\n", r"unknown key\(s\) \['lens'\] in \[camera\]"),
    ("[cameras]\n", r"one \[\[cameras\]\] table each"),
    ("[cameras]\npreset = 'synthetic'\n", r"one \[\[cameras\]\] table each"),
    ("[[cameras]]\npreset = 'synthetic'\nfolder = 'a'\n[[cameras]]\nfolder = 'b'\n",
     r"\[\[cameras\]\] 2 needs exactly one of file or preset"),
    ("[[cameras]]\npreset = 'synthetic'\nfolder = 'a'\nzoom = 2\n[[cameras]]\n"
     "preset = 'synthetic'\nfolder = 'b'\n",
     r"unknown key\(s\) \['zoom'\] in \[\[cameras\]\] 1"),
    ("[camera]\npreset = 'synthetic'\n[[cameras]]\npreset = 'synthetic'\nfolder = 'a'\n"
     "[[cameras]]\npreset = 'synthetic'\nfolder = 'b'\n",
     r"\[camera\] and \[\[cameras\]\] together"),
    ("[camera]\n", "exactly one of file or preset"),
    ("[output]\nvti = 'yes'\n[camera]\npreset = 'synthetic'\n", "vti must be true or false"),
    ("[piv]\nensemble = 1\n[camera]\npreset = 'synthetic'\n",
     r"\[piv\] ensemble must be true or false"),
])
def test_bad_experiment_files_are_refused_before_any_work(tmp_path, change, message):
    base = EXPERIMENT.replace('[camera]\npreset = "synthetic"\n', "").replace(
        '[output]\nfolder = "results"\n', "")
    (tmp_path / "e.toml").write_text(change + base)
    with pytest.raises(ValueError, match=message):
        load_experiment(tmp_path / "e.toml")


def test_bad_values_are_named(tmp_path):
    for old, new, message in (('dt_s = 1e-3', 'dt_s = -1', "dt_s = -1 s is negative"),
                              ('pairing = "sequence"', 'pairing = "odd"', "pairing must"),
                              ("iterations = 20", "iterations = -2", "iterations"),
                              ('dt_s = 1e-3', 'dt_s = 175', r"dt_s = 175 s .*175 µs would be"
                               r".*force_dt = true"),
                              ('pairing = "sequence"', 'pairing = "list"', "goes with"),
                              ('pairing = "sequence"', 'first_frame = -1', "first_frame"),
                              ('dt_s = 1e-3', 'dt_s = 1e-3\nforce_dt = 1', "force_dt")):
        (tmp_path / "e.toml").write_text(EXPERIMENT.replace(old, new))
        with pytest.raises(ValueError, match=message):
            load_experiment(tmp_path / "e.toml")
    (tmp_path / "e.toml").write_text(EXPERIMENT.replace("dt_s = 1e-3",
                                                        "dt_s = 2.5\nforce_dt = true"))
    assert load_experiment(tmp_path / "e.toml")["images"]["dt_s"] == 2.5  # forced: real


@pytest.mark.one_device
def test_dask_workers_give_the_serial_fields_and_a_store_xarray_reads(experiment, tmp_path):
    exp = _copy_experiment(experiment, tmp_path / "in", pinned=True)
    serial = plenocl.run(exp, tmp_path / "serial", progress=False)
    dask = plenocl.run(exp, tmp_path / "dask", workers=2, progress=False)
    assert dask.processed == serial.processed == [0, 1]
    assert list(dask.failed) == list(serial.failed) == [2]
    for k in (0, 1):
        name = f"pairs/pair_{k:05d}.npz"
        _, want = read_npz(tmp_path / "serial" / name)
        _, got = read_npz(tmp_path / "dask" / name)
        for key in ("displacement", "velocity", "valid", "peak_ratio",
                    "velocity_uncertainty"):
            assert np.array_equal(got[key], want[key], equal_nan=True), key
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(tmp_path / "dask" / "timeseries.zarr")
    assert ds.u.dims == ("time", "z", "y", "x") and ds.sizes["time"] == 2
    assert ds.x.attrs["units"] == "mm" and ds.u.attrs["units"] == "m/s"
    assert ds.u_sigma.dims == ds.u.dims and ds.w_sigma.attrs["units"] == "m/s"
    sigma = ds.u_sigma.values[ds.valid.values]
    assert np.isfinite(sigma).mean() > 0.9 and np.all(sigma[np.isfinite(sigma)] >= 0)
    np.testing.assert_array_equal(ds.v_sigma.values[0],
                                  read_npz(tmp_path / "dask" / "pairs" / "pair_00000.npz")[1]
                                  ["velocity_uncertainty"][1].astype(np.float32))
    assert list(ds.pair.values) == [0, 1]
    _, first = read_npz(tmp_path / "dask" / "pairs" / "pair_00000.npz")
    np.testing.assert_allclose(ds.x.values, first["x_mm"])
    u = ds.u.values
    valid = ds.valid.values
    mean = np.where(valid.sum(0) > 0, np.nansum(np.where(valid, u, 0), 0)
                    / np.maximum(valid.sum(0), 1), np.nan)
    np.testing.assert_allclose(ds.u_mean.values, mean, rtol=1e-5, equal_nan=True)
    assert float(np.nanmedian(ds.u_mean.values)) == pytest.approx(0.25, rel=0.1)


@pytest.mark.one_device
def test_a_rerun_skips_and_says_so_and_an_interrupted_run_keeps_a_consistent_store(
        experiment, tmp_path, monkeypatch):
    out = tmp_path / "r"
    calls = []
    from plenocl.batch import worker

    real = worker.PairProcessor.__call__

    def stop_after_first(self, task, read=None):
        if calls:
            raise KeyboardInterrupt
        calls.append(task.index)
        return real(self, task, read)

    monkeypatch.setattr(worker.PairProcessor, "__call__", stop_after_first)
    first = plenocl.run(experiment / "experiment.toml", out, progress=False)
    assert first.interrupted and first.processed == [0]
    xr = pytest.importorskip("xarray")
    assert xr.open_zarr(out / "timeseries.zarr").sizes["time"] == 1
    monkeypatch.setattr(worker.PairProcessor, "__call__", real)
    messages = []
    second = plenocl.run(experiment / "experiment.toml", out, progress=False,
                         log=messages.append)
    assert second.skipped == [0] and second.processed == [1]
    assert any("already done" in m and "skipped" in m for m in messages)
    assert xr.open_zarr(out / "timeseries.zarr").sizes["time"] == 2
    assert not (out / "timeseries.zarr.partial").exists()
    # the disk full while the store is written: neither its half nor the older store
    # (which no longer gathers the run's pairs) stays; the summary says why, and a rerun
    # with space writes it from the pairs kept
    import errno
    import importlib

    batch_run = importlib.import_module("plenocl.batch.run")  # the module, not plenocl.run

    def full(path, *args, **kwargs):
        (out / "timeseries.zarr.partial" / "u").mkdir(parents=True)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(batch_run, "write_timeseries", full)
    said = []
    third = plenocl.run(experiment / "experiment.toml", out, progress=False, log=said.append)
    assert third.skipped == [0, 1] and third.store is None
    assert batch_run.RunSummary(pairs=1, stopped=third.stopped).exit_status() == 1
    assert "timeseries.zarr could not be written, the output disk is full" in third.stopped
    assert any(line.startswith("stopped: the time series") for line in said)
    assert not (out / "timeseries.zarr").exists()
    assert not (out / "timeseries.zarr.partial").exists()
    assert not (out / "figures").exists()  # they drew the store no longer there
    assert json.loads((out / "summary.json").read_text())["stopped"] == third.stopped
    monkeypatch.undo()
    fourth = plenocl.run(experiment / "experiment.toml", out, progress=False)
    assert fourth.stopped is None and fourth.store is not None
    assert xr.open_zarr(out / "timeseries.zarr").sizes["time"] == 2


@pytest.mark.one_device
def test_time_series_demo_writes_an_experiment_and_measures_it(tmp_path, queue):
    from plenocl.demo.time_series import run_time_series

    told = []
    s = run_time_series(tmp_path, pairs=2, queue=queue, log=told.append)
    assert s["processed"] == 2 and not s["failed"]
    # the closing line gives the throughput a user plans a campaign by
    per_hour = f"{3600 / s['seconds_per_pair']:.0f} pairs per hour"
    assert any(m.startswith("2 pair(s) processed") and per_hour in m for m in told), told[-3:]
    assert len(list((tmp_path / "raw").glob("frame_*.tif"))) == 4
    assert load_experiment(tmp_path / "experiment.toml")["images"]["pair_interval_s"] > 0
    # the small demo measures the boundary layer to within about 10 % of U∞ per component
    assert max(s["rms_error"].values()) < 0.15 and s["valid_fraction"] > 0.8
    assert set(s["stage_seconds_per_pair"]) >= {"read", "reconstruct_a", "reconstruct_b",
                                                "piv", "write"}
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["ensemble_mean_rms_error"] == s["ensemble_mean_rms_error"]
    # the demo keeps the volumes and correlates the pairs as one ensemble too
    assert len(list((tmp_path / "results" / "pairs").glob("volumes_*.npz"))) == 2
    assert max(s["ensemble_correlation_rms_error"].values()) < 0.15
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(tmp_path / "results" / "timeseries.zarr")
    assert ds.u_ensemble.dims == ("z", "y", "x") and ds.u_ensemble.attrs["units"] == "m/s"
    _, ens = read_npz(tmp_path / "results" / "ensemble.npz")
    np.testing.assert_allclose(ds.u_ensemble.values, ens["velocity"][0], rtol=1e-6)
    # a rerun that adds no pair keeps the ensemble as it is
    made = (tmp_path / "results" / "ensemble.npz").stat().st_mtime_ns
    said = []
    again = plenocl.run(tmp_path / "experiment.toml", log=said.append, progress=False)
    assert again.skipped == [0, 1] and again.ensemble.endswith("ensemble.npz")
    assert (tmp_path / "results" / "ensemble.npz").stat().st_mtime_ns == made
    assert any("no new pair" in m for m in said)
    # the disk full while the ensemble field is made again: no half of it is left, the
    # summary says why, the store is still written
    import errno

    from plenocl.batch import ensemble_field as module

    def full(out, *args, **kwargs):
        (out / "ensemble.vti").write_bytes(b"<VTK")  # a copy written before the field
        (out / "ensemble.npz").write_bytes(b"PK")
        raise OSError(errno.ENOSPC, "No space left on device")

    (tmp_path / "results" / "ensemble.npz").unlink()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(module, "ensemble_field", full)
        third = plenocl.run(tmp_path / "experiment.toml", log=said.append, progress=False)
    assert third.ensemble is None and third.store is not None
    assert "the ensemble field ensemble.npz could not be written, the output disk is full" \
        in third.stopped
    assert not list((tmp_path / "results").glob("ensemble.*"))


def test_pairs_of_another_grid_and_device_objects_with_workers_are_refused(experiment,
                                                                           tmp_path, queue):
    out = tmp_path / "g"
    (out / "pairs").mkdir(parents=True)
    (out / "pairs" / "pair_00000.npz").write_bytes(b"")
    plenocl.Grid((8, 8, 8), x=(-1, 1), y=(-1, 1), z=(-1, 1)).to_toml(out / "grid_used.toml")
    with pytest.raises(ValueError, match=r"holds pairs this run can neither keep nor remake "
                                         r"\(made from other images.*damaged\): pair 0: "
                                         "pair_00000.npz cannot be read"):
        plenocl.run(experiment / "experiment.toml", out, progress=False)
    with pytest.raises(ValueError, match="must be a name each worker looks up"):
        plenocl.run(experiment / "experiment.toml", tmp_path / "w", queue=queue, workers=2)
    for workers in (0, -2, 1.5):  # refused before anything is written
        with pytest.raises(ValueError, match=rf"workers must be a positive number of "
                                             rf"processes \(--workers N\), got {workers}"):
            plenocl.run(experiment / "experiment.toml", tmp_path / "n", workers=workers)
        assert not (tmp_path / "n").exists()
    bad = (experiment / "experiment.toml").read_text().replace("dt_s = 1e-3",
                                                                "dt_s = 1e-3\npair_interval_s = -1")
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(ValueError, match="pair_interval_s must be the time between"):
        load_experiment(tmp_path / "bad.toml")


def test_windows_larger_than_the_grid_are_refused_before_any_work(experiment, tmp_path,
                                                                  monkeypatch):
    """[piv] windows that the grid cannot hold fail every pair after its reconstructions:
    refused before any frame is read or anything is written, naming the axis and the
    grid's size (the default schedule on a grid under 8 voxels too)."""
    run_module = importlib.import_module("plenocl.batch.run")

    def no_pair(*args, **kwargs):
        raise AssertionError("a pair was processed")

    monkeypatch.setattr(run_module, "_process", no_pair)
    (tmp_path / "raw").symlink_to(experiment / "raw")
    text = (experiment / "experiment.toml").read_text()
    for edit, message in (("[piv]\nwindows = [512]\n", r"\[piv\] windows do not fit the "
                           r"grid's \d+ x \d+ x \d+ voxels \(z, y, x\): window 512 of "
                           r"pass 1 is larger than the volume along z"),
                          ("", r"holds no 8-voxel window")):
        exp = tmp_path / "e.toml"
        exp.write_text(text.replace("[output]", edit + "[output]") if edit else
                       text.replace("fraction = 0.6", "fraction = 0.6\nvoxel_mm = 0.9"))
        out = tmp_path / "out"
        with pytest.raises(ValueError, match=message):
            plenocl.run(exp, out, progress=False, log=lambda _: None)
        assert not out.exists() or not any(out.iterdir())


#: The FFT route pinned where runs in two processes are compared bit for bit: measured
#: (``PIVSettings.fft`` unset), each process times the routes itself, and with other work
#: beside it (a second test process under ``pytest -n 2``) two processes may take
#: different routes, whose fields differ at float32 rounding.
PINNED_ROUTE = '[piv]\nfft = "fftw"\n'


def _copy_experiment(experiment, dest, drop=(), pinned=False):
    """The fixture's experiment in ``dest`` without the frames numbered in ``drop``
    (``pinned``: its FFT route pinned, :data:`PINNED_ROUTE`)."""
    import shutil

    shutil.copytree(experiment / "raw", dest / "raw")
    for n in drop:
        (dest / "raw" / f"frame_{n:03d}.tif").unlink()
    text = (experiment / "experiment.toml").read_text()
    (dest / "experiment.toml").write_text(text + (PINNED_ROUTE if pinned else ""))
    return dest / "experiment.toml"


@pytest.mark.one_device
def test_a_missing_frame_is_reported_and_no_pair_mixes_exposures(experiment, tmp_path):
    """frame_002 deleted: pair 1 is not made and is named; pair 0 keeps frames 0 + 1 and
    pair 2 frames 4 + 5 (not 3 + 4); each field, the store and summary.json name their
    two source files."""
    exp = _copy_experiment(experiment, tmp_path, drop=[2])
    said = []
    s = plenocl.run(exp, log=said.append, progress=False)
    assert s.processed == [0] and list(s.failed) == [2] and list(s.gaps) == [1]
    assert "frame_002.tif missing" in s.gaps[1] and "frame_005.tif" in s.failed[2]
    assert any(m.startswith("pair 1: not made") for m in said)
    out = tmp_path / "results"
    saved = json.loads((out / "summary.json").read_text())
    assert "frame_002.tif" in saved["gaps"]["1"]
    src = saved["sources"]["0"]
    assert (src["a"]["name"], src["b"]["name"]) == ("frame_000.tif", "frame_001.tif")
    assert src["a"]["bytes"] == (tmp_path / "raw" / "frame_000.tif").stat().st_size
    assert len(src["b"]["sha256"]) == 64
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(out / "timeseries.zarr")
    assert list(ds.source_a.values) == ["frame_000.tif"]
    assert list(ds.source_b_sha256.values) == [src["b"]["sha256"]]


@pytest.mark.one_device
def test_a_rerun_refuses_inputs_that_changed_since(experiment, tmp_path):
    exp = _copy_experiment(experiment, tmp_path, drop=[2, 3, 4, 5])
    assert plenocl.run(exp, progress=False).processed == [0]
    frame = tmp_path / "raw" / "frame_001.tif"
    frame.write_bytes(frame.read_bytes()[:-4] + b"\0\0\0\1")  # same size, new content
    with pytest.raises(ValueError, match=r"neither keep nor remake.*frame_001.tif"):
        plenocl.run(exp, progress=False)
    assert plenocl.run(exp, tmp_path / "elsewhere", progress=False).processed == [0]


@pytest.mark.one_device
def test_a_sigkilled_run_rerun_equals_an_uninterrupted_one(experiment, tmp_path):
    """Killed with SIGKILL after its first field, then rerun: every field equals the
    uninterrupted run's bit for bit, and the half-written files of the kill are gone."""
    import os
    import signal
    import subprocess
    import sys
    import time

    exp = _copy_experiment(experiment, tmp_path, drop=[4, 5], pinned=True)
    reference = plenocl.run(exp, tmp_path / "whole", progress=False)
    assert reference.processed == [0, 1]
    out = tmp_path / "killed"
    env = {k: v for k, v in os.environ.items() if k != "PYOPENCL_CTX"}
    proc = subprocess.Popen([sys.executable, "-m", "plenocl", "run", str(exp), "--out",
                             str(out)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not (out / "pairs" / "pair_00000.npz").is_file() and time.monotonic() < deadline:
        assert proc.poll() is None, "the run ended before it could be killed"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stale = out / "pairs" / ".pair_00001.npz.kill.part.npz"  # as a kill mid-write leaves
    stale.write_bytes(b"half")
    said = []
    again = plenocl.run(exp, out, progress=False, log=said.append)
    assert again.processed in ([1], []) and sorted(again.processed + again.skipped) == [0, 1]
    assert not stale.exists() and any("half-written" in m for m in said)
    assert not list(out.rglob(".*.part*"))
    for k in (0, 1):
        _, want = read_npz(tmp_path / "whole" / "pairs" / f"pair_{k:05d}.npz")
        _, got = read_npz(out / "pairs" / f"pair_{k:05d}.npz")
        assert sorted(got) == sorted(want)
        for key in want:
            same = np.array_equal(got[key], want[key], equal_nan=want[key].dtype.kind == "f")
            assert same, (key, got[key], want[key]) if key == "metadata" else key


@pytest.mark.one_device
def test_a_run_applies_the_dark_frame_and_flat_field_of_the_experiment(experiment, tmp_path):
    """Frames recorded through an uneven gain and dark level, with the dark frame and flat
    field in [images]: the run's field is the one of the clean frames."""
    from plenocl.io import read_image

    exp = _copy_experiment(experiment, tmp_path, drop=[2, 3, 4, 5])
    clean = plenocl.run(exp, tmp_path / "clean", progress=False)
    assert clean.processed == [0]
    rows, cols = read_image(tmp_path / "raw" / "frame_000.tif").shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    dark = (40.0 + 0.02 * xx).astype(np.float32)
    gain = (0.8 + 0.4 * yy / rows).astype(np.float32)
    for n in (0, 1):
        path = tmp_path / "raw" / f"frame_{n:03d}.tif"
        write_tiff(path, dark + gain * read_image(path).astype(np.float32))
    write_tiff(tmp_path / "dark.tif", dark)
    write_tiff(tmp_path / "flat.tif", dark + gain * 1000.0)
    text = exp.read_text().replace("dt_s = 1e-3", 'dt_s = 1e-3\ndark = "dark.tif"\n'
                                                  'flat = "flat.tif"')
    exp.write_text(text)
    assert plenocl.run(exp, tmp_path / "corrected", progress=False).processed == [0]
    _, want = read_npz(tmp_path / "clean" / "pairs" / "pair_00000.npz")
    _, got = read_npz(tmp_path / "corrected" / "pairs" / "pair_00000.npz")
    ok = want["valid"] & got["valid"]
    assert ok.mean() > 0.8
    np.testing.assert_allclose(got["velocity"][:, ok], want["velocity"][:, ok], atol=0.01)
    exp.write_text(text.replace('flat = "flat.tif"', 'flat = "nope.tif"'))
    with pytest.raises(ValueError, match=r"\[images\] flat = 'nope.tif': no such file"):
        load_experiment(exp)


@pytest.mark.one_device
def test_a_bad_dark_frame_or_flat_field_is_refused_once_before_any_pair(experiment,
                                                                        tmp_path):
    """A dark frame with a NaN pixel, of another shape, a flat field with a dark pixel or
    below the dark frame: the run is refused before any pair, naming the file (it failed
    every pair, blaming a NaN on the images); a raw frame with a NaN pixel fails its pair
    naming that frame."""
    from plenocl.io import read_image

    exp = _copy_experiment(experiment, tmp_path, drop=[4, 5])
    shape = read_image(tmp_path / "raw" / "frame_000.tif").shape
    dark = np.full(shape, 40.0, np.float32)
    nan_dark = dark.copy()
    nan_dark[4, 7] = np.nan
    flat = np.full(shape, 1000.0, np.float32)
    dark_pixel = flat.copy()
    dark_pixel[3, 2] = 0.0
    text = exp.read_text()
    cases = [({"dark": nan_dark}, r"dark frame d\.npy contains 1 NaN .* row 4, column 7"),
             ({"dark": dark[:, :-3]}, r"dark frame d\.npy is .* does not match"),
             ({"flat": dark_pixel}, r"flat field f\.npy is not positive at 1 pixel.* row 3, "
                                    "column 2"),
             ({"dark": dark, "flat": dark - 1.0}, r"f\.npy minus the dark frame is not "
                                                  f"positive at {dark.size} pixel")]
    for files, message in cases:
        keys = ""
        for kind, frame in files.items():
            np.save(tmp_path / f"{kind[0]}.npy", frame)
            keys += f'{kind} = "{kind[0]}.npy"\n'
        exp.write_text(text.replace("dt_s = 1e-3", "dt_s = 1e-3\n" + keys))
        with pytest.raises(ValueError, match=message):
            plenocl.run(exp, tmp_path / "out", progress=False)
        assert not (tmp_path / "out" / "pairs").exists()
    exp.write_text(text)
    frame = read_image(tmp_path / "raw" / "frame_003.tif").astype(np.float32)
    frame[5, 6] = np.inf
    (tmp_path / "raw" / "frame_003.tif").unlink()
    write_tiff(tmp_path / "raw" / "frame_003.tif", frame)
    summary = plenocl.run(exp, tmp_path / "out", progress=False)
    assert list(summary.failed) == [1] and summary.processed == [0]
    assert "frame_003.tif contains 1 NaN or Inf pixel(s), the first at row 5, column 6" \
        in summary.failed[1]


def test_a_full_disk_stops_the_run_at_its_first_pair(experiment, tmp_path, monkeypatch):
    """Out of space writing the first pair: the run stops there (no later pair computed
    for nothing), says why in its summary and log, and a rerun with space goes on."""
    import errno

    from plenocl.batch import worker

    exp = _copy_experiment(experiment, tmp_path)
    calls = []

    def full(*args, **kwargs):
        calls.append(1)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(worker, "process_pair", full)
    monkeypatch.setattr(worker.PairProcessor, "projector", None)
    said = []
    summary = plenocl.run(exp, tmp_path / "out", progress=False, log=said.append)
    assert len(calls) == 1 and list(summary.failed) == [0] and not summary.processed
    assert "no space left on the disk of" in summary.stopped
    assert any(line.startswith("stopped, the output disk is full") for line in said)
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["stopped"] == summary.stopped and summary.exit_status() == 1


def test_the_experiment_sets_every_part_of_the_pair_and_the_worker_gets_it(
        experiment, tmp_path, monkeypatch):
    """[mte], [particles], [image_fit] and every [reconstruction]/[piv] option reach each
    pair's process_pair as the run's PairSettings object (no file read back); the run
    writes them, resolved, into experiment_used.toml for the record."""
    from plenocl.batch import worker
    from plenocl.pipeline import MTESettings, PairSettings
    from plenocl.pipeline.settings import PARTS
    from plenocl.projection.projector import DEFAULT_LENS_WEIGHTS

    text = (EXPERIMENT.replace("iterations = 20", "iterations = 20\ntol = 0.01")
            .replace('folder = "raw"', f'folder = "{(experiment / "raw").as_posix()}"')
            + "[piv]\nwindows = [16]\ncorrelation = 'fft'\nweighting = 'none'\n"
            "[mte]\ncycles = 1\n"
            "iterations = 4\n[particles]\nenabled = false\n[image_fit]\nrays = 200\n")
    (tmp_path / "e.toml").write_text(text)
    expected = load_experiment(tmp_path / "e.toml").pair
    assert expected.mte == MTESettings(cycles=1, iterations=4) and not expected.particles
    assert expected.image_fit.rays == 200 and expected.piv.windows == (16,)
    assert expected.piv.weighting is None  # "none": TOML has no null
    assert expected.reconstruction.tol == 0.01 and expected.reconstruction.supersample == 3
    # the default lens weights named, so that a record says which weights made its volumes
    assert expected.reconstruction.lens_weights == DEFAULT_LENS_WEIGHTS == "extent"
    got = []

    def fake(raw_a, raw_b, projector, settings, volumes=True):
        # the run keeps no volumes: it asks for the vectors alone
        got.append(None if volumes else settings)
        raise ValueError("not processed")

    monkeypatch.setattr(worker, "process_pair", fake)
    monkeypatch.setattr(worker.PairProcessor, "projector", None)
    summary = plenocl.run(tmp_path / "e.toml", tmp_path / "out", progress=False,
                          log=lambda _: None)
    assert len(summary.failed) == 3 and got and all(s == expected for s in got)
    used = read_toml(tmp_path / "out" / "experiment_used.toml")
    assert used["mte"]["cycles"] == 1 and used["particles"]["enabled"] is False
    assert used["image_fit"]["rays"] == 200 and used["piv"]["correlation"] == "fft"
    # the record, read back, is the settings the workers got (None options included)
    parts = {part: dict(used[part]) for part in PARTS}
    parts["piv"].pop("ensemble")
    assert PairSettings.from_dict(parts) == expected


@pytest.mark.one_device
def test_a_serial_run_reads_the_next_pair_while_one_computes(experiment, tmp_path,
                                                             monkeypatch):
    """Serially, each next pair's frames are read on a helper thread while a pair
    computes (where two threads are allowed): the same fields, bit for bit, and the same
    failure of the corrupt last pair as the run reading each pair in turn
    (``PLENOCL_THREADS=1``)."""
    import threading

    from plenocl.batch import worker

    exp = _copy_experiment(experiment, tmp_path, pinned=True)
    readers = []
    real = worker.PairProcessor.read

    def spy(self, task):
        readers.append(threading.current_thread().name)
        return real(self, task)

    monkeypatch.setattr(worker.PairProcessor, "read", spy)
    runs, who = {}, {}
    for threads in ("1", "2"):
        monkeypatch.setenv("PLENOCL_THREADS", threads)
        readers.clear()
        runs[threads] = plenocl.run(exp, tmp_path / f"out{threads}", progress=False,
                                    log=lambda line: None)
        who[threads] = list(readers)
    assert who["1"] == ["MainThread"] * 3
    assert len(who["2"]) == 3 and all(n.startswith("plenocl-read") for n in who["2"])
    for threads, summary in runs.items():
        assert summary.processed == [0, 1] and list(summary.failed) == [2], threads
    assert runs["1"].failed == runs["2"].failed  # the corrupt frame named alike
    for k in (0, 1):
        name = f"pairs/pair_{k:05d}.npz"
        (_, one), (_, two) = (read_npz(tmp_path / f"out{t}" / name) for t in ("1", "2"))
        assert one.keys() == two.keys()
        for key in one:
            np.testing.assert_array_equal(one[key], two[key])


@pytest.mark.one_device
def test_workers_given_a_name_of_several_devices_share_them(experiment, tmp_path):
    """``--device cpu --workers 2``: worker k takes the k-th CPU device that builds the
    kernels, in turn (the plugin set up as Dask sets it up on workers 0 and 1), and
    ``summary.json`` counts the pairs each device made (which worker takes which pair
    is Dask's); a serial run counts its one device."""
    import pyopencl as cl

    from plenocl.batch.cluster import PlenoclWorker
    from plenocl.batch.worker import RunSettings
    from plenocl.opencl.device import building_devices, device_label

    exp = _copy_experiment(experiment, tmp_path / "in", pinned=True)
    cpus = [d for d in building_devices()[0] if d.type & cl.device_type.CPU]
    spread = plenocl.run(exp, tmp_path / "spread", queue="cpu", workers=2, progress=False)
    assert spread.processed == [0, 1] and list(spread.failed) == [2]
    assert set(spread.devices) <= {device_label(d) for d in cpus[:2]}
    assert sum(spread.devices.values()) == 2
    settings = RunSettings(plenocl.PairSettings(), 1e-3)
    plugin = PlenoclWorker(str(tmp_path / "spread"), settings, "cpu")
    for number in range(3):
        plugin.setup(type("Worker", (), {"name": number})())
        assert plugin.processor.device == cpus[number % len(cpus)]
    saved = json.loads((tmp_path / "spread" / "summary.json").read_text())
    assert saved["devices"] == spread.devices
    serial = plenocl.run(exp, tmp_path / "serial", queue=cpus[0], progress=False)
    assert serial.devices == {device_label(cpus[0]): 2}
