"""A rerun after a settings change (issue 44): every stored product carries the record of
what made it, and a rerun redoes exactly what a change affects, or refuses, naming the
changed entries and the way out (docs/batch.md "Resume")."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import plenocl
from plenocl import Camera, random_particles, simulate_image
from plenocl.batch import worker
from plenocl.batch.config import load_experiment
from plenocl.batch.prepare import run_camera, run_grid
from plenocl.batch.record import record_changes, run_record
from plenocl.cli.main import main
from plenocl.io import write_tiff
from plenocl.io.fieldformat import field_metadata, read_field
from plenocl.io.files import read_volumes
from plenocl.io.tomlfile import read_toml

DT = 1e-3
EXPERIMENT = f"""
[camera]
file = "camera.toml"
[grid]
file = "grid.toml"
[images]
folder = "raw"
pattern = "frame_*.tif"
dt_s = {DT}
[reconstruction]
iterations = 6
supersample = 1
[piv]
windows = [12, 8]
ensemble = true
# the FFT route pinned: measured, a fresh run's device volumes and the kept host volumes
# are timed apart and may take different routes, whose fields differ at rounding
fft = "fftw"
[particles]
enabled = false
[output]
folder = "results"
"""
PAIR = "results/pairs/pair_00000.npz"
VOLUMES = "results/pairs/volumes_00000.npz"


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """One pair of a small camera (24 x 24 lenses) moved 0.2 mm along x, its camera and
    grid files and the experiment file."""
    d = tmp_path_factory.mktemp("rerun")
    (d / "raw").mkdir()
    doc = Camera.synthetic_850().to_dict()
    doc["microlens_array"]["count"] = [24, 24]
    doc["sensor"]["pixels"] = [408, 408]
    cam = Camera.from_dict(doc)
    cam.to_toml(d / "camera.toml")
    plenocl.Grid.for_camera(cam, (-1.5, 1.5), fraction=0.7).to_toml(d / "grid.toml")
    pos, inten = random_particles(((-1.2, 1.2), (-1.2, 1.2), (-1.5, 1.5)), count=120,
                                  seed=5, intensity=3e4)
    for j, sign in enumerate((-0.5, 0.5)):
        img = simulate_image(cam, pos + sign * np.array([0.2, 0.0, 0.0]), inten, 2000,
                             seed=j, read_noise=2.0, bit_depth=16)
        write_tiff(d / "raw" / f"frame_{j:03d}.tif", img)
    (d / "experiment.toml").write_text(EXPERIMENT)
    return d


@pytest.fixture
def done(frames, tmp_path):
    """A copy of the experiment, run once."""
    for name in ("raw", "camera.toml", "grid.toml", "experiment.toml"):
        (shutil.copytree if name == "raw" else shutil.copy)(frames / name, tmp_path / name)
    assert plenocl.run(tmp_path / "experiment.toml", progress=False,
                       log=lambda _: None).processed == [0]
    return tmp_path


def _edit(folder, old, new):
    exp = folder / "experiment.toml"
    text = exp.read_text()
    assert old in text
    exp.write_text(text.replace(old, new))
    return exp


def _no_reconstruction(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("reconstructed")

    monkeypatch.setattr(worker, "process_pair", refuse)


def _rerun(folder, monkeypatch=None):
    """``plenocl.run`` of ``folder``'s experiment again: its summary and the lines it
    logged; with ``monkeypatch``, any reconstruction fails the test (the kept volumes
    must serve)."""
    said = []
    if monkeypatch is None:
        return plenocl.run(folder / "experiment.toml", progress=False, log=said.append), said
    with monkeypatch.context() as patch:
        _no_reconstruction(patch)
        s = plenocl.run(folder / "experiment.toml", progress=False, log=said.append)
    return s, said


def _record_matches_the_run(folder):
    """The field's record is the run's, and experiment_used.toml names the same."""
    exp = load_experiment(folder / "experiment.toml")
    camera = run_camera(exp, None, lambda _: None)
    record = run_record(exp, camera, run_grid(exp, camera))
    assert field_metadata(folder / PAIR)["record"] == record
    used = read_toml(folder / "results" / "experiment_used.toml")
    assert used["images"]["dt_s"] == record["images"]["dt_s"]
    for part in ("reconstruction", "mte"):
        assert used[part] == record[part]
    assert {k: v for k, v in used["piv"].items() if k != "ensemble"} == record["piv"]


def test_a_changed_dt_rescales_the_stored_velocities_and_nothing_else(done, monkeypatch):
    before = read_field(done / PAIR)
    ensemble = read_field(done / "results" / "ensemble.npz")
    volumes = (done / VOLUMES).read_bytes()
    _edit(done, f"dt_s = {DT}", "dt_s = 2.5e-3")
    s, said = _rerun(done, monkeypatch)
    assert s.rescaled == [0] and s.processed == [] and s.skipped == []
    assert any("images.dt_s changed" in m and "rescaled" in m for m in said)
    after = read_field(done / PAIR)
    ratio = DT / 2.5e-3
    np.testing.assert_array_equal(after["displacement"], before["displacement"])
    for key in ("velocity", "velocity_uncertainty", "vorticity"):
        np.testing.assert_allclose(after[key], before[key] * ratio, rtol=1e-12)
    np.testing.assert_allclose(after["q_criterion"], before["q_criterion"] * ratio**2,
                               rtol=1e-12)
    assert float(after["dt"]) == 2.5e-3
    assert (done / VOLUMES).read_bytes() == volumes
    again = read_field(done / "results" / "ensemble.npz")
    np.testing.assert_allclose(again["velocity"], ensemble["velocity"] * ratio, rtol=1e-12)
    _record_matches_the_run(done)
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(done / "results" / "timeseries.zarr")
    np.testing.assert_array_equal(ds.u.values[0], after["velocity"][0].astype(np.float32))
    assert ds.attrs["record"]["pairs"]["0"] == field_metadata(done / PAIR)["digests"]["record"]
    # and back: the first field again, to the last bit
    _edit(done, "dt_s = 2.5e-3", f"dt_s = {DT}")
    assert plenocl.run(done / "experiment.toml", progress=False,
                       log=lambda _: None).rescaled == [0]
    np.testing.assert_allclose(read_field(done / PAIR)["velocity"], before["velocity"],
                               rtol=1e-12)


def _fresh(done, tmp_path_factory):
    """The experiment as it now stands, run into a new folder."""
    out = tmp_path_factory.mktemp("fresh")
    assert plenocl.run(done / "experiment.toml", out, progress=False,
                       log=lambda _: None).processed == [0]
    return out


@pytest.mark.filterwarnings("ignore:the final windows")  # 2 vectors in depth: enough here
def test_a_changed_piv_table_correlates_the_kept_volumes_again(done, monkeypatch,
                                                               tmp_path_factory):
    volumes = (done / VOLUMES).read_bytes()
    old = read_field(done / PAIR)
    _edit(done, "windows = [12, 8]", "windows = [10]")
    s, said = _rerun(done, monkeypatch)
    assert s.processed == [0] and s.redone == [0]
    assert any("piv.windows changed" in m and "kept volumes" in m for m in said)
    assert (done / VOLUMES).read_bytes() == volumes
    new = read_field(done / PAIR)
    assert new["velocity"].shape != old["velocity"].shape
    fresh = read_field(_fresh(done, tmp_path_factory) / "pairs" / "pair_00000.npz")
    for key in ("displacement", "valid", "velocity"):  # as if made with [8] from the start
        np.testing.assert_array_equal(new[key], fresh[key])
    _record_matches_the_run(done)
    ensemble = field_metadata(done / "results" / "ensemble.npz")["record"]
    assert ensemble["pairs"]["0"] == field_metadata(done / PAIR)["digests"]["field"]


@pytest.mark.parametrize("name, section", [("REFINEMENT_METHOD", "refinement"),
                                           ("CORRELATION_METHOD", "correlation")])
def test_a_field_of_an_earlier_method_is_correlated_again(done, monkeypatch, name, section):
    """The particle refinement (``plenocl.piv.refinement.METHOD``) or the correlation
    (``plenocl.piv.direct.METHOD``: the 45 depth lags of issue 46) changed with the same
    settings: the kept volumes are correlated again, never the old field kept."""
    import plenocl.batch.record as record_module

    volumes = (done / VOLUMES).read_bytes()
    monkeypatch.setattr(record_module, name, f"a later {section}")
    s, said = _rerun(done, monkeypatch)
    assert s.processed == [0] and s.redone == [0]
    assert any(f"{section}.method changed" in m and "kept volumes" in m for m in said)
    assert (done / VOLUMES).read_bytes() == volumes
    assert field_metadata(done / PAIR)["record"][section]["method"] == f"a later {section}"


def test_an_ensemble_of_an_earlier_method_is_made_again(done, monkeypatch):
    """The ensemble correlation's method (``plenocl.piv.ensemble.METHOD``) changed, with
    ``dt_s`` too: the ensemble field is correlated again from the kept volumes, not kept
    or rescaled; the pairs' fields are kept."""
    import plenocl.batch.record as record_module

    field = (done / PAIR).read_bytes()
    monkeypatch.setattr(record_module, "ENSEMBLE_METHOD", "a later ensemble")
    _edit(done, f"dt_s = {DT}", f"dt_s = {2 * DT}")
    s, said = _rerun(done, monkeypatch)
    assert s.rescaled == [0] and not s.processed and (done / PAIR).read_bytes() != field
    assert any("ensemble correlation of 1 pair(s)" in m for m in said), said
    made = field_metadata(done / "results" / "ensemble.npz")["record"]
    assert made["method"] == "a later ensemble" and made["dt_s"] == 2 * DT


@pytest.mark.parametrize("earlier", ["another method", None])
def test_volumes_of_an_earlier_reconstruction_method_are_made_again(done, monkeypatch,
                                                                    earlier):
    """The reconstruction's method (``plenocl.reconstruction.METHOD``) changed with the
    same settings, or the pair's record was written before the method was recorded
    (``None``): the pair is reconstructed again, never its kept volumes correlated, and
    its record and kept volumes name today's method."""
    import importlib

    import plenocl.batch.record as record_module

    run_module = importlib.import_module("plenocl.batch.run")  # the package's run() hides it
    volumes_digest = field_metadata(done / PAIR)["digests"]["volumes"]
    with monkeypatch.context() as patch:
        if earlier is None:
            made = run_module.run_record

            def without_method(*args):
                record = made(*args)
                del record["reconstruction_method"]
                return record

            patch.setattr(run_module, "run_record", without_method)
        else:
            patch.setattr(record_module, "RECONSTRUCTION_METHOD", earlier)
        s, _ = _rerun(done)  # what the earlier code wrote
    assert s.redone == [0]
    assert field_metadata(done / PAIR)["digests"]["volumes"] != volumes_digest
    s, said = _rerun(done)
    assert s.processed == [0] and s.redone == [0]
    assert any("reconstruction_method.method changed" in m and "redoing" in m
               for m in said), said
    assert field_metadata(done / PAIR)["digests"]["volumes"] == volumes_digest
    _record_matches_the_run(done)
    assert (field_metadata(done / PAIR)["record"]["reconstruction_method"]["method"]
            == plenocl.reconstruction.METHOD)


@pytest.mark.parametrize("old, new, changed, action", [
    ("iterations = 6", "iterations = 4", "reconstruction.iterations", "redoing"),
    ("iterations = 6", "iterations = 6\nsmooth_px = 1.0", "reconstruction.smooth_px",
     "redoing"),
    ("iterations = 6", "iterations = 6\nlens_weights = 'paper'",
     "reconstruction.lens_weights", "redoing"),
    ("windows = [12, 8]\nensemble = true", "windows = [8]\nensemble = false", "piv.windows",
     "no volumes of this reconstruction are kept"),
])
def test_a_changed_reconstruction_or_piv_without_volumes_redoes_the_pair(
        done, tmp_path_factory, old, new, changed, action):
    if "ensemble = false" in new:
        (done / VOLUMES).unlink()  # as a run without the ensemble keeps none
    _edit(done, old, new)
    s, said = _rerun(done)
    assert s.processed == [0] and s.redone == [0]
    assert any(changed in m and action in m for m in said), said
    fresh = _fresh(done, tmp_path_factory)
    got, want = read_field(done / PAIR), read_field(fresh / "pairs" / "pair_00000.npz")
    for key in ("displacement", "valid", "velocity"):
        np.testing.assert_array_equal(got[key], want[key])
    if "ensemble = true" in new or "iterations" in new:
        for a, b in zip(read_volumes(done / VOLUMES),
                        read_volumes(fresh / "pairs" / "volumes_00000.npz")):
            np.testing.assert_array_equal(a, b)
    _record_matches_the_run(done)


def test_another_camera_or_old_results_are_refused_until_redo(done):
    exp = done / "experiment.toml"
    field = (done / PAIR).read_bytes()
    camera = (done / "camera.toml").read_text()
    (done / "camera.toml").write_text(camera.replace("f_number = 2.0", "f_number = 2.2"))
    with pytest.raises(ValueError, match=r"pair 0: the camera changed.*--out.*--redo"):
        plenocl.run(exp, progress=False, log=lambda _: None)
    assert main(["run", str(exp), "--no-progress"]) != 0
    assert (done / PAIR).read_bytes() == field  # nothing changed by the refusal
    s = plenocl.run(exp, progress=False, log=lambda _: None, redo=True)
    assert s.processed == [0] and s.redone == [0]
    _record_matches_the_run(done)
    # a field of an older plenocl, without a record: refused, then redone on request
    data = read_field(done / PAIR)
    meta = field_metadata(done / PAIR)
    data["metadata"] = np.asarray(__import__("json").dumps(
        {k: v for k, v in meta.items() if k not in ("record", "digests")}))
    with open(done / PAIR, "wb") as fh:
        np.savez_compressed(fh, **data)
    with pytest.raises(ValueError, match="records no settings.*--redo"):
        plenocl.run(exp, progress=False, log=lambda _: None)
    assert main(["run", str(exp), "--no-progress", "--redo"]) == 0
    _record_matches_the_run(done)


def test_a_narrowed_selection_keeps_no_pair_it_no_longer_makes(done):
    """A pair the run no longer makes while its frames are still there (``[images]
    pattern`` narrowed) is refused, naming its frames and the way out, and removed with
    ``--redo``; a pair whose frames are gone is kept, as before."""
    raw = done / "raw"
    for k in (0, 1):
        shutil.copy(raw / f"frame_00{k}.tif", raw / f"frame_00{k + 2}.tif")
    s, _ = _rerun(done)
    assert s.skipped == [0] and s.processed == [1]
    second = done / "results" / "pairs" / "pair_00001.npz"
    made = second.read_bytes()
    exp = _edit(done, 'pattern = "frame_*.tif"', 'pattern = "frame_00[01].tif"')
    with pytest.raises(ValueError, match=r"pair 1: it was made from frame_002.tif and "
                                         r"frame_003.tif, still in .*no longer pairs so.*"
                                         r"--redo"):
        plenocl.run(exp, progress=False, log=lambda _: None)
    assert second.read_bytes() == made  # nothing changed by the refusal
    said = []
    s = plenocl.run(exp, progress=False, log=said.append, redo=True)
    assert s.skipped == [0] and not s.processed and not second.exists()
    assert any("pair 1" in line and "removed: this run makes no such pair" in line
               for line in said)
    with pytest.importorskip("xarray").open_zarr(done / "results" / "timeseries.zarr") as ds:
        assert ds.sizes["time"] == 1
    # frames deleted after their pair was made: the pair is kept
    _edit(done, 'pattern = "frame_00[01].tif"', 'pattern = "frame_*.tif"')
    s, _ = _rerun(done)
    assert s.processed == [1]
    for k in (2, 3):
        (raw / f"frame_00{k}.tif").unlink()
    kept = second.read_bytes()
    s, _ = _rerun(done)
    assert not s.processed and second.read_bytes() == kept
    with pytest.importorskip("xarray").open_zarr(done / "results" / "timeseries.zarr") as ds:
        assert ds.sizes["time"] == 2


def test_a_tracking_rerun_leaves_only_results_of_its_record(tmp_path, monkeypatch):
    """[tracking]: the store records the digests of what made it; a rerun with another
    frame interval removes the old tracks and field before tracking again, so a run that
    fails leaves none of them beside the new experiment_used.toml."""
    from test_batch_tracking import EXPERIMENT as TRACKED
    from test_batch_tracking import INTERVAL_S

    from plenocl.batch import tracking
    from plenocl.bench.accuracy_section import UNIFORM, paper_optics
    from plenocl.bench.tracking_section import simulate_series

    cam, grid = paper_optics((24, 16))
    series = simulate_series(cam, grid, 0.15, 4, 11, None, UNIFORM)
    (tmp_path / "raw").mkdir()
    for k, frame in enumerate(series.frames):
        write_tiff(tmp_path / "raw" / f"frame_{k:03d}.tif", frame.astype(np.float32))
    cam.to_toml(tmp_path / "camera.toml")
    grid.to_toml(tmp_path / "grid.toml")
    exp = tmp_path / "experiment.toml"
    exp.write_text(TRACKED.replace("[output]", "min_length = 3\n[output]"))
    out = tmp_path / "results"
    assert plenocl.run(exp, log=lambda _: None, progress=False).processed == ["tracks",
                                                                             "field"]
    xr = pytest.importorskip("xarray")

    def recorded():
        state = __import__("json").loads((out / "state.json").read_text())
        with xr.open_zarr(out / "tracks.zarr") as ds:
            assert ds.attrs["record"] == {"tracks": state["config"],
                                          "field": state["stages"]["field"]["key"]}
            assert plenocl.Tracks.record_of(out / "tracks.npz") == {"tracks": state["config"]}
            return ds.attrs["record"]

    first = recorded()
    exp.write_text(exp.read_text().replace(f"frame_interval_s = {INTERVAL_S}",
                                           "frame_interval_s = 0.002"))

    def fail(*args, **kwargs):
        raise ValueError("stopped")

    with monkeypatch.context() as patch:
        patch.setattr(tracking, "track_job", fail)
        said = []
        with pytest.raises(ValueError, match="stopped"):
            plenocl.run(exp, log=said.append, progress=False)
    assert any("removed tracks.npz, tracks.vtu, tracks.zarr" in m for m in said)
    assert not any((out / name).exists() for name in ("tracks.npz", "tracks.vtu",
                                                      "tracks.zarr"))
    assert read_toml(out / "experiment_used.toml")["tracking"]["frame_interval_s"] == 0.002
    again = plenocl.run(exp, log=lambda _: None, progress=False)
    assert again.processed == ["tracks", "field"]
    assert plenocl.Tracks.load(out / "tracks.npz").dt == 0.002
    assert recorded()["tracks"] != first["tracks"]
    # stopped after writing another configuration's tracks, before its stage's entry:
    # the configuration it started with is the state's, so 0.002 does not keep them
    tracked = tracking.track_job

    def stopped(*args, **kwargs):
        tracked(*args, **kwargs)
        raise KeyboardInterrupt

    exp.write_text(exp.read_text().replace("frame_interval_s = 0.002",
                                           "frame_interval_s = 0.003"))
    with monkeypatch.context() as patch:
        patch.setattr(tracking, "track_job", stopped)
        with pytest.raises(KeyboardInterrupt):
            plenocl.run(exp, log=lambda _: None, progress=False)
    assert plenocl.Tracks.load(out / "tracks.npz").dt == 0.003
    exp.write_text(exp.read_text().replace("frame_interval_s = 0.003",
                                           "frame_interval_s = 0.002"))
    assert plenocl.run(exp, log=lambda _: None, progress=False).processed == ["tracks",
                                                                             "field"]
    assert plenocl.Tracks.load(out / "tracks.npz").dt == 0.002
    recorded()


def test_vti_asked_for_later_is_written_from_the_kept_field(done, monkeypatch):
    _edit(done, 'folder = "results"', 'folder = "results"\nvti = true\nformats = ["csv"]')
    s, _ = _rerun(done, monkeypatch)
    assert s.skipped == [0] and s.processed == []
    vti = (done / PAIR).with_suffix(".vti")
    assert vti.is_file() and b"velocity_m_per_s" in vti.read_bytes()
    # the kept ensemble field gets its copies too, with its own velocities
    ensemble = done / "results" / "ensemble.npz"
    assert ensemble.with_suffix(".vti").is_file()
    table = np.genfromtxt(ensemble.with_suffix(".csv"), delimiter=",", names=True)
    u = read_field(ensemble)["velocity"][0].ravel()
    np.testing.assert_allclose(table["u_ms"], u, rtol=1e-9)


def test_the_fits_particles_per_launch_neither_recorded_nor_compared(frames):
    """``image_fit.chunk`` changes how fast a pair runs, not what it gives (each
    particle's step and covariance are its own: ``tests/test_imagefit.py``): the run's
    record leaves it out, and a record written before (``chunk = 128``) is the run's;
    another fit setting is still named."""
    exp = load_experiment(frames / "experiment.toml")
    camera = run_camera(exp, None, lambda _: None)
    record = run_record(exp, camera, run_grid(exp, camera))
    assert "chunk" not in record["image_fit"] and "rays" in record["image_fit"]
    older = {**record, "image_fit": {**record["image_fit"], "chunk": 128}}
    assert record_changes(older, record) == []
    other = {**record, "image_fit": {**record["image_fit"], "iterations": 9}}
    assert record_changes(other, record) == ["image_fit.iterations"]


def test_an_ensemble_removed_takes_its_copies_along(done):
    """The ensemble field removed (switched off, its pairs changed) left its .csv copy
    beside the new run, the older ensemble's vectors in it: the copies go with it."""
    _edit(done, 'folder = "results"', 'folder = "results"\nformats = ["csv"]')
    _rerun(done)
    ensemble = done / "results" / "ensemble.npz"
    assert ensemble.with_suffix(".csv").is_file()
    _edit(done, "windows = [12, 8]\nensemble = true", "windows = [12, 10]\nensemble = false")
    s, said = _rerun(done)
    assert s.processed == [0]
    assert not ensemble.exists() and not ensemble.with_suffix(".csv").exists(), said


def test_a_frame_rewritten_at_its_size_is_named_as_changed_content(done):
    """The refusal named the same file and size twice ("made from frame_001.tif (N
    bytes), now frame_001.tif (N bytes)"): it says the content changed."""
    from plenocl.io import read_image

    frame = sorted((done / "raw").glob("frame_*.tif"))[1]
    size = frame.stat().st_size
    image = read_image(frame)
    write_tiff(frame, (image + 1).astype(image.dtype))
    assert frame.stat().st_size == size
    with pytest.raises(ValueError, match=rf"made from {frame.name} \({size} bytes\), whose "
                                         r"content has changed since \(its SHA-256 differs\)"):
        plenocl.run(done / "experiment.toml", progress=False, log=lambda _: None)
