"""The command line and the examples, run as a user would."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

from plenocl.cli.main import main
from plenocl.io import read_particles, write_particles

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_devices_command(capsys):
    assert main(["devices"]) == 0
    assert "platform 0" in capsys.readouterr().out


def test_python_dash_m_runs_the_cli():
    out = subprocess.run([sys.executable, "-m", "plenocl", "devices"], capture_output=True,
                         text=True, check=True)
    assert "64-bit atomics" in out.stdout


def test_simulate_writes_16_bit_tiff_and_truth(tmp_path, small_camera):
    small_camera.to_toml(tmp_path / "cam.toml")
    pos = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 1.0]])
    write_particles(tmp_path / "p.csv", pos, [3e4, 3e4])
    rc = main(["simulate", "--camera", str(tmp_path / "cam.toml"), "--particles",
               str(tmp_path / "p.csv"), "--out", str(tmp_path / "raw.tif"), "--rays", "500"])
    assert rc == 0
    img = tifffile.imread(tmp_path / "raw.tif")
    assert img.dtype == np.uint16 and img.shape == (170, 204) and img.max() > 0
    truth, inten = read_particles(tmp_path / "raw_particles.csv")
    np.testing.assert_allclose(truth, pos)


def test_simulate_several_cameras_writes_each_cameras_pair_in_its_folder(tmp_path,
                                                                           small_camera,
                                                                           monkeypatch):
    """``--camera`` with several files: each posed camera's images of the same world
    particles in ``camK/`` beside ``--out`` (the same names: the batch's frame numbers),
    each the Python simulator's image through that camera's pose, the truth once."""
    from plenocl import simulate_image
    from plenocl.camera import Pose

    cams = [small_camera.with_pose(Pose((0.0, t, 0.0), (0.0, 0.0, 0.0))) for t in (-12.5, 12.5)]
    for k, cam in enumerate(cams, start=1):
        cam.to_toml(tmp_path / f"cam{k}.toml")
    pos = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 1.0]])
    write_particles(tmp_path / "p.csv", pos, [3e4, 3e4])
    rc = main(["simulate", "--camera", str(tmp_path / "cam1.toml"), str(tmp_path / "cam2.toml"),
               "--particles", str(tmp_path / "p.csv"), "--out", str(tmp_path / "raw.tif"),
               "--rays", "500", "--velocity", "0.5", "0", "0", "--dt", "1e-3", "--seed", "4"])
    assert rc == 0
    truth_a, _ = read_particles(tmp_path / "raw_a_particles.csv")
    images = {}
    for k, cam in enumerate(cams, start=1):
        for tag in "ab":
            images[k, tag] = tifffile.imread(tmp_path / f"cam{k}" / f"raw_{tag}.tif")
        expected = simulate_image(cam, truth_a, 3e4, 500, 4 + k - 1, bit_depth=16)
        np.testing.assert_array_equal(images[k, "a"], expected)
    assert not np.array_equal(images[1, "a"], images[2, "a"])  # two views
    assert not list(tmp_path.glob("raw_*.tif"))  # each camera's images in its folder
    # the second camera's image refused: the first's is not left behind either
    import plenocl.simulate as simulate_module

    calls = []

    def second_refused(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("refused for the test")
        return simulate_image(*args, **kwargs)

    monkeypatch.setattr(simulate_module, "simulate_image", second_refused)
    rc = main(["simulate", "--camera", str(tmp_path / "cam1.toml"), str(tmp_path / "cam2.toml"),
               "--particles", str(tmp_path / "p.csv"), "--out", str(tmp_path / "new.tif"),
               "--rays", "50", "--velocity", "0.5", "0", "0", "--dt", "1e-3"])
    assert rc == 2 and not list(tmp_path.rglob("new*"))


def test_simulate_reports_bad_files_clearly(tmp_path, capsys):
    (tmp_path / "p.csv").write_text("x_mm,y_mm\n1,2\n")
    rc = main(["simulate", "--particles", str(tmp_path / "p.csv"), "--out",
               str(tmp_path / "o.tif")])
    assert rc == 2 and "x_mm,y_mm,z_mm" in capsys.readouterr().err
    assert not (tmp_path / "o.tif").exists()  # nothing half-written


def test_particle_example_runs_small(tmp_path):
    subprocess.run([sys.executable, str(EXAMPLES / "simulate_particles.py"), str(tmp_path), "20"],
                   check=True, capture_output=True)
    img = tifffile.imread(tmp_path / "raw.tif")
    assert img.shape == (850, 850) and (tmp_path / "raw_preview.png").stat().st_size > 0


def test_synthetic_reconstruction_example_runs(tmp_path):
    out = subprocess.run([sys.executable, str(EXAMPLES / "synthetic_reconstruction.py"), "8",
                          "3"], check=True, capture_output=True, text=True, cwd=tmp_path)
    assert "paper's MART" in out.stdout and "default (MLEM" in out.stdout


def test_cli_rounds_out(tmp_path, capsys):
    """--version, --device after the subcommand, defaults in the help, presets listed for
    a misspelt camera, an empty image file named, a particle CSV without its header,
    volumes of different grids refused, a rotated grid kept by the volume file."""
    import numpy as np

    from plenocl import Grid
    from plenocl.cli.main import build_parser, main
    from plenocl.io import read_particles
    from plenocl.volumefile import load_volume, save_volume

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and "plenocl 0." in capsys.readouterr().out
    args = build_parser().parse_args(["piv", "a.npz", "b.npz", "--dt", "1e-4", "--out", "f.vti",
                                      "--device", "pthread"])
    assert args.device == "pthread"
    assert build_parser().parse_args(["--device", "cpu", "devices"]).device == "cpu"
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert "(default: 2000)" in capsys.readouterr().out
    empty = tmp_path / "raw.tif"
    empty.write_bytes(b"")
    assert main(["reconstruct", str(empty), "--camera", "synthtic", "--grid", "g.toml",
                 "--out", str(tmp_path / "v.npz")]) == 2
    assert "presets ['paper', 'synthetic']" in capsys.readouterr().err
    from plenocl.io import read_image

    with pytest.raises(ValueError, match="raw.tif is empty"):
        read_image(empty)
    csv = tmp_path / "p.csv"
    csv.write_text("0.1,0.2,0.3\n0.4,0.5,0.6\n")
    with pytest.raises(ValueError, match="is a particle, not the header"):
        read_particles(csv)
    g1 = Grid((8, 8, 8), (-1, 1), (-1, 1), (-1, 1), rotation_deg=0.3)
    g2 = Grid((8, 8, 8), (-1, 1), (-1, 1), (-2, 2))
    vol = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)
    save_volume(tmp_path / "a.npz", vol, g1)
    save_volume(tmp_path / "b.npz", vol, g2)
    assert load_volume(tmp_path / "a.npz")[1] == g1
    assert main(["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--dt", "1e-4",
                 "--out", str(tmp_path / "f.npz")]) == 2
    assert "different grids" in capsys.readouterr().err


def test_likely_mistakes_warn_in_the_library(queue):
    """Particles outside the field of view, an image too dim to reconstruct, a grid
    reaching well beyond the field of view."""
    from plenocl import Camera, Grid, Projector, reconstruct, simulate_image

    cam = Camera.synthetic_850()
    with pytest.warns(UserWarning, match="outside the field of view"):
        simulate_image(cam, np.array([[40.0, 0.0, 0.0]]), 1e4, 200, queue=queue)
    with pytest.warns(UserWarning, match="too dim"):
        simulate_image(cam, np.array([[0.1, 0.0, 0.0]]), 1000.0, 2000, queue=queue)
    img = simulate_image(cam, np.array([[0.1, 0.2, 0.3]]), 2e4, 2000, queue=queue)
    wide = Grid((8, 40, 40), x=(-6.0, 6.0), y=(-6.0, 6.0), z=(-1.0, 1.0))
    with pytest.warns(UserWarning, match="beyond the camera's field of view"):
        reconstruct(img, Projector(cam, wide, queue), iterations=1, supersample=1)
    # coarse-to-fine: once, from the coarse run (its sub-voxels cover the same extent)
    wider = Grid((8, 40, 40), x=(-7.0, 7.0), y=(-7.0, 7.0), z=(-1.0, 1.0))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        reconstruct(img, Projector(cam, wider, queue), iterations=2, supersample=2,
                    coarse_iterations=1, early_iterations=1, early_oversample=0.6)
    assert sum("field of view" in str(w.message) for w in seen) == 1


def test_a_whole_experiment_from_the_command_line(tmp_path, capsys):
    """white image -> calibrate -> grid -> displaced pair -> reconstruct -> piv, all from
    the command line: the field moves the way the particles were moved."""
    from plenocl import random_particles
    from plenocl.io import write_particles
    from plenocl.vectorfield import read_npz

    d = tmp_path
    assert main(["white", "--out", str(d / "white.tif"), "--photon-noise"]) == 0
    assert main(["calibrate", str(d / "white.tif"), "--camera", "synthetic",
                 "--out", str(d / "cam.toml")]) == 0
    assert main(["grid", "--camera", str(d / "cam.toml"), "--z", "-2", "2",
                 "--fraction", "0.6", "--out", str(d / "grid.toml")]) == 0
    pos, inten = random_particles(((-1.6, 1.6), (-1.6, 1.6), (-1.8, 1.8)), count=300,
                                  seed=2, intensity=3e4)
    write_particles(d / "p.csv", pos, inten)
    # 0.25 m/s for 1 ms: 0.25 mm, two voxels of 0.125 mm along x
    assert main(["simulate", "--particles", str(d / "p.csv"), "--velocity", "0.25", "0", "0",
                 "--dt", "1e-3", "--rays", "3000", "--out", str(d / "raw.tif")]) == 0
    for tag in "ab":
        assert main(["reconstruct", str(d / f"raw_{tag}.tif"), "--camera", str(d / "cam.toml"),
                     "--grid", str(d / "grid.toml"), "--out", str(d / f"vol_{tag}.npz")]) == 0
    capsys.readouterr()
    raws = [str(d / f"raw_{tag}.tif") for tag in "ab"]
    assert main(["piv", str(d / "vol_a.npz"), str(d / "vol_b.npz"), "--dt", "1e-3",
                 "--camera", str(d / "cam.toml"), "--raw", *raws,
                 "--out", str(d / "field.npz")]) == 0
    res, arrays = read_npz(d / "field.npz")
    u = arrays["velocity"][0][res.valid]
    assert np.median(u) == pytest.approx(0.25, rel=0.1)
    out = capsys.readouterr().out
    assert "windows per pass" in out and "focal-zone" not in out and "--raw" not in out
    # without the camera the field comes out, and the missing terms are said
    assert main(["piv", str(d / "vol_a.npz"), str(d / "vol_b.npz"), "--dt", "1e-3",
                 "--out", str(d / "plain.npz")]) == 0
    out = capsys.readouterr().out
    assert "without --camera the depth uncertainty has no focal-zone term" in out
    assert "without --raw the particles are the volumes' peaks" in out
    # raw images need the camera whose rays they are fitted with
    assert main(["piv", str(d / "vol_a.npz"), str(d / "vol_b.npz"), "--dt", "1e-3",
                 "--raw", *raws, "--out", str(d / "no.npz")]) == 2
    assert "--raw needs --camera" in capsys.readouterr().err
    assert not (d / "no.npz").exists()


def test_ctrl_c_exits_130_with_one_line_and_warnings_print_once(tmp_path, capsys,
                                                                monkeypatch, small_camera):
    """Ctrl-C: status 130 and one line; an uncalibrated camera warns once, as one line;
    --iterations 0 runs no iteration."""
    from plenocl import Grid
    from plenocl.io import write_tiff

    small_camera.to_toml(tmp_path / "cam.toml")
    Grid((4, 10, 12), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1, 1)).to_toml(tmp_path / "g.toml")
    raw = np.ones(small_camera.pixels[::-1], np.uint16)
    raw[::7, ::5] = 1000  # a few lit pixels: a blank frame is refused
    write_tiff(tmp_path / "raw.tif", raw)
    args = ["reconstruct", str(tmp_path / "raw.tif"), "--camera", str(tmp_path / "cam.toml"),
            "--grid", str(tmp_path / "g.toml"), "--out", str(tmp_path / "v.npz"),
            "--iterations", "0"]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.err.count("has no [calibration]") == 1
    assert "plenocl reconstruct: warning: " in captured.err and ".py:" not in captured.err
    assert " 0 mlem iterations" in captured.out

    def interrupted(_args):
        raise KeyboardInterrupt

    import importlib

    cli_main = importlib.import_module("plenocl.cli.main")
    parsed = cli_main.build_parser().parse_args(args)
    parsed.func = interrupted
    monkeypatch.setattr(cli_main, "build_parser",
                        lambda: type("P", (), {"parse_args": lambda self, a: parsed})())
    assert main(args) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0]


def _volumes(tmp_path, shape=(8, 10, 12)):
    from plenocl import Grid
    from plenocl.volumefile import save_volume

    grid = Grid(shape, x=(-1.2, 1.2), y=(-1.0, 1.0), z=(-0.8, 0.8))
    vol = np.random.default_rng(1).random(shape).astype(np.float32)
    for name in ("a.npz", "b.npz"):
        save_volume(tmp_path / name, vol, grid)
    for name in ("a.npy", "b.npy"):
        np.save(tmp_path / name, vol)
    grid.to_toml(tmp_path / "grid.toml")
    return grid


@pytest.mark.parametrize("args, message", [
    (["--dt", "175"], r"--dt = 175 s .* 175 µs would be 0.000175.*--force"),
    (["--dt", "0"], r"--dt = 0 s is zero: it must be positive"),
    (["--dt", "1e-9"], r"outside what PIV uses"),
])
def test_piv_refuses_an_implausible_dt_before_any_work(tmp_path, capsys, args, message):
    _volumes(tmp_path)
    rc = main(["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), *args, "--out",
               str(tmp_path / "f.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and re.search(message, err), err
    assert not (tmp_path / "f.npz").exists() and "windows per pass" not in err


def test_piv_grids_conflicts_and_gridless_volumes_are_refused(tmp_path, capsys):
    from plenocl import Grid

    _volumes(tmp_path)
    Grid((8, 10, 12), x=(-2, 2), y=(-1, 1), z=(-0.8, 0.8)).to_toml(tmp_path / "other.toml")
    base = ["--dt", "1e-3", "--no-particles", "--out", str(tmp_path / "f.npz")]
    npz = [str(tmp_path / "a.npz"), str(tmp_path / "b.npz")]
    npy = [str(tmp_path / "a.npy"), str(tmp_path / "b.npy")]
    assert main(["piv", *npz, "--grid", str(tmp_path / "other.toml"), *base]) == 2
    assert "is not the grid the volumes carry" in capsys.readouterr().err
    assert main(["piv", *npy, *base]) == 2
    assert "carry no grid (.npy): give --grid" in capsys.readouterr().err
    Grid((8, 10, 10), x=(-1, 1), y=(-1, 1), z=(-0.8, 0.8)).to_toml(tmp_path / "small.toml")
    assert main(["piv", *npy, "--grid", str(tmp_path / "small.toml"), *base]) == 2
    assert "holds (8, 10, 12) voxels but the grid is (8, 10, 10)" in capsys.readouterr().err
    assert not (tmp_path / "f.npz").exists()
    # the same grid given again is no conflict
    assert main(["piv", *npz, "--grid", str(tmp_path / "grid.toml"), *base]) == 0


def test_simulate_refuses_a_dt_in_the_wrong_units(tmp_path, capsys):
    write_particles(tmp_path / "p.csv", np.array([[0.0, 0.0, 0.0]]), np.array([1e4]))
    out = tmp_path / "raw.tif"
    common = ["simulate", "--particles", str(tmp_path / "p.csv"), "--out", str(out),
              "--velocity", "4.57", "0", "0"]
    assert main([*common, "--dt", "175"]) == 2
    assert "175 µs would be" in capsys.readouterr().err
    assert main([*common, "--dt", "0.5"]) == 2  # a plausible dt, but 2.3 m of travel
    assert "move 2285 mm between the exposures, more than the 6.29 mm field of view" in \
        capsys.readouterr().err
    assert not list(tmp_path.glob("raw*.tif"))
    assert main([*common, "--dt", "0.5", "--force"]) == 0  # the rare real case: forced
    # one flow: --omega beside --velocity dropped the velocity in silence; --dt alone
    # (no flow) was ignored
    with pytest.raises(SystemExit) as stop:
        main([*common, "--omega", "0", "0", "100", "--dt", "175e-6"])
    assert stop.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    assert main([*common[:5], "--dt", "175e-6"]) == 2
    assert "--dt is the time between a displaced pair's exposures" in capsys.readouterr().err


def test_one_meaning_per_option_name(tmp_path, capsys):
    """--supersample means sub-voxels (reconstruct); refocus's output pixels per lens are
    --upsample, and the old spelling there is refused naming it. --background takes the
    API's names (median, none)."""
    from plenocl import Camera

    Camera.synthetic_850().to_toml(tmp_path / "cam.toml")
    np.save(tmp_path / "raw.npy", np.zeros((850, 850), np.float32))
    common = ["refocus", str(tmp_path / "raw.npy"), "--camera", str(tmp_path / "cam.toml"),
              "--z", "0", "--out", str(tmp_path / "s.tif")]
    assert main([*common, "--supersample", "2"]) == 2
    assert "refocus takes --upsample" in capsys.readouterr().err
    far = [*common[:4], "--z", "500", "--out", str(tmp_path / "far.tif")]
    assert main(far) == 2  # beyond the depths the camera resolves: no image of that depth
    assert "lies beyond the depths the camera resolves" in capsys.readouterr().err
    assert not (tmp_path / "far.tif").exists()
    with pytest.raises(SystemExit):
        main(["reconstruct", str(tmp_path / "raw.npy"), "--camera", "synthetic", "--grid",
              "g.toml", "--out", "v.npz", "--background", "auto"])
    assert "choose from median, none" in capsys.readouterr().err.replace("'", "")


def test_grid_command_labels_its_sizes_in_their_order(tmp_path, capsys):
    assert main(["grid", "--camera", "synthetic", "--z", "-2", "2", "--depth-voxel-mm",
                 "0.25", "--out", str(tmp_path / "g.toml")]) == 0
    out, err = capsys.readouterr()
    from plenocl import Grid

    g = Grid.from_toml(tmp_path / "g.toml")
    dz, dy, dx = g.spacing
    assert f"of {dz:.4g} x {dy:.4g} x {dx:.4g} mm (z, y, x)" in out
    assert "warning: " in err and "fewer than 3 layers of vectors in depth" in err
    assert "--depth-voxel-mm" in err
    # -q silences the summary, not the warning (it was printed to stdout, and -q hid it)
    assert main(["-q", "grid", "--camera", "synthetic", "--z", "-2", "2", "--depth-voxel-mm",
                 "0.25", "--out", str(tmp_path / "g.toml")]) == 0
    out, err = capsys.readouterr()
    assert out == "" and "fewer than 3 layers of vectors in depth" in err
    # a depth voxel of 0 is refused as by the API (it silently took the default)
    assert main(["grid", "--camera", "synthetic", "--z", "-2", "2", "--depth-voxel-mm", "0",
                 "--out", str(tmp_path / "g0.toml")]) == 2
    assert "depth_voxel_mm" in capsys.readouterr().err and not (tmp_path / "g0.toml").exists()


def test_quiet_and_verbose(tmp_path, capsys):
    out = ["--camera", "synthetic", "--z", "-2", "2", "--out", str(tmp_path / "g.toml")]
    assert main(["-q", "grid", *out]) == 0
    quiet = capsys.readouterr()
    assert quiet.out == "" and (tmp_path / "g.toml").is_file()
    assert main(["grid", "-v", *out]) == 0
    loud = capsys.readouterr()
    assert "wrote" in loud.out and "OpenCL device" in loud.err
    with pytest.raises(SystemExit):
        main(["-q", "-v", "grid", *out])


def test_reconstruct_takes_a_renders_alpha_as_its_pixel_mask(tmp_path, capsys):
    """An RGBA render whose alpha marks unrendered pixels: --mask alpha leaves them out
    (their zeros would otherwise be read as dark); an image without alpha is refused."""
    import imageio.v3 as iio

    from plenocl import Camera, Grid, random_particles, simulate_image

    cam = Camera.synthetic_850()
    cam.with_centers(cam.ideal_microlens_centers()).to_toml(tmp_path / "cam.toml")
    Grid((8, 20, 20), x=(-1.2, 1.2), y=(-1.2, 1.2), z=(-1.0, 1.0)).to_toml(tmp_path / "g.toml")
    pos, inten = random_particles(((-1, 1), (-1, 1), (-0.8, 0.8)), count=10, seed=3,
                                  intensity=2e4)
    img = simulate_image(cam, pos, inten, 2000, seed=3)
    grey = np.clip(img / img.max() * 255, 0, 255).astype(np.uint8)
    alpha = np.full_like(grey, 255)
    alpha[::3] = 0  # every third row not rendered
    grey[alpha == 0] = 0
    iio.imwrite(tmp_path / "render.png", np.dstack([grey, grey, grey, alpha]))
    common = ["reconstruct", str(tmp_path / "render.png"), "--camera", str(tmp_path / "cam.toml"),
              "--grid", str(tmp_path / "g.toml"), "--iterations", "5", "--supersample", "1"]
    assert main([*common, "--mask", "alpha", "--out", str(tmp_path / "m.npz")]) == 0
    assert main([*common, "--out", str(tmp_path / "n.npz")]) == 0
    from plenocl.volumefile import load_volume

    masked, naive = load_volume(tmp_path / "m.npz")[0], load_volume(tmp_path / "n.npz")[0]
    assert masked.sum() > 1.2 * naive.sum()  # the unrendered rows did not darken it
    iio.imwrite(tmp_path / "grey.png", grey)
    common[1] = str(tmp_path / "grey.png")
    assert main([*common, "--mask", "alpha", "--out", str(tmp_path / "x.npz")]) == 2
    assert "has no alpha channel" in capsys.readouterr().err


def test_reconstructs_progress_bar_counts_the_coarse_and_the_fine_iterations(
        tmp_path, monkeypatch):
    """Coarse-to-fine: the bar's total is coarse + fine, and it sees every iteration."""
    from contextlib import contextmanager

    from plenocl import Camera, Grid, random_particles, simulate_image
    from plenocl.io import progress, write_tiff

    cam = Camera.synthetic_850()
    cam.with_centers(cam.ideal_microlens_centers()).to_toml(tmp_path / "cam.toml")
    Grid((8, 20, 20), x=(-1.2, 1.2), y=(-1.2, 1.2), z=(-1.0, 1.0)).to_toml(tmp_path / "g.toml")
    pos, inten = random_particles(((-1, 1), (-1, 1), (-0.8, 0.8)), count=10, seed=3,
                                  intensity=2e4)
    img = simulate_image(cam, pos, inten, 2000, seed=3, background=20.0)
    write_tiff(tmp_path / "raw.tif", np.clip(img, 0, 65535).astype(np.uint16))
    bars = []

    @contextmanager
    def recording_bar(total, desc, enabled=True):
        bars.append((total, []))
        yield lambda iteration, residual: bars[-1][1].append(iteration)

    monkeypatch.setattr(progress, "iteration_bar", recording_bar)
    assert main(["reconstruct", str(tmp_path / "raw.tif"), "--camera", str(tmp_path / "cam.toml"),
                 "--grid", str(tmp_path / "g.toml"), "--out", str(tmp_path / "v.npz"),
                 "--supersample", "2", "--coarse-iterations", "3", "--iterations", "2"]) == 0
    assert bars == [(5, [1, 2, 3, 4, 5])]


def test_a_complex_volume_or_a_field_for_a_volume_is_one_line_exit_2(tmp_path, capsys):
    """The API refuses a complex array with TypeError and an HDF5 file without a volume
    with KeyError: both reached the command line as tracebacks (exit 1)."""
    import h5py

    from plenocl import Grid

    Grid((8, 8, 8), x=(-1, 1), y=(-1, 1), z=(-1, 1)).to_toml(tmp_path / "g.toml")
    np.save(tmp_path / "c.npy", np.ones((8, 8, 8), np.complex64))
    np.save(tmp_path / "v.npy", np.ones((8, 8, 8), np.float32))
    with h5py.File(tmp_path / "f.h5", "w") as fh:
        fh["velocity"] = np.zeros((3, 2, 2, 2))
    (tmp_path / "x.h5").write_bytes(b"not hdf5")
    common = ["--dt", "175e-6", "--grid", str(tmp_path / "g.toml"), "--out",
              str(tmp_path / "o.npz")]
    for first, message in (("c.npy", "must hold real numbers"),
                           ("f.h5", "f.h5 holds no 'volume' dataset"),
                           ("x.h5", "x.h5 cannot be read as HDF5")):
        assert main(["piv", str(tmp_path / first), str(tmp_path / "v.npy"), *common]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    # a white image of no light: refused (it wrote an all-zero image, exit 0)
    assert main(["white", "--camera", "synthetic", "--intensity", "0", "--out",
                 str(tmp_path / "w.tif")]) == 2
    assert "intensity must be positive" in capsys.readouterr().err
    assert not (tmp_path / "w.tif").exists()
    # a binary file given as a camera file: named (it was a bare 'utf-8' codec error)
    assert main(["grid", "--camera", str(tmp_path / "v.npy"), "--z", "-2", "2", "--out",
                 str(tmp_path / "g2.toml")]) == 2
    assert "v.npy is not a TOML text file" in capsys.readouterr().err


def test_an_output_that_is_an_input_is_refused_before_any_work(tmp_path, capsys):
    """``grid --camera cam.toml --out cam.toml`` replaced the calibrated camera with a
    grid file (exit 0): an output naming one of the command's inputs is refused."""
    from plenocl import Camera

    Camera.synthetic_850().to_toml(tmp_path / "cam.toml")
    before = (tmp_path / "cam.toml").read_bytes()
    assert main(["grid", "--camera", str(tmp_path / "cam.toml"), "--z", "-2", "2",
                 "--out", str(tmp_path / "cam.toml")]) == 2
    assert "--out" in capsys.readouterr().err
    assert (tmp_path / "cam.toml").read_bytes() == before


def test_piv_names_the_volume_file_it_refuses_or_warns_of(tmp_path, capsys):
    """``plenocl piv``'s messages about a volume name its file (they said ``vol_a``)."""
    _volumes(tmp_path)
    vol = np.load(tmp_path / "a.npy")
    bad = vol.copy()
    bad[1, 2, 3] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    np.save(tmp_path / "lifted.npy", vol + 10 * vol.max())  # a constant background
    base = ["--dt", "1e-3", "--no-particles", "--grid", str(tmp_path / "grid.toml"),
            "--out", str(tmp_path / "f.npz")]
    assert main(["piv", str(tmp_path / "a.npy"), str(tmp_path / "nan.npy"), *base]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'nan.npy'} contains 1 NaN/Inf values" in err and "vol_b" not in err
    assert not (tmp_path / "f.npz").exists()
    assert main(["piv", str(tmp_path / "lifted.npy"), str(tmp_path / "a.npy"), *base]) == 0
    err = capsys.readouterr().err
    assert f"{tmp_path / 'lifted.npy'}'s darkest voxel" in err and "vol_a" not in err


@pytest.mark.parametrize("flow", [[], ["--velocity", "1", "0", "0", "--dt", "1e-4"]])
def test_simulate_does_not_write_over_its_particles(tmp_path, capsys, flow):
    """The truth file is named after --out (OUT_particles.csv, OUT_a_particles.csv for a
    pair): a particles file of that name was replaced by the displaced positions, exit 0,
    and drifted at every rerun."""
    name = "raw_a_particles.csv" if flow else "raw_particles.csv"
    write_particles(tmp_path / name, np.array([[0.05, 0.0, 0.3]]), np.array([2e4]))
    before = (tmp_path / name).read_bytes()
    assert main(["simulate", "--particles", str(tmp_path / name), "--out",
                 str(tmp_path / "raw.tif"), *flow]) == 2
    assert "which this command writes, is also the command's input (particles)" in \
        capsys.readouterr().err
    assert (tmp_path / name).read_bytes() == before and not list(tmp_path.glob("*.tif"))


def test_particle_columns_are_read_by_their_names(tmp_path):
    """A particle file's columns in another order are read by their header's names (they
    were read by position: z, y, x taken as x, y, z, in silence); NumPy's '# ' header and
    names without the unit are the same columns."""
    want = np.array([[0.05, -0.1, 0.3]])
    for header, row in (("z_mm,y_mm,x_mm,intensity", "0.3,-0.1,0.05,7"),
                        ("# intensity,x,y,z", "7,0.05,-0.1,0.3"),
                        ("x [mm], y [mm], z [mm], intensity", "0.05,-0.1,0.3,7")):
        (tmp_path / "p.csv").write_text(f"{header}\n{row}\n")
        positions, intensities = read_particles(tmp_path / "p.csv")
        np.testing.assert_array_equal(positions, want)
        assert intensities.tolist() == [7.0], header
