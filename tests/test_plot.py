"""Figures of a user's own results: ``plenocl plot`` for fields, volumes, tracks and a
batch's store, the batch's summary figures, and the derivatives behind the vorticity."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl.batch.trackstore import track_variables
from plenocl.cli.main import main
from plenocl.grid import Grid
from plenocl.io.timeseries import write_timeseries
from plenocl.io.zarrstore import write_store
from plenocl.plot import PlotOptions, VectorData, batch_figures, plot_file, read_vector_field
from plenocl.plot.derivatives import derivative, vorticity
from plenocl.plot.planes import plane_indices, thinning_step
from plenocl.plot.profiles import plane_means
from plenocl.plot.timeseries import SUMMARY_FIGURES, nearest_vector
from plenocl.plot.vectors3d import isosurfaces, thinned
from plenocl.ptv import Tracks
from plenocl.vectorfield import PIVResult, save_field
from plenocl.volumefile import save_volume

PNG = b"\x89PNG\r\n\x1a\n"
VOXEL = (0.2, 0.1, 0.1)  # (dz, dy, dx) mm
DT = 1e-3


def _result(shape=(4, 5, 6), flow=None, invalid=()) -> PIVResult:
    """A field on a vector grid 4 voxels apart whose displacement (voxels) is
    ``flow(x, y, z)`` of the window centres (voxel units)."""
    nz, ny, nx = shape
    x, y, z = (np.arange(n) * 4.0 + 8.0 for n in (nx, ny, nz))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    u, v, w = flow(xx, yy, zz) if flow else (np.full(shape, 1.0), np.full(shape, 2.0),
                                             np.full(shape, 0.5))
    valid = np.ones(shape, bool)
    for index in invalid:
        valid[index] = False
    return PIVResult(x=x, y=y, z=z, u=u, v=v, w=w, valid=valid,
                     peak_ratio=np.full(shape, np.nan), outlier=~valid,
                     masked=np.zeros(shape, bool), window=(8, 8, 8))


def _data(shape, spacing, velocity) -> VectorData:
    """A :class:`VectorData` on coordinates ``spacing`` (dx, dy, dz) mm apart, from
    ``velocity(x, y, z)`` (mm) in m/s."""
    nz, ny, nx = shape
    x, y, z = (np.arange(n) * s - 0.3 for n, s in zip((nx, ny, nz), spacing))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return VectorData(x, y, z, velocity=np.stack(velocity(xx, yy, zz)),
                      valid=np.ones(shape, bool))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A field, a field without dt, a volume with its grid, tracks and a store of three
    pairs (the last with a quarter of its vectors invalid)."""
    d = tmp_path_factory.mktemp("plot")
    save_field(d / "field.npz", _result(), VOXEL, dt=DT)
    save_field(d / "nodt.npz", _result(), VOXEL)
    grid = Grid((6, 8, 10), x=(-1.0, 1.0), y=(-0.8, 0.8), z=(-0.6, 0.6))
    vol = np.zeros(grid.shape, np.float32)
    vol[3, 4, 5] = 7.0
    save_volume(d / "vol.npz", vol, grid)
    t = np.arange(6)[None, :, None] * 1e-3
    start = np.random.default_rng(1).uniform(-1, 1, (5, 1, 3))
    measured = start + t * np.array([0.4e3, 0.0, 0.1e3])  # mm: 0.4 m/s along x
    tracks = Tracks.from_measured(measured, np.full(measured.shape, 1e-3),
                                  np.ones(measured.shape[:2]), dt=1e-3, window=5)
    tracks.save(d / "tracks.npz")
    write_store(d / "tracks.zarr", track_variables(tracks, range(6)))  # a tracking run's
    fields = []
    for k in range(3):
        invalid = [(slice(None), slice(0, 2))] if k == 2 else []
        path = d / f"pair_{k}.npz"
        save_field(path, _result(invalid=invalid), VOXEL, dt=DT)
        fields.append((k, 0.1 * k, path))
    write_timeseries(d / "timeseries.zarr", fields)
    return d


def test_vorticity_of_solid_body_rotation_is_twice_its_rate_and_zero_when_uniform():
    omega = 150.0  # 1/s
    shape, spacing = (5, 7, 9), (0.25, 0.4, 0.3)

    def rotation(x, y, z):  # m/s from mm
        return -omega * y * 1e-3, omega * x * 1e-3, np.zeros_like(x)

    data = _data(shape, spacing, rotation)
    valid = data.valid.copy()
    valid[2, 3, 4] = False  # the stencils around it fall back, never use it
    wx, wy, wz = vorticity(data.velocity, valid, data.x, data.y, data.z)
    assert np.isnan(wz[2, 3, 4]) and np.isfinite(wz[valid]).all()
    np.testing.assert_allclose(wz[valid], 2 * omega, rtol=1e-9)
    np.testing.assert_allclose([wx[valid], wy[valid]], 0.0, atol=1e-9)
    uniform = _data(shape, spacing, lambda x, y, z: (np.full_like(x, 3.0), np.ones_like(x),
                                                     np.zeros_like(x)))
    np.testing.assert_allclose(vorticity(uniform.velocity, uniform.valid, uniform.x,
                                         uniform.y, uniform.z), 0.0, atol=1e-9)


def test_the_least_squares_derivative_passes_a_fifth_of_the_noise_of_a_central_one():
    """On independent noise of variance s², the least-squares stencil's derivative has
    variance s² / (10 h²), the central difference's s² / (2 h²)."""
    noise = np.random.default_rng(0).normal(size=(200, 400))
    h = 0.5
    d_ls = derivative(noise, h, axis=1)[:, 2:-2]
    d_c = (noise[:, 2:] - noise[:, :-2])[:, 1:-1] / (2 * h)
    assert np.var(d_ls) * h**2 == pytest.approx(0.1, rel=0.03)
    assert np.var(d_c) * h**2 == pytest.approx(0.5, rel=0.03)
    assert np.isfinite(derivative(noise, h, axis=1)).all()  # ends: one-sided stencils


@pytest.mark.parametrize("cap", [1, 10, 57, 300])
def test_thinning_caps_the_arrow_count_with_the_smallest_step(cap):
    data = _data((12, 20, 30), (0.1, 0.1, 0.1), lambda x, y, z: (x, y, z))
    points, vectors, step = thinned(data, cap)
    assert 0 < len(points) <= cap and vectors.shape == points.shape
    if step > 1:  # one step less would draw more than the cap
        assert np.prod([len(range(0, n, step - 1)) for n in data.shape]) > cap
    assert thinning_step((4, 4), 16) == 1 and thinning_step((8, 8), 16) == 2


def test_slices_are_vector_planes_and_a_plane_outside_is_refused():
    coord = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    assert plane_indices(coord, [0.2, -0.9, 1.2]) == [2, 0, 4]
    assert plane_indices(coord) == [1, 2, 3]  # inside the faces
    assert plane_indices(coord[:4]) == [0, 2, 3] and plane_indices(coord, count=2) == [1, 3]
    with pytest.raises(ValueError, match=r"outside the grid, which spans -1 to 1 mm"):
        plane_indices(coord, [1.5])


def test_plane_means_and_isosurfaces_follow_the_field():
    data = _data((6, 5, 4), (0.2, 0.2, 0.3), lambda x, y, z: (0 * x, 2.0 * z + 0 * x, 0 * x))
    v = data.component("v")
    v[0, 0, 0] = np.nan  # an invalid vector is left out of its plane's mean
    mean, std, count = plane_means(v, "z")
    np.testing.assert_allclose(mean, 2.0 * data.z)
    np.testing.assert_allclose(std, 0.0, atol=1e-12)
    assert count.tolist() == [19, 20, 20, 20, 20, 20]
    (tris,) = isosurfaces(data.component("v"), [2.0 * 0.5], data)  # the plane z = 0.5 mm
    np.testing.assert_allclose(tris[..., 2], 0.5, atol=1e-9)


def test_a_field_read_back_keeps_its_coordinates_and_velocity(files):
    data = read_vector_field(files / "field.npz")
    assert data.unit == "m/s" and data.shape == (4, 5, 6)
    dx = 0.1e-3 / DT  # m/s per voxel along x
    np.testing.assert_allclose(data.velocity[0], 1.0 * dx)
    np.testing.assert_allclose(np.diff(data.x), 0.4)  # 4 voxels of 0.1 mm
    # without dt: displacements in mm, each axis's voxels by their size (arrows in voxels
    # on axes in mm pointed the wrong way where the voxels are not cubes)
    nodt = read_vector_field(files / "nodt.npz")
    assert nodt.unit == "mm"
    np.testing.assert_allclose(nodt.velocity[0], 1.0 * 0.1)   # 1 voxel of 0.1 mm along x
    np.testing.assert_allclose(nodt.velocity, data.velocity * DT / 1e-3)


def test_a_turned_grid_names_its_frame_and_a_field_without_positions_is_refused(tmp_path):
    save_field(tmp_path / "plain.npz", _result(), VOXEL, dt=DT)
    assert read_vector_field(tmp_path / "plain.npz").label("u") == "u (m/s)"
    np.savez(tmp_path / "turned.npz", **_result().arrays(VOXEL, dt=DT, rotation_deg=30.0))
    data = read_vector_field(tmp_path / "turned.npz")
    assert "grid turned 30°" in data.label("x")
    assert data.label("u") == "u along the grid's x (m/s)"
    with np.load(tmp_path / "turned.npz") as stored:
        kept = {k: stored[k] for k in stored.files if not k.endswith("_mm")}
    np.savez(tmp_path / "bare.npz", **kept)
    with pytest.raises(ValueError, match=r"bare.npz holds no vector positions \(x_mm"):
        read_vector_field(tmp_path / "bare.npz")


@pytest.mark.parametrize("name, args, kind", [
    ("field.npz", [], "slices"),
    ("field.npz", ["--view", "profile", "--axis", "y"], "profile"),
    ("field.npz", ["--view", "vectors", "--max-arrows", "20"], "vectors"),
    ("field.npz", ["--view", "vorticity", "--axis", "x", "--at", "1.0"], "vorticity"),
    ("field.npz", ["--view", "iso", "--component", "u"], "iso"),
    ("vol.npz", [], "projection"),
    ("vol.npz", ["--view", "slices", "--axis", "x", "--at", "0"], "slices"),
    ("tracks.npz", [], "tracks"),
    ("tracks.zarr", [], "tracks"),
    ("timeseries.zarr", [], "mean"),
    ("timeseries.zarr", ["--view", "probe", "--probe", "1.0", "1.0", "2.0"], "probe"),
    ("timeseries.zarr", ["--view", "valid"], "valid"),
    ("timeseries.zarr", ["--view", "profile"], "profile"),
])
def test_plot_draws_each_kind_of_file(files, tmp_path, capsys, name, args, kind):
    import imageio.v3 as iio

    assert main(["plot", str(files / name), *args, "--out", str(tmp_path / "f.png")]) == 0
    assert "wrote" in capsys.readouterr().out
    data = (tmp_path / "f.png").read_bytes()
    assert data[:8] == PNG
    height, width = iio.imread(tmp_path / "f.png").shape[:2]
    assert 200 < width < 2500 and 200 < height < 2500
    assert not list(tmp_path.glob(".*part*"))  # written atomically, nothing left over


def test_plot_writes_pdf_and_names_its_default_output(files, tmp_path):
    out = plot_file(files / "field.npz", tmp_path / "slices.pdf", PlotOptions(axis="y"))
    assert out.read_bytes()[:5] == b"%PDF-"
    default = plot_file(files / "vol.npz")
    assert default == files / "vol_projection.png" and default.read_bytes()[:8] == PNG


@pytest.mark.parametrize("name, args, message", [
    ("field.npz", ["--out", "f.jpg"], r"name it \.png \(PNG\) or \.pdf"),
    ("field.npz", ["--view", "probe"], "is a field; its views are slices"),
    ("nodt.npz", ["--view", "vorticity"], "vorticity needs velocities"),
    ("field.npz", ["--at", "50"], "outside the grid"),
    ("timeseries.zarr", ["--view", "probe", "--probe", "0", "0", "90"], "outside the vectors"),
    ("pair_0.npz.missing", [], "no such file or store"),
])
def test_plot_refuses_bad_input_with_a_clear_message(files, capsys, name, args, message):
    import re

    assert main(["plot", str(files / name), *args]) == 2
    assert re.search(message, capsys.readouterr().err)


def test_plot_refuses_files_it_cannot_draw(tmp_path, capsys):
    (tmp_path / "raw.tif").write_bytes(b"II*\x00")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    assert main(["plot", str(tmp_path / "raw.tif")]) == 2
    assert "cannot plot 'raw.tif'" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "other.npz")]) == 2
    assert "holds no vector field, tracks or volume" in capsys.readouterr().err
    np.savez(tmp_path / "other.npz", volume=np.ones((8, 8, 8)), spacing=np.ones(3))
    assert main(["plot", str(tmp_path / "other.npz")]) == 2  # a volume of another tool
    assert "is not a volume plenocl.save_volume wrote" in capsys.readouterr().err
    np.savez(tmp_path / "none.npz", counts=np.arange(3))
    assert main(["plot", str(tmp_path / "none.npz")]) == 2
    assert "holds no vector field, tracks or volume" in capsys.readouterr().err
    # a damaged field is named damaged (each reader was tried and it read "holds no ...")
    raw = bytearray(save_field(tmp_path / "hurt.npz", _result(), VOXEL, dt=DT).read_bytes())
    raw[len(raw) // 3:len(raw) // 3 + 64] = bytes(64)
    (tmp_path / "hurt.npz").write_bytes(bytes(raw))
    assert main(["plot", str(tmp_path / "hurt.npz")]) == 2
    assert "damaged" in capsys.readouterr().err
    save_field(tmp_path / "field.h5", _result(), VOXEL, dt=DT)  # fields are plotted from .npz
    assert main(["plot", str(tmp_path / "field.h5")]) == 2
    assert "holds no 'volume' dataset" in \
        capsys.readouterr().err


def test_batch_figures_are_written_from_the_store(files, tmp_path):
    written = batch_figures(files / "timeseries.zarr", tmp_path / "figures")
    assert sorted(p.name for p in written) == sorted(SUMMARY_FIGURES)
    assert all(p.read_bytes()[:8] == PNG for p in written)
    from plenocl.io.zarrstore import read_store

    arrays, attrs = read_store(files / "timeseries.zarr")
    assert attrs["arrays"]["time"]["units"] == "s"
    iz, iy, ix = nearest_vector(arrays, (arrays["x"][3] + 0.1, arrays["y"][1], arrays["z"][2]))
    assert (iz, iy, ix) == (2, 1, 3)
    # the last pair lost two of five rows: its valid fraction, as the figure shows it
    fraction = arrays["valid"].reshape(3, -1).mean(axis=1)
    np.testing.assert_allclose(fraction, [1.0, 1.0, 0.6])


@pytest.mark.parametrize("shape", [(4, 1, 6), (3, 5, 1), (1, 1, 5)])
def test_a_field_one_vector_thin_is_drawn_in_every_view(tmp_path, shape):
    """A thin volume's field, one vector along an axis (a reduced camera's grid with the
    default windows): its slices and a batch's summary figures are drawn (as cells where
    a plane has no contours), not refused at the end of the run (found with
    benchmarks/throughput.py on a 40 x 40 lens camera: contourf raised)."""
    field = _result(shape)
    for axis in "xyz":
        out = plot_file(_saved(tmp_path, field), tmp_path / f"{axis}.png",
                        PlotOptions(axis=axis))
        assert out.read_bytes()[:8] == PNG
    fields = [(k, 0.1 * k, _saved(tmp_path, field, f"pair_{k}.npz")) for k in range(2)]
    write_timeseries(tmp_path / "series.zarr", fields)
    written = batch_figures(tmp_path / "series.zarr", tmp_path / "figures")
    assert sorted(p.name for p in written) == sorted(SUMMARY_FIGURES)


def _saved(folder, field: PIVResult, name: str = "thin.npz"):
    save_field(folder / name, field, VOXEL, dt=DT)
    return folder / name


def test_a_thin_plane_is_drawn_as_cells_of_its_values():
    """A plane one vector thin has no contours: its values are cells centred on the
    vectors, as wide as their spacing and, across the single row, as tall (not a line of
    zero height that shows only the background)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from plenocl.plot.slices import contour

    fig, ax = plt.subplots()
    try:
        mesh = contour(ax, np.array([0.0, 1.0, 2.0]), np.array([5.0]),
                       np.array([[0.1, 0.2, np.nan]]), (0.0, 0.4), "viridis")
        corners = mesh.get_coordinates()
        np.testing.assert_allclose(corners[0, :, 0], [-0.5, 0.5, 1.5, 2.5])
        np.testing.assert_allclose(corners[:, 0, 1], [4.5, 5.5])
        shown = np.ma.masked_invalid(mesh.get_array())
        np.testing.assert_allclose(shown.compressed(), [0.1, 0.2])  # the NaN stays grey
    finally:
        plt.close(fig)


@pytest.mark.parametrize("rotation", [0.0, 30.0])
def test_a_rotated_grids_field_is_drawn_on_its_axes(tmp_path, rotation):
    """A stored field's velocity is in object space and its coordinates along the grid's
    axes; the figures turn the velocity onto those axes before they differentiate or draw
    it: a rigid rotation at omega has |vorticity| 2 omega on any grid (the world velocity
    against grid coordinates gave 2 omega cos 30 degrees), and u stays -omega y."""
    from plenocl import Grid, PIVResult
    from plenocl.plot.data import read_vector_field
    from plenocl.plot.derivatives import vorticity_magnitude

    omega, dt = 100.0, 1e-4
    grid = Grid((16, 40, 48), x=(-6, 6), y=(-4, 4), z=(10, 18), rotation_deg=rotation)
    dz, dy, dx = grid.spacing
    x, y, z = np.arange(4, 48, 4.0), np.arange(4, 40, 4.0), np.arange(4, 16, 4.0)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    xg, yg = (grid.x[0] + (xx + 0.5) * dx) * 1e-3, (grid.y[0] + (yy + 0.5) * dy) * 1e-3  # m
    u, v = -omega * yg * dt / (dx * 1e-3), omega * xg * dt / (dy * 1e-3)  # voxels
    none = np.zeros(xx.shape, bool)
    result = PIVResult(x, y, z, u, v, 0 * u, ~none, np.ones(xx.shape), none, none, (8, 8, 8))
    data = read_vector_field(save_field(tmp_path / "f.npz", result, grid=grid, dt=dt))
    magnitude = vorticity_magnitude(data.velocity, data.valid, data.x, data.y, data.z)
    assert np.nanmedian(magnitude) == pytest.approx(2 * omega, rel=1e-6)
    np.testing.assert_allclose(data.velocity[0], -omega * yg, atol=1e-9)


def test_a_stores_mean_field_is_drawn_on_its_grids_axes(tmp_path):
    """The time-series store records its grid's rotation; its mean field is turned onto
    the grid's axes as a field file's is."""
    from plenocl import Grid, PIVResult
    from plenocl.io.timeseries import write_timeseries
    from plenocl.io.zarrstore import read_store
    from plenocl.plot.data import store_field

    grid = Grid((16, 16, 16), x=(-1, 1), y=(-1, 1), z=(0, 2), rotation_deg=30.0)
    x = y = z = np.arange(4, 16, 4.0)
    ones, none = np.ones((3, 3, 3)), np.zeros((3, 3, 3), bool)
    result = PIVResult(x, y, z, ones, 0 * ones, 0 * ones, ~none, ones, none, none, (8, 8, 8))
    path = save_field(tmp_path / "f.npz", result, grid=grid, dt=1e-3)  # u: 1 voxel along x
    arrays, attrs = read_store(write_timeseries(tmp_path / "s.zarr", [(0, 0.0, path)]))
    assert attrs["rotation_deg"] == 30.0
    mean = store_field(arrays, rotation_deg=attrs["rotation_deg"])
    np.testing.assert_allclose(mean.velocity[0], grid.spacing[2], rtol=1e-6)  # m/s, 1 ms
    np.testing.assert_allclose(mean.velocity[1], 0.0, atol=1e-9)


def test_a_volume_with_a_nan_voxel_is_drawn_on_its_own_scale_and_said(tmp_path):
    """One NaN voxel made the colour scale's percentile NaN: a figure saturated 0-1 for
    data up to 2600, in silence. It is drawn as no light, the scale the others', and said."""
    import imageio.v3 as iio

    from plenocl.plot.volume import volume_figure

    rng = np.random.default_rng(0)
    vol = (rng.random((6, 12, 14)) ** 8 * 2600).astype(np.float32)
    clean = iio.imread(volume_figure(tmp_path / "clean.png", vol))
    vol[2, 3, 4] = np.nan
    with pytest.warns(UserWarning, match=r"1 voxel\(s\) of the volume are NaN or Inf"):
        damaged = iio.imread(volume_figure(tmp_path / "nan.png", vol))
    assert damaged.shape == clean.shape
    assert np.mean(damaged != clean) < 0.01  # the same figure but for that voxel


def test_a_volume_is_saved_with_its_own_grid_only(tmp_path):
    grid = Grid((4, 6, 10), x=(-1.0, 1.0), y=(-0.6, 0.6), z=(-0.4, 0.4))
    with pytest.raises(ValueError, match=r"shape \(4, 18, 30\) is not its grid's \(4, 6, 10\)"):
        save_volume(tmp_path / "v.npz", np.zeros((4, 18, 30), np.float32), grid)
    assert not (tmp_path / "v.npz").exists()


def test_a_lost_ensemble_chunk_reads_unknown_not_a_valid_zero(files, tmp_path):
    """The ensemble arrays took zarr's fill value 0: a lost chunk read as a valid zero
    mean (and was drawn so); it reads NaN (the count -1) now."""
    import shutil

    import xarray as xr

    store = tmp_path / "timeseries.zarr"
    shutil.copytree(files / "timeseries.zarr", store)
    for name in ("u_mean", "u_rms", "valid_count"):
        shutil.rmtree(store / name / "c")
    ds = xr.open_zarr(store)
    assert np.isnan(ds["u_mean"].values).all() and np.isnan(ds["u_rms"].values).all()
    assert (ds["valid_count"].values == -1).all()
    assert np.isfinite(ds["v_mean"].values).any()  # the others as written


def test_track_speeds_are_labelled_in_the_units_of_their_dt(tmp_path):
    """Tracks whose dt is not seconds (plenocl.track takes a frame count) were labelled
    m/s, 1000x off: their speeds are mm per dt then; seconds stay m/s."""
    from plenocl.plot.tracks import tracks_with_speeds

    start = np.zeros((2, 1, 3))
    for dt, unit, scale in ((1.0, "mm per dt of 1", 1.0), (1e-3, "m/s", 1e-3)):
        measured = start + np.arange(6)[None, :, None] * np.array([2.0, 0.0, 0.0])
        tracks = Tracks.from_measured(measured, np.full(measured.shape, 1e-3),
                                      np.ones(measured.shape[:2]), dt=dt, window=5)
        _, velocities, got = tracks_with_speeds(tracks)
        assert got == unit
        np.testing.assert_allclose(np.nanmedian(velocities[..., 0]), 2.0 / dt * scale,
                                   rtol=1e-6)


def test_iso_surfaces_stop_where_the_field_holds_no_valid_vector():
    """NaN filled for marching cubes drew surfaces across a masked half (40 of 70
    triangles there): none lies farther than half a spacing from a valid vector now."""
    z, y, x = np.arange(6.0), np.arange(8.0), np.arange(8.0)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    u = 0.1 * xx
    valid = yy >= 4
    u[~valid] = np.nan
    data = VectorData(x, y, z, velocity=np.stack([u, 0 * u, 0 * u]), valid=valid)
    for tris in isosurfaces(data.component("u"), [0.25, 0.45], data):
        assert len(tris) > 0
        assert tris[..., 1].mean(axis=1).min() >= 3.5 - 1e-9   # y of the last valid row - 0.5
