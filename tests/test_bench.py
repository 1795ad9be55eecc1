"""The benchmark report: one call writes every section and its plots; the Pareto helper."""

from __future__ import annotations

import argparse
import re

import numpy as np
import pytest

from plenocl.bench import (
    loglog_slope,
    md_table,
    pareto_front,
    run_report,
)
from plenocl.bench.accuracy_section import ROWS
from plenocl.cli.bench import add_bench_parser, cmd_bench

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SECTIONS = ("## Simulator", "## Calibration", "## Refocusing", "## Projector",
            "## Reconstruction", "## Skipping", "## PIV", "## Accuracy", "## Scaling",
            "## Cross-device agreement")
PLOTS = ("recon_pareto.png", "piv_pareto.png", "scaling.png")


@pytest.mark.one_device
def test_report_regenerates_from_one_call(tmp_path, queue):
    messages = []
    path = run_report("test", tmp_path / "bench", queue=queue, log=messages.append)
    text = path.read_text(encoding="utf-8")
    assert path == tmp_path / "bench" / "report.md"
    for heading in SECTIONS:
        assert heading in text, heading
    assert "incomplete" not in text  # the final rewrite replaced the progress version
    assert "device: **" in text and "load average" in text and "CPU cores" in text
    assert "medians of 2 runs" in text  # the repeat count is stated
    for name in PLOTS:
        data = (path.parent / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5000, name
        assert f"]({name})" in text
    assert not list(path.parent.glob(".*part*"))  # atomic writes leave no temporaries
    assert any("scaling" in m for m in messages)
    assert "dark microlenses" in text and "lit lenses" in text
    budget = text.split("## Accuracy")[1].split("## ")[0]
    rows = [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in budget.strip().splitlines() if line.startswith("| 0.")]
    # default, its unfitted particles, correlation, before (no "previous": not asked for)
    assert [r[4] for r in rows] == [v for k, v in ROWS.items() if k != "previous"]
    for row in rows:
        windows_only, reconstructed = float(row[2]), float(row[5])   # lateral RMS, voxels
        assert windows_only < 0.1 and reconstructed > windows_only  # the reconstruction limits
    if "Portable Computing Language" in queue.device.platform.name:  # its two drivers
        assert re.search(r"(\d+) of \1 comparisons within tolerance", text)


def test_pareto_front_excludes_dominated_points():
    time = [1.0, 2.0, 2.0, 3.0, 0.5, 4.0, 1.5]
    score = [0.5, 0.9, 0.8, 0.9, 0.1, np.nan, 0.5]
    front = pareto_front(time, score)
    # (2, 0.8) loses to (2, 0.9); (3, 0.9) to (2, 0.9); (1.5, 0.5) to (1, 0.5); NaN never
    np.testing.assert_array_equal(front, [True, True, False, False, True, False, False])


def test_pareto_front_lower_is_better_and_ties():
    time = [1.0, 1.0, 2.0, 3.0]
    error = [0.3, 0.3, 0.1, 0.2]
    front = pareto_front(time, error, higher_is_better=False)
    np.testing.assert_array_equal(front, [True, True, True, False])  # equal points both stay


def test_loglog_slope_and_table():
    n = np.array([10.0, 100.0, 1000.0])
    assert loglog_slope(n, 3 * n**1.5) == pytest.approx(1.5)
    assert np.isnan(loglog_slope([10.0], [1.0]))
    assert md_table(["a", "b"], [[1, 2]]).splitlines() == ["| a | b |", "|---|---|",
                                                          "| 1 | 2 |"]


def test_bench_parser_and_bad_arguments(tmp_path):
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default=None)
    add_bench_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["bench"])
    assert (args.size, args.out, args.repeats) == ("ci", "plenocl_bench", None)
    args = parser.parse_args(["--device", "cpu", "bench", "--size", "small", "--out", "o",
                              "--repeats", "2"])
    assert (args.size, args.out, args.repeats, args.device) == ("small", "o", 2, "cpu")
    for bad in (["bench", "--size", "huge"], ["bench", "--repeats", "0"]):
        with pytest.raises(SystemExit):
            parser.parse_args(bad)
    with pytest.raises(ValueError, match="size must be one of"):
        run_report("huge", tmp_path)
    with pytest.raises(ValueError, match="repeats"):
        run_report("test", tmp_path, repeats=0)


def test_piv_section_says_when_openpiv_is_missing(tmp_path, queue, monkeypatch):
    from plenocl.bench import core, piv_section

    monkeypatch.setattr(piv_section, "load_openpiv", lambda: (None, "ImportError: no openpiv"))
    run = core.BenchRun(core.bench_sizes()["test"], queue, tmp_path, lambda *a: None, 1, 1)
    text = piv_section.section_piv(run)
    assert "openpiv is **not** importable" in text and "| openpiv" not in text
    assert (tmp_path / "piv_pareto.png").read_bytes().startswith(PNG_MAGIC)


def test_bench_command_prints_where_the_report_is(tmp_path, capsys):
    args = argparse.Namespace(size="test", out=str(tmp_path), repeats=1, device=None)
    assert cmd_bench(args) == 0
    assert str(tmp_path / "report.md") in capsys.readouterr().out
    assert "medians of 1 run for" in (tmp_path / "report.md").read_text(encoding="utf-8")
