"""An experiment of several cameras (``[[cameras]]``, docs/batch.md; docs/design.md
§6.7): every camera's folder paired by the same rule, pairs matched by frame number, one
joint reconstruction per exposure, resumable like one camera's run."""

from __future__ import annotations

import json

import numpy as np
import pytest

import plenocl
from plenocl import Camera, random_particles, simulate_image, simulate_white_image
from plenocl.batch import load_experiment
from plenocl.camera import Pose
from plenocl.io import write_tiff
from plenocl.io.tomlfile import read_toml
from plenocl.vectorfield import read_npz

EXPERIMENT = """
[[cameras]]
file = "cam1.toml"
folder = "raw1"
[[cameras]]
file = "cam2.toml"
white = "white_2.tif"
folder = "raw2"
[grid]
z_mm = [-2.0, 2.0]
fraction = 0.6
[images]
pattern = "frame_*.tif"
pairing = "sequence"
dt_s = 1e-3
[reconstruction]
iterations = 7
[output]
folder = "results"
"""

#: The second camera's turn about y (degrees): the first stands in the world frame.
TURN = 20.0


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory):
    """Three pairs moved 0.25 mm along x (0.25 m/s over 1 ms) seen by two cameras
    ``TURN`` degrees apart, the second camera's frame 3 missing; the second camera's
    white image, to calibrate it from (on the default device, as the run itself: the
    batch is tested once, not per device)."""
    d = tmp_path_factory.mktemp("cams")
    cams = [Camera.synthetic_850(),
            Camera.synthetic_850().with_pose(Pose((0.0, TURN, 0.0), (0.0, 0.0, 0.0)))]
    pos, inten = random_particles(((-1.4, 1.4), (-1.4, 1.4), (-1.8, 1.8)), count=300,
                                  seed=5, intensity=3e4)
    shift = np.array([0.25, 0.0, 0.0])
    for c, cam in enumerate(cams, start=1):
        cam.to_toml(d / f"cam{c}.toml")
        (d / f"raw{c}").mkdir()
        for k in range(3):
            for j, sign in enumerate((-0.5, 0.5)):
                img = simulate_image(cam, pos + sign * shift, inten, 3000,
                                     seed=100 * c + 10 * k + j, read_noise=2.0,
                                     bit_depth=16)
                write_tiff(d / f"raw{c}" / f"frame_{2 * k + j:03d}.tif", img)
    (d / "raw2" / "frame_003.tif").unlink()
    write_tiff(d / "white_2.tif", simulate_white_image(cams[1], seed=3, bit_depth=16))
    (d / "experiment.toml").write_text(EXPERIMENT)
    return d


@pytest.fixture(scope="module")
def first_run(two_cameras):
    """The experiment run once (its summary and log), for every test that reads its
    results: none depends on another test having run it first (pytest-xdist may run
    them in different processes)."""
    said = []
    return plenocl.run(two_cameras / "experiment.toml", log=said.append,
                       progress=False), said


def test_two_cameras_run_matches_frames_by_number_and_resumes(two_cameras, first_run):
    """Pairs 0 and 2 are made from both cameras' frames of the same numbers, pair 1
    (camera 2's frame 3 missing) is a gap naming the camera and the frame; the second
    camera is calibrated from its white image and keeps its pose; the fields measure the
    motion, record every camera's source files, and a rerun skips them."""
    s, said = first_run
    assert s.processed == [0, 2] and not s.failed and list(s.gaps) == [1]
    assert "camera 2" in s.gaps[1] and "frame_003.tif missing" in s.gaps[1]
    assert any(m.startswith("pair 1: not made") and "camera 2" in m for m in said)
    out = two_cameras / "results"
    for k in (0, 2):
        res, arrays = read_npz(out / "pairs" / f"pair_{k:05d}.npz")
        assert res.valid.mean() > 0.8
        assert np.median(arrays["velocity"][0][res.valid]) == pytest.approx(0.25, rel=0.1)
        src = s.sources[k]
        names = [(f["a"]["name"], f["b"]["name"]) for f in [src, *src["cameras"]]]
        assert names == [(f"frame_{2 * k:03d}.tif", f"frame_{2 * k + 1:03d}.tif")] * 2
    second = read_toml(out / "camera_2_used.toml")  # calibrated, its pose kept
    assert second["pose"]["rotation_deg"] == pytest.approx([0.0, TURN, 0.0])
    assert "calibration" in second
    assert (out / "camera_1_used.toml").is_file() and not (out / "camera_used.toml").exists()
    used = read_toml(out / "experiment_used.toml")
    assert [c["folder"] for c in used["cameras"]] == ["raw1", "raw2"]
    again = plenocl.run(two_cameras / "experiment.toml", progress=False, log=lambda m: None)
    assert again.skipped == [0, 2] and again.processed == []
    saved = json.loads((out / "summary.json").read_text())
    assert "camera 2" in saved["gaps"]["1"]


def test_a_changed_frame_of_the_second_camera_refuses_the_rerun(two_cameras, first_run,
                                                                tmp_path):
    """Camera 2's image of a finished pair replaced: the rerun names that camera's file
    and refuses, before anything is changed."""
    import shutil

    for name in ("cam1.toml", "cam2.toml", "white_2.tif", "experiment.toml"):
        shutil.copy(two_cameras / name, tmp_path / name)
    for folder in ("raw1", "raw2", "results"):
        shutil.copytree(two_cameras / folder, tmp_path / folder)
    shutil.copy(tmp_path / "raw2" / "frame_004.tif", tmp_path / "raw2" / "frame_000.tif")
    with pytest.raises(ValueError, match="camera 2: it was made from"):
        plenocl.run(tmp_path / "experiment.toml", progress=False, log=lambda m: None)


def test_several_cameras_are_refused_for_tracking_and_beside_an_images_folder(tmp_path):
    (tmp_path / "e.toml").write_text(EXPERIMENT.replace("[images]", "[images]\nfolder = 'x'"))
    with pytest.raises(ValueError, match=r"\[images\] folder with \[\[cameras\]\]"):
        load_experiment(tmp_path / "e.toml")
    (tmp_path / "e.toml").write_text(EXPERIMENT + "[tracking]\nenabled = true\n")
    with pytest.raises(ValueError, match=r"plenocl.track\(\[frames_1"):
        load_experiment(tmp_path / "e.toml")


def test_two_cameras_at_one_pose_are_refused_before_any_frame(two_cameras, tmp_path):
    """Both [[cameras]] naming one camera file (or two files without [pose]) would
    reconstruct one view twice: refused before anything is written."""
    text = EXPERIMENT.replace('file = "cam2.toml"\nwhite = "white_2.tif"',
                              'file = "cam1.toml"')
    assert text != EXPERIMENT
    (tmp_path / "experiment.toml").write_text(text)
    for name in ("cam1.toml", "raw1", "raw2"):
        (tmp_path / name).symlink_to(two_cameras / name)
    with pytest.raises(ValueError, match=r"cameras 1 and 2 have the same pose"):
        plenocl.run(tmp_path / "experiment.toml", progress=False)
    assert not (tmp_path / "results").exists()


def test_a_bad_frame_of_one_camera_is_named_with_its_camera(two_cameras, tmp_path,
                                                             monkeypatch):
    """Both cameras' folders hold frame_004.tif: camera 2's with a NaN pixel fails its
    pair naming camera 2's file, and the pair's files each with its camera (the pair's
    names were four file names, two of them the same)."""
    import shutil

    from plenocl.batch import worker
    from plenocl.io.files import read_image

    for name in ("experiment.toml", "cam1.toml", "cam2.toml", "white_2.tif"):
        shutil.copy(two_cameras / name, tmp_path / name)
    for name in ("raw1", "raw2"):
        shutil.copytree(two_cameras / name, tmp_path / name)
    bad = read_image(tmp_path / "raw2" / "frame_004.tif").astype(np.float32)
    bad[3, 4] = np.nan
    (tmp_path / "raw2" / "frame_004.tif").unlink()
    write_tiff(tmp_path / "raw2" / "frame_004.tif", bad)

    def unused(*args, **kwargs):
        raise ValueError("not computed in this test")

    monkeypatch.setattr(worker, "process_pair", unused)
    monkeypatch.setattr(worker.PairProcessor, "projector", None)
    summary = plenocl.run(tmp_path / "experiment.toml", progress=False, log=lambda _: None)
    assert "camera 2's frame_004.tif contains 1 NaN or Inf pixel(s)" in summary.failed[2]
    assert summary.failed[2].startswith("camera 1's frame_004.tif + camera 2's "
                                        "frame_004.tif + camera 1's frame_005.tif")


def test_a_grid_fitted_to_a_posed_first_camera_is_refused_with_the_files_fix(tmp_path):
    """[grid] z_mm with a posed first camera: named with the experiment file's fix
    ([grid] file), not only the Python one."""
    from plenocl.batch.prepare import run_grid

    posed = Camera.synthetic_850().with_pose(Pose((0.0, 10.0, 0.0), (0.0, 0.0, 0.0)))
    posed.to_toml(tmp_path / "cam1.toml")
    Camera.synthetic_850().with_pose(Pose((0.0, -10.0, 0.0), (0.0, 0.0, 0.0))).to_toml(
        tmp_path / "cam2.toml")
    (tmp_path / "experiment.toml").write_text(EXPERIMENT.replace(
        'file = "cam2.toml"\nwhite = "white_2.tif"', 'file = "cam2.toml"'))
    exp = load_experiment(tmp_path / "experiment.toml")
    with pytest.raises(ValueError, match=r"the \(first\) camera has a \[pose\]: .*give it as "
                                         r"\[grid\] file"):
        run_grid(exp, [posed, posed])
