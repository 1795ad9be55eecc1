"""The command line and the examples, run as a user would."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
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
