"""Bad inputs named early and once (issue 44, part 2): blank and saturated frames refused
by name, an empty volume an error, a dark frame's noise below zero clipped and measured,
a particle image refused by calibrate, negative numbers on the command line, the device
fallback said once (never under -q), and no misleading notes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import lens_camera

from plenocl import (
    Camera,
    Grid,
    Projector,
    calibrate,
    reconstruct,
    simulate_image,
    simulate_white_image,
)
from plenocl.cli.main import main
from plenocl.io import write_tiff
from plenocl.optics.rawimage import dark_noise, median_and_noise
from plenocl.reconstruction import (
    NOISE_SIGMAS,
    ReconstructionSettings,
    UnusableImageError,
    preprocess,
)
from plenocl.simulate.sensor import correct_frame
from plenocl.volumefile import load_volume

SMALL_GRID = Grid((6, 20, 24), x=(-0.72, 0.72), y=(-0.6, 0.6), z=(-0.5, 0.5))


def _frames(tmp_path, camera):
    """The camera, a grid, a blank, a saturated and a sparse frame, written as TIFFs."""
    camera.to_toml(tmp_path / "cam.toml")
    SMALL_GRID.to_toml(tmp_path / "grid.toml")
    shape = camera.pixels[::-1]
    sparse = np.full(shape, 10, np.uint16)
    sparse[::7, ::5] = 1000
    bright = sparse.copy()
    bright.ravel()[: 2 * bright.size // 3] = 4095
    for name, img in (("blank.tif", np.zeros(shape, np.uint16)), ("bright.tif", bright),
                      ("sparse.tif", sparse)):
        write_tiff(tmp_path / name, img)


@pytest.mark.parametrize("name, message", [
    ("blank.tif", "blank.tif is blank: every pixel is 0"),
    ("bright.tif", "bright.tif is saturated: 67% of its pixels are at its brightest value"),
])
def test_blank_and_saturated_frames_are_refused_naming_the_file(tmp_path, capsys,
                                                                 small_camera, name, message):
    _frames(tmp_path, small_camera)
    out = tmp_path / "v.npz"
    rc = main(["reconstruct", str(tmp_path / name), "--camera", str(tmp_path / "cam.toml"),
               "--grid", str(tmp_path / "grid.toml"), "--out", str(out)])
    assert rc == 2 and message in capsys.readouterr().err and not out.exists()


def test_a_blank_white_image_is_named_and_a_saturated_one_is_not_refused(tmp_path, capsys,
                                                                         small_camera):
    """calibrate names a blank file; a white image's spots may all be saturated, so its
    saturation is not refused there (it fails later, if at all, for its own reasons)."""
    _frames(tmp_path, small_camera)
    base = ["--camera", str(tmp_path / "cam.toml"), "--out", str(tmp_path / "c.toml")]
    assert main(["calibrate", str(tmp_path / "blank.tif"), *base]) == 2
    assert "blank.tif is blank" in capsys.readouterr().err
    main(["calibrate", str(tmp_path / "bright.tif"), *base])
    assert "is saturated" not in capsys.readouterr().err


def _dense_case(camera, seed: int = 0):
    """A dense raw image (3000 particles: most pixels lit, as a real scene's) on a dark
    level with fixed-pattern noise, its dark frame (the pattern with its own read noise),
    and the clean image."""
    rng = np.random.default_rng(seed)
    n = 3000
    pos = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.5, 0.5, n),
                           rng.uniform(-0.45, 0.45, n)])
    clean = simulate_image(camera, pos, 2e4, 3000, seed=1, blur_px=0.5).astype(np.float64)
    pattern = 100 + rng.normal(0, 5, clean.shape)
    raw = np.rint(clean + pattern + rng.normal(0, 3, clean.shape))
    dark = np.rint(pattern + rng.normal(0, 3, clean.shape))
    return raw, dark, clean


@pytest.fixture(scope="module")
def dense(queue):
    camera = lens_camera(12, 10)
    return camera, Projector(camera, SMALL_GRID, queue), *_dense_case(camera)


def test_the_noise_below_zero_is_the_noise_of_a_dark_subtracted_image():
    """Noise about a subtracted dark level, under a scene lighting two thirds of the
    pixels: the pixels below zero give the noise (the MAD of the whole image gives the
    scene's spread); the zeros of integer counts are counted as noise too."""
    rng = np.random.default_rng(4)
    scene = np.where(rng.random((300, 300)) < 2 / 3, rng.uniform(50, 500, (300, 300)), 0.0)
    image = scene + rng.normal(0, 3.0, scene.shape)
    assert dark_noise(image) == pytest.approx(3.0, rel=0.05)
    assert median_and_noise(image)[1] > 20 * 3.0
    assert dark_noise(np.rint(image)) == pytest.approx(3.0, rel=0.1)
    assert dark_noise(np.abs(image)) == 0.0  # nothing below zero: no estimate


def test_a_dark_subtracted_image_is_clipped_and_thresholded_at_its_noise(dense):
    """Either background: the pixels below zero are clipped (not refused), the threshold
    is NOISE_SIGMAS times the noise measured after the subtraction (the true one is 3√2,
    rounded counts)."""
    camera, _, raw, dark, _ = dense
    sub = correct_frame(raw, dark)
    assert sub.min() < 0
    for background in ("median", None):
        img, scale, threshold = preprocess(sub, camera, background)
        assert img.min() == 0 and img.max() == 1 and scale == sub.max()
        assert threshold * scale == pytest.approx(NOISE_SIGMAS * 3 * 2 ** 0.5, rel=0.1)


def test_a_dense_image_with_its_dark_frame_reconstructs_by_default(dense):
    """The real camera's case (a dense image, its dark frame): the old default threshold,
    4 x the MAD about the median, lies above the brightest pixel and every pixel would be
    dark, which is now an error naming the fix; with the dark frame subtracted the
    default reconstructs what the clean image gives."""
    camera, proj, raw, dark, clean = dense
    sub = correct_frame(raw, dark)
    _, mad = median_and_noise(sub)
    assert NOISE_SIGMAS * mad > sub.max()  # the old default: everything dark
    with pytest.raises(UnusableImageError, match="every pixel counts as dark.*--dark"):
        reconstruct(raw, proj, iterations=4, supersample=1)
    vol = reconstruct(sub, proj, iterations=4, supersample=1)
    ref = reconstruct(clean, proj, iterations=4, supersample=1, background=None)
    assert vol.max() > 0 and np.corrcoef(vol.ravel(), ref.ravel())[0, 1] > 0.99


def test_the_command_line_reconstructs_a_dense_image_with_its_dark_frame(tmp_path, capsys,
                                                                          dense):
    """--dark: the default works, and so does --background none (its negative pixels,
    made by the subtraction, clipped); without the dark frame the command fails, exit 2,
    and writes nothing."""
    camera, _, raw, dark, _ = dense
    camera.to_toml(tmp_path / "cam.toml")
    SMALL_GRID.to_toml(tmp_path / "grid.toml")
    write_tiff(tmp_path / "raw.tif", raw.astype(np.uint16))
    write_tiff(tmp_path / "dark.tif", dark.astype(np.uint16))
    base = [str(tmp_path / "raw.tif"), "--camera", str(tmp_path / "cam.toml"), "--grid",
            str(tmp_path / "grid.toml"), "--iterations", "2", "--supersample", "1"]
    for extra in ([], ["--background", "none"]):
        out = tmp_path / f"v{len(extra)}.npz"
        assert main(["reconstruct", *base, "--dark", str(tmp_path / "dark.tif"), *extra,
                     "--out", str(out)]) == 0
        assert load_volume(out)[0].max() > 0
    assert "negative pixels" not in capsys.readouterr().err
    assert main(["reconstruct", *base, "--out", str(tmp_path / "empty.npz")]) == 2
    assert "volume would be empty" in capsys.readouterr().err
    assert not (tmp_path / "empty.npz").exists()


def test_a_pair_with_a_blank_exposure_names_that_image(dense):
    """process_pair says which exposure cannot give a volume (``which``)."""
    from plenocl.pipeline import process_pair

    _, proj, raw, dark, _ = dense
    with pytest.raises(UnusableImageError, match="raw_b: the image is blank") as err:
        process_pair(correct_frame(raw, dark), np.zeros_like(raw), proj,
                     reconstruction=ReconstructionSettings(iterations=1, supersample=1))
    assert err.value.which == "b"


def test_the_batch_records_each_failed_pair_with_the_files_name(tmp_path, small_camera):
    """A blank or saturated frame fails its pair before any reconstruction, named; an
    exposure the reconstruction refuses (all dark after the dark frame) names its own
    file; no pair processed: no seconds per pair."""
    from plenocl.batch.layout import pair_file
    from plenocl.batch.run import run
    from plenocl.batch.worker import PairProcessor, PairTask, RunSettings
    from plenocl.pipeline import PairSettings

    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    _frames(raw_dir, small_camera)
    # eight voxels deep: a grid the default windows fit (a batch checks them first)
    Grid((8, 20, 24), x=SMALL_GRID.x, y=SMALL_GRID.y, z=SMALL_GRID.z).to_toml(
        raw_dir / "grid.toml")
    for k, name in enumerate(("blank.tif", "sparse.tif", "sparse.tif", "bright.tif")):
        (raw_dir / f"frame_{k:03d}.tif").write_bytes((raw_dir / name).read_bytes())
    (tmp_path / "experiment.toml").write_text(
        f'[camera]\nfile = "{raw_dir / "cam.toml"}"\n[grid]\nfile = "{raw_dir / "grid.toml"}"'
        '\n[images]\nfolder = "raw"\npattern = "frame_*.tif"\npairing = "sequence"\n'
        'dt_s = 1e-3\n[output]\nfolder = "results"\n')
    lines = []
    summary = run(tmp_path / "experiment.toml", log=lines.append)
    assert summary.processed == [] and sorted(summary.failed) == [0, 1]
    assert "frame_000.tif is blank" in summary.failed[0]
    assert "frame_003.tif is saturated" in summary.failed[1]
    assert "0 pair(s) processed, " in lines[-1] and "s each" not in lines[-1]

    settings = RunSettings(PairSettings(ReconstructionSettings(iterations=1, supersample=1)),
                           1e-3, dark=str(raw_dir / "sparse.tif"))
    worker = PairProcessor(tmp_path / "results", settings)
    write_tiff(raw_dir / "brighter.tif", np.asarray(worker.dark * 2, np.uint16))
    outcome = worker(PairTask(0, str(raw_dir / "brighter.tif"), str(raw_dir / "sparse.tif"),
                              str(pair_file(tmp_path / "results", 0))))
    assert outcome.error.startswith("sparse.tif: raw_b: the image is blank"), outcome.error


def test_a_particle_image_given_to_calibrate_is_not_a_white_image(tmp_path, capsys, queue):
    """A particle image of the synthetic camera (the demo's) is refused as not a white
    image, not blamed on the spot spacing or the camera file."""
    cam = Camera.synthetic_850()
    rng = np.random.default_rng(2)
    pos = rng.uniform(-2.5, 2.5, (200, 3))
    image = simulate_image(cam, pos, 3e4, 4000, seed=2, blur_px=0.5, background=20.0,
                           read_noise=3.0, bit_depth=16, queue=queue)
    with pytest.raises(ValueError, match="does not look like a white image: .* irregularly "
                                         "spaced .* a particle image"):
        calibrate(image, cam)
    write_tiff(tmp_path / "raw_a.tif", image)
    assert main(["calibrate", str(tmp_path / "raw_a.tif"), "--camera", "synthetic", "--out",
                 str(tmp_path / "c.toml")]) == 2
    err = capsys.readouterr().err
    assert "not look like a white image" in err and "camera file" not in err
    assert "apart but the camera predicts" not in err


def test_a_negative_number_in_exponent_form_reaches_its_check(tmp_path, capsys):
    """--dt -175e-6 is read as a number (argparse took it for an option) and refused
    by the value check naming its sign; negative depths parse in any form."""
    rc = main(["piv", "a.npz", "b.npz", "--dt", "-175e-6", "--out", str(tmp_path / "f.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "expected one argument" not in err
    assert "--dt = -0.000175 s is negative: it must be positive" in err
    assert main(["grid", "--camera", "synthetic", "--z", "-2.5e0", "-1E-1", "--out",
                 str(tmp_path / "g.toml")]) == 0
    assert Grid.from_toml(tmp_path / "g.toml").z == (-2.5, -0.1)


def _fake_fallback(monkeypatch):
    """The default device choice passes over a GPU that cannot build (not the expected
    fallback), three times; the ``grid`` command runs it."""
    from plenocl.cli import simulate
    from plenocl.opencl import device

    class Platform:
        def __init__(self, name: str) -> None:
            self.name = name

    class Dev:
        def __init__(self, name: str, kind: int, platform: str) -> None:
            self.name, self.type, self.platform = name, kind, Platform(platform)

    import pyopencl as cl

    gpu = Dev("broken-gpu", cl.device_type.GPU, "Some GPU")
    cpu = Dev("cpu", cl.device_type.CPU, device.CPU_PLATFORMS[0])
    monkeypatch.setattr(device, "all_devices", lambda: [cpu, gpu])
    monkeypatch.setattr(device, "build_problem",
                        lambda d: "no compiler" if d is gpu else None)
    monkeypatch.setattr(device, "_SAID", set())
    monkeypatch.setattr(device, "_FALLBACK", {"note": None})
    monkeypatch.setattr(simulate, "cmd_grid",
                        lambda args: [device._default_device() for _ in range(3)] and 0)


def test_the_device_fallback_is_said_once_and_not_under_quiet(monkeypatch, capsys):
    from plenocl.opencl import device

    _fake_fallback(monkeypatch)
    args = ["grid", "--camera", "synthetic", "--z", "-1", "1", "--out", "unused.toml"]
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # a script's own filter: still said once
        assert main(args) == 0 and main(args) == 0
    err = capsys.readouterr().err
    assert err.count("plenocl uses cpu") == 1 and "broken-gpu" in err
    monkeypatch.setattr(device, "_SAID", set())  # a new process
    assert main(["-q", *args]) == 0
    assert "plenocl uses" not in capsys.readouterr().err


def test_the_grid_commands_default_depth_voxel_gives_three_layers(tmp_path, capsys):
    """The default depth voxel for --z -3 3 no longer triggers the command's own
    'too shallow' note: it is made thinner where half the depth resolution would leave
    fewer than THREE_LAYERS voxels, and stays that where the range is deep enough."""
    from plenocl.cli.simulate import THREE_LAYERS

    cam = Camera.synthetic_850()
    assert main(["grid", "--camera", "synthetic", "--z", "-3", "3", "--out",
                 str(tmp_path / "g.toml")]) == 0
    assert "note:" not in capsys.readouterr().out
    assert Grid.from_toml(tmp_path / "g.toml").shape[0] == THREE_LAYERS
    deep = (THREE_LAYERS + 12) * cam.depth_resolution_mm / 2
    assert main(["grid", "--camera", "synthetic", "--z", "0", str(deep), "--out",
                 str(tmp_path / "d.toml")]) == 0
    dz = Grid.from_toml(tmp_path / "d.toml").spacing[0]
    assert dz == pytest.approx(cam.depth_resolution_mm / 2)


def test_piv_prints_no_peak_ratio_note(tmp_path, capsys):
    """A normal piv run ends with the field written, no note about NaN peak ratios."""
    from plenocl.volumefile import save_volume

    grid = Grid((32, 32, 32), x=(-1, 1), y=(-1, 1), z=(-1, 1))
    rng = np.random.default_rng(1)
    vol = np.zeros(grid.shape, np.float32)
    vol[tuple(rng.integers(2, 30, (3, 400)))] = 1.0
    save_volume(tmp_path / "a.npz", vol, grid)
    save_volume(tmp_path / "b.npz", np.roll(vol, 1, axis=2), grid)
    assert main(["piv", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--dt", "1e-3",
                 "--no-particles", "--out", str(tmp_path / "f.npz")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "NaN" not in out  # (the folder is named for the test)


@pytest.mark.parametrize("n", [1 << 16, (1 << 16) + 1, 300_001, 1_000_000])
def test_exact_median_is_numpys(n):
    """The bracketed median, and median absolute deviation, equal NumPy's exactly: odd and
    even counts, float noise, heavy ties, a bright tail, NaN (NumPy's NaN) and an order
    that defeats the strided sample (the bracket misses: NumPy's median of the whole)."""
    from plenocl.optics.rawimage import BRACKET_SAMPLE, exact_median

    rng = np.random.default_rng(n)
    noisy = rng.poisson(20, n) + rng.normal(0, 1, n)
    noisy[rng.random(n) < 0.03] += 3000
    ties = rng.poisson(3, n).astype(np.float64)
    stride = n // BRACKET_SAMPLE
    fooled = np.ones(n)
    fooled[::stride] = 0.0  # every sampled value 0, the median 1
    fooled[1::2] = 2.0
    with_nan = noisy.copy()
    with_nan[n // 3] = np.nan
    for data in (noisy, ties, fooled, -noisy, noisy.reshape(-1, 2) if n % 2 == 0 else noisy):
        assert exact_median(data) == float(np.median(data))
        centre = float(np.median(data))  # the median absolute deviation, and off-centre
        for c in (centre, centre + 0.37):
            assert exact_median(data, centre=c) == float(np.median(np.abs(data - c)))
    assert np.isnan(exact_median(with_nan)) and np.isnan(exact_median(with_nan, 1.0))


@pytest.mark.parametrize("options, message", [
    ({"voxel_mm": 0}, r"voxel_mm must be a positive size in mm, or None for the default"),
    ({"depth_voxel_mm": -0.1}, r"depth_voxel_mm must be a positive size in mm"),
    ({"voxel_mm": float("nan")}, r"voxel_mm must be a positive size in mm"),
    ({"fraction": 0}, r"fraction is the share of the field of view.*got 0"),
    ({"fraction": 1.5}, r"0 < fraction <= 1, got 1.5"),
    ({"voxel_mm": 100.0}, r"voxel_mm = 100 mm is larger than the field of view covered.*"
                          "millimetres"),
    ({"depth_voxel_mm": 5.0}, r"depth_voxel_mm = 5 mm is larger than the depth range"),
    ({"voxel_mm": 1e-5}, r"more than any device holds.*in millimetres"),
    ({"z": (float("nan"), 0.5)}, r"grid extent z must be two finite numbers \(lo, hi\) "
                                 r"with lo < hi in mm, got \(nan, 0.5\)"),
    ({"z": (0.5, -0.5)}, r"grid extent z must be two finite numbers .* got \(0.5, -0.5\)"),
])
def test_a_grid_of_impossible_sizes_is_refused_naming_the_option(options, message):
    """``Grid.for_camera`` (``plenocl grid``, a batch's ``[grid]``): a zero or negative
    voxel is not the default, a voxel larger than what it divides is a unit mistake, and a
    grid no device holds is refused before it is made."""
    camera = lens_camera(12, 10)
    with pytest.raises(ValueError, match=message):
        Grid.for_camera(camera, **{"z": (-0.5, 0.5), **options})


def test_a_grid_of_default_sizes_and_numbers_of_any_kind_is_made():
    """The defaults are not held to the span they divide (a range thinner than the
    default depth voxel is one layer, as before); a NumPy 0-d array or a fraction is a
    size; a boolean fraction is not."""
    from fractions import Fraction

    camera = lens_camera(12, 10)
    assert Grid.for_camera(camera, (-0.1, 0.1)).shape[0] == 1
    assert Grid.for_camera(camera, (-0.5, 0.5), voxel_mm=np.array(0.125)) == \
        Grid.for_camera(camera, (-0.5, 0.5), voxel_mm=Fraction(1, 8))
    with pytest.raises(ValueError, match="0 < fraction <= 1, got True"):
        Grid.for_camera(camera, (-0.5, 0.5), fraction=True)


@pytest.mark.parametrize("text, message", [
    ("rotaton_deg = 10", r"unknown key\(s\) \['rotaton_deg'\] in \[grid\]; it takes"),
    ("", None),
])
def test_a_grid_file_names_unknown_keys_and_wrong_values(tmp_path, text, message):
    good = SMALL_GRID.to_dict()["grid"]
    lines = [f"{k} = {v!r}".replace("(", "[").replace(")", "]") for k, v in good.items()]
    path = tmp_path / "g.toml"
    path.write_text("[grid]\n" + "\n".join(lines + [text]) + "\n")
    if message is None:
        assert Grid.from_toml(path) == SMALL_GRID
        path.write_text(path.read_text().replace("x_mm = [-0.72, 0.72]", "x_mm = 0.72"))
        message = r"\[grid\] x_mm must be a list of 2 numbers \(\[low, high\] mm\), got 0.72"
    with pytest.raises(ValueError, match=message):
        Grid.from_toml(path)


def test_a_damaged_npz_is_named_with_the_fix(tmp_path, capsys):
    """A truncated or foreign ``.npz``/``.npy`` (a copy cut short, a file of another
    tool): the file, what it should hold and the fix, from the API and the command line
    (exit status 2, no traceback); a missing array names what the file holds."""
    from plenocl.io.fieldformat import read_field

    whole = tmp_path / "v.npz"
    np.savez(whole, volume=np.ones((8, 8, 8), np.float32))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(whole.read_bytes()[:100])
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not numpy")
    for path, read in ((cut, load_volume), (junk, load_volume), (cut, read_field)):
        with pytest.raises(ValueError, match=rf"{path.name} cannot be read as .*truncated, "
                                             "damaged or not one plenocl wrote"):
            read(path)
    other = tmp_path / "other.npz"
    np.savez(other, vol=np.ones(3))
    with pytest.raises(ValueError, match=r"is not a volume .*it holds \['vol'\]"):
        load_volume(other)
    objects, renamed = tmp_path / "objects.npz", tmp_path / "renamed.npz"
    np.savez(objects, volume=np.array([None, 1], dtype=object))
    np.save(tmp_path / "one.npy", np.ones(3))
    (tmp_path / "one.npy").rename(renamed)
    for path in (objects, renamed):
        with pytest.raises(ValueError, match=rf"{path.name} cannot be read as a volume"):
            load_volume(path)
    assert main(["piv", str(cut), str(cut), "--dt", "1e-3", "--out",
                 str(tmp_path / "f.npz")]) == 2
    err = capsys.readouterr().err
    assert "cut.npz cannot be read as a volume" in err and "Traceback" not in err


def test_a_start_volume_that_cannot_grow_is_refused():
    """Every method multiplies its voxels, so a start of zeros returns zeros: refused with
    the fix, as a complex start is (it was cast, its imaginary part dropped)."""
    camera = lens_camera(12, 10)
    projector = Projector(camera, SMALL_GRID)
    image = simulate_image(camera, np.array([[0.0, 0.0, 0.1]]), 2e4, 2000, seed=1,
                           background=20.0)
    for start, message in ((np.zeros(SMALL_GRID.shape), r"no positive voxel.*start='uniform'"),
                           (np.ones(SMALL_GRID.shape) * 1j, r"must hold real numbers, got "
                                                            r"complex128")):
        for supersample in (1, 3):
            with pytest.raises(ValueError, match=message):
                reconstruct(image, projector, start=start, supersample=supersample)


def test_a_field_saved_with_another_grid_is_refused(tmp_path):
    """``save_field(grid=)`` places and scales the vectors by the grid: one that does not
    hold the field's windows (another grid than the volumes') is refused, naming both."""
    from plenocl import piv3d, save_field

    rng = np.random.default_rng(0)
    vol = np.zeros((32, 32, 32), np.float32)
    vol[tuple(rng.integers(2, 30, (3, 300)))] = 1.0
    result = piv3d(vol, np.roll(vol, 1, axis=2), windows=(16,), queue=False)
    for n in (16, 24):  # centres on the grid, windows beyond it: another grid too
        small = Grid((n, n, n), x=(-1, 1), y=(-1, 1), z=(-1, 1))
        with pytest.raises(ValueError, match=rf"windows of 16 voxels lie at voxels .* to "
                                             rf"23.5 along z, but the grid has {n} voxels"):
            save_field(tmp_path / "f.npz", result, grid=small, dt=1e-3)
    assert not (tmp_path / "f.npz").exists()
    right = Grid((32, 32, 32), x=(-1, 1), y=(-1, 1), z=(-1, 1))
    assert save_field(tmp_path / "f.npz", result, grid=right, dt=1e-3).is_file()


def test_a_projector_of_file_names_says_how_to_read_them():
    with pytest.raises(TypeError, match=r"takes a plenocl.Camera and a plenocl.Grid, got str "
                                        r"and Grid: read files with plenocl.Camera.from_toml"):
        Projector("camera.toml", SMALL_GRID)


def test_piv_refuses_negative_volumes_and_warns_of_a_background():
    """A volume of another tool with its sign flipped is refused (its vectors were
    garbage); one whose constant background exceeds its particles warns (the vectors were
    pulled towards zero); a reconstruction's ringing below zero passes."""
    from plenocl import piv3d

    rng = np.random.default_rng(0)
    vol = np.zeros((32, 32, 32), np.float32)
    vol[tuple(rng.integers(2, 30, (3, 300)))] = 1.0
    moved = np.roll(vol, 1, axis=2)
    with pytest.raises(ValueError, match=r"vol_b holds negative intensities down to -1 "
                                         r"against a peak of -?0"):
        piv3d(vol, -moved, windows=(16,), queue=False)
    with pytest.warns(UserWarning, match=r"vol_a's darkest voxel \(10\) lies above its "
                                         r"particles' height"):
        piv3d(vol + 10, moved + 10, windows=(16,), queue=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        piv3d(vol - 0.05, moved, windows=(16,), queue=False)


def test_a_partly_dark_white_image_is_not_only_blamed_on_the_lens_count():
    """Half the array dark (occluded, outside the illumination), or one edge column of
    lenses, shows fewer lenses than the camera file has: the message names the lit span
    beside the count."""
    camera = lens_camera(12, 10)
    white = simulate_white_image(camera, rays_per_lens=400, seed=0)
    half = np.where(np.arange(white.shape[1])[None, :] < white.shape[1] // 2, white, 0)
    with pytest.raises(ValueError, match=r"shows about 6 x 10 microlens images .* or, if the "
                                         r"count is right, part of the array is dark: the lit "
                                         r"lenses span x \d+-\d+ of 204 px"):
        calibrate(half, camera)
    one = np.where(np.arange(white.shape[1])[None, :] < white.shape[1] // 12, 0, white)
    with pytest.raises(ValueError, match=r"shows about 11 x 10 microlens images .* or, if "
                                         r"the count is right, part of the array is dark"):
        calibrate(one, camera)


def test_velocities_from_the_default_voxel_warn(tmp_path):
    """``save_field(dt=)`` without the grid or the voxel size writes m/s from 1 mm voxels
    (one voxel in 1 ms is 1 m/s): said; given either, not."""
    from plenocl import PIVResult, read_npz, save_field

    x = y = z = np.array([8.0, 16.0])
    ones, none = np.ones((2, 2, 2)), np.zeros((2, 2, 2), bool)
    result = PIVResult(x, y, z, ones, 0 * ones, 0 * ones, ~none, ones, none, none, (16,) * 3)
    with pytest.warns(UserWarning, match=r"neither grid= nor voxel_size_mm=.*1 mm voxels"):
        path = save_field(tmp_path / "f.npz", result, dt=1e-3)
    assert read_npz(path)[1]["velocity"][0].max() == pytest.approx(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        path = save_field(tmp_path / "g.npz", result, voxel_size_mm=0.125, dt=1e-3)
    assert read_npz(path)[1]["velocity"][0].max() == pytest.approx(0.125)
