"""Field files: one axis rule for every array (x, y, z triples named ``*_xyz``), version-1
files read converted, Tecplot ASCII and CSV tables, velocity as the ``.vti``'s active
vectors, and output paths checked before any work (issue 44)."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from plenocl import PIVResult
from plenocl.cli.main import main
from plenocl.io.fieldformat import AXES, read_field
from plenocl.io.outputs import check_output_folder
from plenocl.vectorfield import read_npz, save_field

#: An anisotropic field: a different voxel size, window, step and count along each axis.
SIZE_ZYX = (0.2, 0.1, 0.05)        # (dz, dy, dx) mm, as Grid.spacing
ORIGIN_ZYX = (3.0, 2.0, 1.0)       # (z0, y0, x0) mm
WINDOW_ZYX = (16, 12, 8)
DT = 2e-4


@pytest.fixture()
def field() -> PIVResult:
    """Window centres every 8 (z), 6 (y), 4 (x) voxels on a 3 x 4 x 5 grid; u depends on
    x only, v on y only, w on z only, so a value on the wrong axis shows; one masked
    (NaN) vector and one replaced outlier."""
    x, y, z = 4.0 + 4 * np.arange(5), 6.0 + 6 * np.arange(4), 8.0 + 8 * np.arange(3)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    shape = zz.shape
    u, v, w = 1.0 + 0.1 * xx, -2.0 + 0.05 * yy, 0.5 + 0.01 * zz
    masked = np.zeros(shape, bool)
    masked[2, 3, 4] = True
    for comp in (u, v, w):
        comp[masked] = np.nan
    outlier = np.zeros(shape, bool)
    outlier[1, 2, 3] = True
    return PIVResult(x=x, y=y, z=z, u=u, v=v, w=w, valid=~(masked | outlier),
                     peak_ratio=np.full(shape, 2.0), outlier=outlier, masked=masked,
                     window=WINDOW_ZYX, sigma_u=np.full(shape, 0.05),
                     sigma_v=np.full(shape, 0.04), sigma_w=np.full(shape, 0.2))


def _save(path: Path, res: PIVResult, dt: float | None = DT) -> Path:
    return save_field(path, res, voxel_size_mm=SIZE_ZYX, origin_mm=ORIGIN_ZYX, dt=dt)


# ------------------------------------------------------------------ one axis rule

def test_every_triple_is_xyz_and_values_land_on_their_axes(tmp_path, field):
    arrays = read_field(_save(tmp_path / "f.npz", field))
    assert int(arrays["format_version"]) == 2
    dz, dy, dx = SIZE_ZYX
    np.testing.assert_allclose(arrays["voxel_size_mm_xyz"], (dx, dy, dz))
    np.testing.assert_allclose(arrays["origin_mm_xyz"], ORIGIN_ZYX[::-1])
    np.testing.assert_array_equal(arrays["window_xyz"], WINDOW_ZYX[::-1])
    np.testing.assert_allclose(arrays["vector_spacing_mm_xyz"], (4 * dx, 6 * dy, 8 * dz))
    np.testing.assert_allclose(arrays["vector_origin_mm_xyz"],
                               (1.0 + 4 * dx, 2.0 + 6 * dy, 3.0 + 8 * dz))
    # the old names, whose order differed between them, are gone
    assert not {"voxel_size_mm", "origin_mm", "window", "vector_origin_mm",
                "vector_spacing_mm"} & set(arrays)
    # gridded arrays (.., nz, ny, nx); components (x, y, z), each scaled by its own axis
    assert arrays["velocity"].shape == (3, 3, 4, 5)
    np.testing.assert_allclose(arrays["x_mm"], 1.0 + dx * field.x)
    np.testing.assert_allclose(arrays["z_mm"], 3.0 + dz * field.z)
    for k, (comp, size) in enumerate(zip((field.u, field.v, field.w), (dx, dy, dz))):
        np.testing.assert_allclose(arrays["velocity"][k], comp * size * 1e-3 / DT)
    assert json.loads(str(arrays["metadata"]))["axes"] == AXES
    back, _ = read_npz(tmp_path / "f.npz")
    assert back.window == WINDOW_ZYX and back.step == (8, 6, 4)


def _old_file(path: Path, res: PIVResult) -> dict:
    """The field as the version-1 writer stored it: no ``format_version``,
    ``voxel_size_mm``, ``origin_mm`` and ``window`` (z, y, x), ``vector_origin_mm`` and
    ``vector_spacing_mm`` (x, y, z)."""
    new = read_field(_save(path.with_name("new.npz"), res))
    old = {k: v for k, v in new.items() if k != "format_version" and not k.endswith("_xyz")}
    dz, dy, dx = SIZE_ZYX
    x_mm, y_mm, z_mm = res.positions_mm(SIZE_ZYX, ORIGIN_ZYX)
    old.update(voxel_size_mm=np.asarray(SIZE_ZYX), origin_mm=np.asarray(ORIGIN_ZYX),
               window=np.asarray(res.window),
               vector_origin_mm=np.array([x_mm[0], y_mm[0], z_mm[0]]),
               vector_spacing_mm=np.array([x_mm[1] - x_mm[0], y_mm[1] - y_mm[0],
                                           z_mm[1] - z_mm[0]]))
    meta = json.loads(str(new["metadata"]))
    meta["axes"] = ("arrays (..., nz, ny, nx) on the vector grid, z slowest; vector "
                    "components (x, y, z); voxel_size_mm and origin_mm are (z, y, x)")
    old["metadata"] = np.asarray(json.dumps(meta))
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **old)
    return new


def test_a_version_1_file_is_read_in_the_current_layout(tmp_path, field):
    new = _old_file(tmp_path / "old.npz", field)
    back, arrays = read_npz(tmp_path / "old.npz")
    assert set(arrays) == set(new)
    for name in new:
        if name != "metadata":
            np.testing.assert_array_equal(arrays[name], new[name], err_msg=name)
    meta = json.loads(str(arrays["metadata"]))
    assert meta["axes"] == AXES and meta["converted_from_version"] == 1
    assert back.window == WINDOW_ZYX


def test_h5_reads_back_as_the_npz(tmp_path, field):
    npz = read_field(_save(tmp_path / "f.npz", field))
    h5 = read_field(_save(tmp_path / "f.h5", field))
    assert set(h5) == set(npz)
    for name in npz:
        if name != "metadata":
            np.testing.assert_array_equal(h5[name], npz[name], err_msg=name)
    assert json.loads(str(h5["metadata"])) == json.loads(str(npz["metadata"]))
    back, _ = read_npz(tmp_path / "f.h5")
    np.testing.assert_array_equal(back.w, field.w)


def test_tables_are_not_read_back_as_fields(tmp_path, field):
    with pytest.raises(ValueError, match="reads fields back from .npz and .h5"):
        read_field(_save(tmp_path / "f.csv", field))


# ------------------------------------------------------------------ tables

def _grid_columns(arrays: dict) -> dict[str, np.ndarray]:
    """What the table's rows should hold, x fastest."""
    zz, yy, xx = np.meshgrid(arrays["z_mm"], arrays["y_mm"], arrays["x_mm"], indexing="ij")
    want = {"x [mm]": xx, "y [mm]": yy, "z [mm]": zz}
    want.update({f"{c} [m/s]": arrays["velocity"][k] for k, c in enumerate("uvw")})
    want.update({f"{c}_voxel [voxel]": arrays["displacement"][k] for k, c in enumerate("uvw")})
    want.update({f: arrays[f].astype(float) for f in ("valid", "outlier", "masked")})
    want.update({f"{c}_sigma [m/s]": arrays["velocity_uncertainty"][k]
                 for k, c in enumerate("uvw")})
    want.update({f"{c}_sigma_voxel [voxel]": arrays["displacement_uncertainty"][k]
                 for k, c in enumerate("uvw")})
    return {k: np.asarray(v, float).ravel() for k, v in want.items()}


def test_csv_round_trip(tmp_path, field):
    arrays = read_field(_save(tmp_path / "f.npz", field))
    path = _save(tmp_path / "f.csv", field)
    with open(path, newline="") as fh:       # a plain header a DataFrame reader takes
        header = next(csv.reader(fh))
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    want = _grid_columns(arrays)
    assert header == list(want) and data.shape == (field.u.size, len(want))
    for k, name in enumerate(header):
        np.testing.assert_allclose(data[:, k], want[name], rtol=1e-9, err_msg=name)
    masked = data[:, header.index("masked")] == 1
    assert masked.sum() == 1 and np.isnan(data[masked, header.index("u [m/s]")]).all()


def test_a_rotated_grids_tables_give_positions_in_the_velocitys_frame_too(tmp_path, field):
    """On a grid turned 10 degrees the tables' x, y [mm] lie along the grid's axes and
    u, v [m/s] in object space (a solid-body check against them erred 17 %): the rows
    also give x_object, y_object [mm], where u, v are the grid-axis displacement turned
    the same way; the Tecplot file says the turn; an unturned field's tables are as they
    were."""
    from plenocl import Grid

    grid = Grid((40, 36, 28), x=(-1.4, 1.4), y=(-1.8, 1.8), z=(-4.0, 4.0), rotation_deg=10.0)
    path = save_field(tmp_path / "r.csv", field, grid=grid, dt=DT)
    with open(path, newline="") as fh:
        header = next(csv.reader(fh))
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    col = {name: data[:, k] for k, name in enumerate(header)}
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    x, y = col["x [mm]"], col["y [mm]"]
    np.testing.assert_allclose(col["x_object [mm]"], c * x - s * y, rtol=1e-9)
    np.testing.assert_allclose(col["y_object [mm]"], s * x + c * y, rtol=1e-9)
    dz, dy, dx = grid.spacing
    ug, vg = (col[f"{a}_voxel [voxel]"] * d * 1e-3 / DT for a, d in (("u", dx), ("v", dy)))
    ok = col["masked"] == 0
    np.testing.assert_allclose(col["u [m/s]"][ok], (c * ug - s * vg)[ok], rtol=1e-8)
    np.testing.assert_allclose(col["v [m/s]"][ok], (s * ug + c * vg)[ok], rtol=1e-8)
    text = save_field(tmp_path / "r.dat", field, grid=grid, dt=DT).read_text()
    assert "# the grid is turned 10 deg about the optical axis" in text
    assert '"x_object [mm]"' in text
    plain = _save(tmp_path / "p.csv", field).read_text()
    assert "x_object" not in plain.splitlines()[0]


def _read_tecplot(path: Path) -> tuple[list[str], dict[str, int], np.ndarray]:
    lines = path.read_text().splitlines()
    names = re.findall(r'"([^"]*)"', next(s for s in lines if s.startswith("VARIABLES")))
    at = next(k for k, s in enumerate(lines) if s.startswith("ZONE"))
    zone = {k: int(v) for k, v in re.findall(r"\b([IJK])=(\d+)", lines[at])}
    assert "DATAPACKING=POINT" in lines[at]
    return names, zone, np.loadtxt(lines[at + 1:])


def test_tecplot_ordered_zone_x_fastest(tmp_path, field):
    arrays = read_field(_save(tmp_path / "f.npz", field))
    path = _save(tmp_path / "f.dat", field)
    assert "nan" not in path.read_text().lower()      # Tecplot reads NaN poorly
    names, zone, data = _read_tecplot(path)
    assert zone == {"I": 5, "J": 4, "K": 3}           # x, y, z counts
    want = _grid_columns(arrays)
    assert names == list(want)
    masked = want["masked"] == 1
    for k, name in enumerate(names):
        np.testing.assert_allclose(data[~masked, k], want[name][~masked], rtol=1e-9,
                                   err_msg=name)
    # the masked vector: zeros, flagged invalid and masked; the outlier keeps its value
    row = data[masked][0]
    assert row[names.index("u [m/s]")] == 0 and row[names.index("valid")] == 0
    out = want["outlier"] == 1
    assert data[out, names.index("valid")][0] == 0
    assert data[out, names.index("u_voxel [voxel]")][0] == pytest.approx(field.u[1, 2, 3])


def test_tecplot_writes_an_unknown_uncertainty_as_negative(tmp_path, field):
    """piv3d gives invalid and masked vectors a NaN uncertainty: the Tecplot file wrote 0
    (a perfect vector); it writes -1 there, and the CSV keeps nan."""
    import dataclasses

    unknown = ~field.valid
    sigma = {f"sigma_{c}": np.where(unknown, np.nan, getattr(field, f"sigma_{c}"))
             for c in "uvw"}
    path = _save(tmp_path / "f.dat", dataclasses.replace(field, **sigma))
    assert "written as -1" in path.read_text()
    names, _, data = _read_tecplot(path)
    rows = unknown.ravel()
    for name in names:
        if "sigma" in name:
            assert (data[rows, names.index(name)] == -1).all(), name
            assert (data[~rows, names.index(name)] > 0).all(), name
    assert data[field.masked.ravel(), names.index("u [m/s]")][0] == 0  # values stay 0


def test_tables_without_dt_hold_displacements_only(tmp_path, field):
    path = _save(tmp_path / "f.dat", field, dt=None)
    names, _, _ = _read_tecplot(path)
    assert "u [m/s]" not in names and "w_voxel [voxel]" in names


# ------------------------------------------------------------------ .vti

def _vti_point_data(path: Path) -> tuple[dict, list[str]]:
    text = path.read_bytes().partition(b"<AppendedData")[0].decode("ascii")
    attrs = dict(re.findall(r'(\w+)="([^"]*)"', re.search(r"<PointData([^>]*)>",
                                                          text).group(1)))
    return attrs, re.findall(r'<DataArray [^>]*Name="([^"]*)"', text)


def test_vti_velocity_is_the_active_vector(tmp_path, field):
    attrs, names = _vti_point_data(_save(tmp_path / "f.vti", field))
    assert attrs["Vectors"] == "velocity_m_per_s" and names[0] == "velocity_m_per_s"
    assert "displacement_voxels" in names
    attrs, _ = _vti_point_data(_save(tmp_path / "g.vti", field, dt=None))
    assert attrs["Vectors"] == "displacement_voxels"      # no dt, no velocity


# ------------------------------------------------------------------ checked first

def _fail_if_called(*args, **kwargs):
    raise AssertionError("the computation ran before the output path was checked")


def test_piv_refuses_an_unknown_format_before_any_work(tmp_path, capsys, monkeypatch):
    import plenocl.piv

    monkeypatch.setattr(plenocl.piv, "piv3d", _fail_if_called)
    # the volumes do not exist: a late check would fail on them first
    args = ["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--dt", "1e-3"]
    assert main([*args, "--out", str(tmp_path / "f.xyz")]) == 2
    err = capsys.readouterr().err
    assert "cannot tell the field format from 'f.xyz'" in err
    for ext in (".vti", ".npz", ".h5", ".dat (Tecplot ASCII)", ".csv"):
        assert ext in err
    assert "no such volume" not in err


def test_reconstruct_refuses_a_field_extension_before_reading(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "raw.tif"), "--camera", "synthetic",
                 "--grid", str(tmp_path / "grid.toml"), "--out", str(tmp_path / "v.vti")]) == 2
    err = capsys.readouterr().err
    assert "cannot tell the volume format from 'v.vti'" in err and ".npy" in err


def _unwritable(tmp_path: Path) -> Path:
    """A folder this process cannot create files in (root ignores mode bits: /sys)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    for folder in (locked, Path("/sys")):
        try:
            check_output_folder(folder)
        except ValueError:
            return folder
    pytest.skip("no folder here refuses writes to this process")


def test_outputs_in_unwritable_folders_are_refused_before_work(tmp_path, capsys):
    folder = _unwritable(tmp_path)
    args = ["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--dt", "1e-3"]
    assert main([*args, "--out", str(folder / "f.vti")]) == 2
    assert f"cannot write in {folder}" in capsys.readouterr().err
    (tmp_path / "note.txt").write_text("a file")
    assert main([*args, "--out", str(tmp_path / "note.txt" / "f.csv")]) == 2
    assert "note.txt is a file, not a folder" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "new" / "deeper" / "f.csv")]) != 0
    assert "no such volume" in capsys.readouterr().err   # a folder to be made passes
    # plot checks its figure's folder first too (it drew, then failed with an OS error)
    assert main(["plot", str(tmp_path / "a.npz"), "--out",
                 str(tmp_path / "note.txt" / "f.png")]) == 2
    assert "note.txt is a file, not a folder" in capsys.readouterr().err
    assert main(["plot", str(folder / "a.npz")]) == 2  # the default: beside the input
    assert f"cannot write in {folder}" in capsys.readouterr().err


def test_run_refuses_an_unwritable_output_folder_before_work(tmp_path, monkeypatch):
    import importlib

    batch_run = importlib.import_module("plenocl.batch.run")   # the module, not run()
    monkeypatch.setattr(batch_run, "run_cameras", _fail_if_called)
    (tmp_path / "experiment.toml").write_text(
        '[camera]\npreset = "synthetic"\n[grid]\nz_mm = [-2.0, 2.0]\n[images]\n'
        'folder = "raw"\ndt_s = 1e-3\n[output]\nfolder = "results"\n')
    (tmp_path / "results").write_text("a file where the results folder goes")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        batch_run.run(tmp_path / "experiment.toml", progress=False)


def test_cli_writes_tecplot_and_csv(tmp_path, capsys):
    """``plenocl piv --out f.dat`` / ``f.csv`` on two small volumes, the second the first
    shifted by 2 voxels along x: the tables hold the field the .npz holds."""
    from plenocl import Grid
    from plenocl.volumefile import save_volume

    rng = np.random.default_rng(3)
    vol = np.zeros((32, 32, 40), np.float32)
    vol[tuple(rng.integers(2, 30, (3, 300)))] = 1.0
    grid = Grid(shape=vol.shape, x=(0.0, 4.0), y=(0.0, 3.2), z=(0.0, 6.4))
    save_volume(tmp_path / "a.npz", vol, grid)
    save_volume(tmp_path / "b.npz", np.roll(vol, 2, axis=2), grid)
    base = ["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--dt", "1e-3",
            "--windows", "16", "--no-particles", "--out"]
    for name in ("f.npz", "f.csv", "f.dat"):
        assert main([*base, str(tmp_path / name)]) == 0, capsys.readouterr().err
    arrays = read_field(tmp_path / "f.npz")
    table = np.loadtxt(tmp_path / "f.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 3], arrays["velocity"][0].ravel(), rtol=1e-9)
    assert np.median(table[:, 6]) == pytest.approx(2.0, abs=0.1)   # u in voxels
    _, zone, data = _read_tecplot(tmp_path / "f.dat")
    assert (zone["K"], zone["J"], zone["I"]) == arrays["velocity"].shape[1:]
    np.testing.assert_allclose(data[:, :3], table[:, :3], rtol=1e-9)


# ------------------------------------------------------------------ batch runs

def test_experiment_output_formats(tmp_path):
    from plenocl.batch.config import output_formats

    assert output_formats({"formats": ["dat", ".CSV"], "vti": True}) == (".dat", ".csv", ".vti")
    assert output_formats({"formats": ["vti"], "vti": True}) == (".vti",)
    with pytest.raises(ValueError, match=r"unknown format\(s\) \['xlsx'\]"):
        output_formats({"formats": ["xlsx"], "vti": False})
    with pytest.raises(ValueError, match="must be a list of format names"):
        output_formats({"formats": "dat", "vti": False})


def test_each_pair_is_written_in_the_asked_formats(tmp_path, field, monkeypatch):
    """A run's worker writes each pair's field in ``[output] formats`` beside its .npz,
    every copy holding the field the .npz holds (the chain itself replaced by a stub)."""
    from types import SimpleNamespace

    import plenocl.batch.worker as worker
    from plenocl import Camera, Grid, PairSettings

    Camera.synthetic_850().to_toml(tmp_path / "camera_used.toml")
    # the volumes the field's windows came from (save_field refuses another grid)
    Grid(shape=(32, 30, 24), x=(0.0, 2.4), y=(0.0, 3.0), z=(0.0, 6.4)).to_toml(
        tmp_path / "grid_used.toml")
    formats = (".dat", ".csv", ".vti")
    proc = worker.PairProcessor(tmp_path, worker.RunSettings(PairSettings(), DT, formats))
    monkeypatch.setattr(proc, "frame", lambda path: np.zeros((4, 4)))
    monkeypatch.setattr(worker, "process_pair", lambda *args, **kwargs: SimpleNamespace(
        piv=field, seconds={}, vol_a=None, vol_b=None))
    for name in ("a.tif", "b.tif"):
        (tmp_path / name).write_bytes(b"raw")
    target = tmp_path / "pairs" / "pair_00000.npz"
    outcome = proc(worker.PairTask(0, str(tmp_path / "a.tif"), str(tmp_path / "b.tif"),
                                   str(target)))
    assert outcome.error is None
    assert sorted(p.name for p in target.parent.iterdir()) == [
        "pair_00000.csv", "pair_00000.dat", "pair_00000.npz", "pair_00000.vti"]
    arrays = read_field(target)
    table = np.loadtxt(target.with_suffix(".csv"), delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 3], arrays["velocity"][0].ravel(), rtol=1e-9)
    _, zone, _ = _read_tecplot(target.with_suffix(".dat"))
    assert (zone["K"], zone["J"], zone["I"]) == field.shape


def test_every_command_checks_its_outputs_first(tmp_path, capsys):
    """Each command refuses an output it cannot write before reading any input (none of
    the inputs named here exists)."""
    missing = str(tmp_path / "missing")
    cases = {
        "volume": ["reconstruct", missing, "--camera", "synthetic", "--grid", missing],
        "camera": ["calibrate", missing, "--camera", "synthetic"],
        "focal stack": ["refocus", missing, "--camera", "synthetic", "--z", "0"],
        "raw image": ["simulate", "--particles", missing],
        "white image": ["white"],
        "grid": ["grid", "--z", "-1", "1"],
    }
    for what, args in cases.items():
        assert main([*args, "--out", str(tmp_path / "out.xyz")]) == 2, what
        assert f"cannot tell the {what} format from 'out.xyz'" in capsys.readouterr().err
    assert main(["calibrate", missing, "--camera", "synthetic", "--out",
                 str(tmp_path / "c.toml"), "--diagnostic", str(tmp_path / "d.txt")]) == 2
    assert "diagnostic figure format" in capsys.readouterr().err
    (tmp_path / "note.txt").write_text("a file")
    for command in ("demo", "bench"):
        assert main([command, "--out", str(tmp_path / "note.txt" / "results")]) == 2
        assert "is a file, not a folder" in capsys.readouterr().err
    assert not (tmp_path / "out.xyz").exists()


def test_a_full_disk_names_the_folder_and_the_fix(tmp_path, field, monkeypatch, capsys):
    """Out of space while a pair is written: the pair fails naming the output folder and
    the fix (free space, --out; a rerun makes it), and an out-of-space error reaching the
    command line is one line with that fix and exit status 2, not a traceback."""
    import errno
    import importlib

    import plenocl.batch.worker as worker
    from plenocl import Camera, Grid, PairSettings

    cli = importlib.import_module("plenocl.cli.main")  # the module, not its main()

    Camera.synthetic_850().to_toml(tmp_path / "camera_used.toml")
    Grid(shape=(32, 30, 24), x=(0.0, 2.4), y=(0.0, 3.0), z=(0.0, 6.4)).to_toml(
        tmp_path / "grid_used.toml")
    proc = worker.PairProcessor(tmp_path, worker.RunSettings(PairSettings(), DT, (".dat",)))
    monkeypatch.setattr(proc, "frame", lambda path: np.zeros((4, 4)))
    full = OSError(errno.ENOSPC, "No space left on device")

    def no_space(*args, **kwargs):
        raise full

    monkeypatch.setattr(worker, "process_pair", no_space)
    for name in ("a.tif", "b.tif"):
        (tmp_path / name).write_bytes(b"raw")
    target = tmp_path / "pairs" / "pair_00000.npz"
    outcome = proc(worker.PairTask(0, str(tmp_path / "a.tif"), str(tmp_path / "b.tif"),
                                   str(target)))
    assert f"no space left on the disk of {target.parent}" in outcome.error
    assert "--out" in outcome.error and "a rerun makes" in outcome.error
    monkeypatch.setattr(cli, "check_outputs", no_space)
    assert cli.main(["devices"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("plenocl devices: error: [Errno 28]") and "(--out)" in err
