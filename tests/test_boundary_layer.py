"""The boundary-layer example end to end (small size), resumable and atomic."""

from __future__ import annotations

import json
import re

import pytest

from plenocl.cli.main import main


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("bl")
    assert main(["demo", "boundary-layer", "--size", "small", "--out", str(out)]) == 0
    return out


def test_small_demo_meets_the_accuracy_targets(demo_dir):
    s = json.loads((demo_dir / "summary.json").read_text())
    assert s["mean_profile_rms_error"] <= 0.05
    assert s["velocity_rms_error"] <= 0.15
    assert s["valid_fraction"] >= 0.9
    assert s["recovery"]["default_mlem"]["recovered_fraction"] > \
        s["recovery"]["paper_mart"]["recovered_fraction"]
    assert set(s["seconds"]) >= {"calibration", "images", "reconstruction", "piv"}
    # lateral and depth in voxels, against the window-averaged truth: depth at most 3x
    # lateral (issue 15's target for the paper demo); the averaged truth is the closer one
    win, point = (s["lateral_depth_error"][k] for k in ("window_averaged", "point"))
    assert win["depth_voxels"] <= 3 * win["lateral_voxels"]
    assert win["lateral_voxels"] <= point["lateral_voxels"] + 1e-9


def test_the_hexagonal_camera_demo_meets_the_same_targets(demo_dir, tmp_path, capsys):
    """``plenocl demo --layout hexagonal``: the boundary layer behind a hexagonal array of
    the same pitch on the same sensor (issue 29), calibrated, reconstructed, correlated
    and fitted to its raw images end to end, meets the rectangular demo's targets."""
    out = tmp_path / "hex"
    assert main(["demo", "--layout", "hexagonal", "--out", str(out)]) == 0
    assert "hexagonal array" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    rect = json.loads((demo_dir / "summary.json").read_text())
    print({k: (s[k], rect[k]) for k in ("velocity_rms_error", "mean_profile_rms_error")},
          s["lateral_depth_error"]["window_averaged"], s["recovery"])
    assert s["layout"] == "hexagonal" and rect["layout"] == "rectangular"
    assert s["mean_profile_rms_error"] <= 0.05 and s["velocity_rms_error"] <= 0.15
    assert s["valid_fraction"] >= 0.9
    win = s["lateral_depth_error"]["window_averaged"]
    assert win["depth_voxels"] <= 3 * win["lateral_voxels"]
    assert s["recovery"]["default_mlem"]["recovered_fraction"] > \
        s["recovery"]["paper_mart"]["recovered_fraction"]


def test_the_layout_option_belongs_to_the_boundary_layer_demo(tmp_path, capsys):
    assert main(["demo", "particles", "--layout", "hexagonal", "--out", str(tmp_path)]) == 2
    assert "boundary-layer demo only" in capsys.readouterr().err


def test_demo_writes_field_figures_and_no_partial_files(demo_dir):
    from plenocl.demo.figures import FIGURES

    for name in ("field.vti", "field.npz", "camera_calibrated.toml", *FIGURES):
        assert (demo_dir / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" or \
            not name.endswith(".png"), name
        assert (demo_dir / name).stat().st_size > 0, name
    assert not list(demo_dir.glob(".*.part*"))
    assert "<ImageData" in (demo_dir / "field.vti").read_text(errors="ignore")[:2000]


def test_rerun_resumes_without_repeating_stages(demo_dir, capsys):
    before = (demo_dir / "vol_a.npz").stat().st_mtime_ns
    assert main(["demo", "boundary-layer", "--size", "small", "--out", str(demo_dir)]) == 0
    out = capsys.readouterr().out
    assert "[reconstruction] done earlier" in out and "[piv] done earlier" in out
    assert (demo_dir / "vol_a.npz").stat().st_mtime_ns == before


def test_a_missing_output_reruns_only_its_stage(demo_dir, capsys):
    (demo_dir / "field.vti").unlink()
    assert main(["demo", "boundary-layer", "--size", "small", "--out", str(demo_dir)]) == 0
    out = capsys.readouterr().out
    assert "[reconstruction] done earlier" in out and "[piv] ..." in out
    assert (demo_dir / "field.vti").is_file()


def _readme_blocks(language: str) -> list[str]:
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    return re.findall(rf"```{language}\n(.*?)```", text, flags=re.S)


def test_readme_python_blocks_run_as_written(demo_dir, tmp_path, monkeypatch):
    """Every Python block of the README runs after its first command (the demo), reading
    the files the demo wrote (here from the test's demo folder, linked as ``demo``)."""
    (tmp_path / "demo").symlink_to(demo_dir, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    blocks = _readme_blocks("python")
    assert blocks
    for block in blocks:
        namespace: dict = {}
        exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102
    assert namespace["res"].valid.mean() > 0.5


def test_readme_toml_blocks_are_valid_files(tmp_path):
    """The README's camera and grid files load as written."""
    from plenocl import Camera, Grid

    loaded = []
    for k, block in enumerate(_readme_blocks("toml")):
        path = tmp_path / f"block{k}.toml"
        path.write_text(block)
        loaded.append(Grid.from_toml(path) if "[grid]" in block else Camera.from_toml(path))
    assert {type(x).__name__ for x in loaded} == {"Camera", "Grid"}


def test_two_cameras_see_the_boundary_layer_sharper_in_depth(tmp_path, capsys):
    """``plenocl demo --cameras 2``: two cameras 25 degrees apart, each calibrated from
    its white image and its pose from a dot target (within 0.05 degree and 0.02 mm),
    measure the boundary layer with a smaller depth error than the first camera alone on
    the same particles, recovering more of them; the demo's figures are drawn."""
    out = tmp_path / "two"
    assert main(["demo", "--cameras", "2", "--out", str(out)]) == 0
    assert "two cameras 25 deg apart" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    two, one = s["fields"]["two_cameras"], s["fields"]["camera_1_alone"]
    assert two["depth_voxels"] < 0.8 * one["depth_voxels"], s["fields"]
    assert two["valid_fraction"] >= 0.9
    assert two["recovered_fraction"] > one["recovered_fraction"]
    # the mean profile within the single camera demo's bound, and its figures drawn
    assert two["mean_profile_rms_error"] <= 0.05, two
    from plenocl.demo.figures import FIGURES

    for name in FIGURES:
        assert (out / name).stat().st_size > 10_000, name
    for pose in s["pose_errors"]:
        assert pose["angle_deg"] < 0.05 and pose["translation_mm"] < 0.02, s["pose_errors"]
    assert main(["demo", "--cameras", "2", "--size", "paper", "--out", str(out)]) == 2
    assert "--cameras 2 runs the small boundary-layer demo" in capsys.readouterr().err
