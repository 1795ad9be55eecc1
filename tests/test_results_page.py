"""docs/results.md by one command (``benchmarks/results_page.py``,
:mod:`plenocl.bench.results`): the page from fabricated records, atomic writes, real
subprocess runs of tiny entries, the CLI's ``--page-only`` and the manifest itself."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest

from plenocl.bench import results
from plenocl.bench.results import (
    SECTIONS,
    Entry,
    describe_cpu,
    describe_device,
    git_state,
    load_records,
    record_path,
    render_page,
    run_entries,
    store_record,
    write_page,
)
from plenocl.bench.results_manifest import BUDGET_MINUTES, MANIFEST

ROOT = Path(__file__).resolve().parents[1]
MACHINE = {"device": {"name": "Test CPU", "platform": "Test OpenCL", "platform_version": "3.0"},
           "cpu": {"model": "Test EPYC", "cores": 2}, "git": {"commit": "abc1234", "dirty": True},
           "plenocl_version": "0.0.test", "pyopencl_ctx": None}
# an output line with a code fence and a Markdown heading: both must stay verbatim
OUTPUT = "seeding 0.05: lateral 0.041 / depth 0.27 voxel\n```\n# not a heading\nbaseline 0.51\n"


def entry(name: str, section: str = "Performance", code: str = "print('x')",
          minutes: float = 0.1) -> Entry:
    return Entry(name, section, f"Title of {name}", f"Method of {name}.", ("-c", code), minutes)


def record(e: Entry, status: str = "ok", stdout: str = OUTPUT, **extra) -> dict:
    return {"name": e.name, "section": e.section, "title": e.title, "method": e.method,
            "command": e.command, "argv": list(e.argv), "status": status,
            "returncode": 0 if status == "ok" else 2, "stdout": stdout,
            "stderr_tail": "" if status == "ok" else "Traceback ...\nValueError: broken",
            "wall_s": 83.4, "date": "2026-11-28T10:00:00+00:00", **MACHINE, **extra}


def headings(page: str) -> list[tuple[int, str]]:
    """(level, text) of the page's headings, outside its code blocks."""
    out, fence = [], None
    for line in page.splitlines():
        run = line[:len(line) - len(line.lstrip("`"))]
        if len(run) >= 3 and (fence is None or (run.startswith(fence) and not line[len(run):])):
            fence = None if fence else run
        elif fence is None and line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            out.append((level, line[level:].strip()))
    return out


def test_page_shows_every_entry_in_section_order_and_how_to_measure_the_missing():
    manifest = [entry("acc", "Accuracy"), entry("perf"), entry("cal", "Calibration"),
                entry("agree", "Agreement")]
    records = {"acc": record(manifest[0]), "perf": record(manifest[1])}
    page = render_page(manifest, records)
    heads = headings(page)
    assert heads[0] == (1, "Results: accuracy and performance")
    assert [t for lvl, t in heads if lvl == 2] == ["Accuracy", "Performance", "Calibration",
                                                  "Agreement"]
    assert [t for lvl, t in heads if lvl == 3] == [e.title for e in manifest]
    assert all(b[0] <= a[0] + 1 for a, b in zip(heads, heads[1:], strict=False))
    assert "python benchmarks/results_page.py" in page.split("##")[0]
    assert "do not edit it by hand" in page
    for e in manifest[2:]:
        assert f"Not yet measured: run `python benchmarks/results_page.py --only {e.name}`" in page
    assert "Test CPU on Test OpenCL (3.0)" in page and "Test EPYC (2 cores)" in page
    assert "2026-11-28 10:00 UTC" in page and "abc1234 with uncommitted changes" in page
    assert "1 min 23 s" in page and "plenocl 0.0.test" in page


def fences(page: str) -> list[str]:
    """The contents of the page's fenced code blocks, read by CommonMark's rule: a block
    opens with three or more backticks and closes at a line of at least as many backticks
    and nothing else."""
    blocks, open_fence, lines = [], None, []
    for line in page.splitlines():
        if open_fence is None:
            start = re.fullmatch(r"(`{3,})[^`]*", line)
            if start:
                open_fence, lines = start.group(1), []
        elif re.fullmatch(f"`{{{len(open_fence)},}}\\s*", line):
            blocks.append("".join(f"{text}\n" for text in lines))
            open_fence = None
        else:
            lines.append(line)
    return blocks


def test_page_keeps_every_record_text_verbatim():
    e, gone = entry("perf"), entry("retired", "Tracking")
    failed = record(e, "failed", stdout="half a table\n",
                    previous=record(e, stdout="the last good table\n"))
    page = render_page([e], {"perf": failed, "retired": record(gone, stdout=OUTPUT)})
    blocks = fences(page)
    assert blocks == ["half a table\n", failed["stderr_tail"] + "\n",
                      "the last good table\n", OUTPUT]
    assert "**Failed** (exit code 2)" in page
    assert "## Tracking" in page and "No longer in the manifest" in page


def test_store_record_keeps_the_last_good_run_beside_a_failure(tmp_path):
    page, e = tmp_path / "results.md", entry("perf")
    store_record(page, record(e, stdout="good\n"))
    store_record(page, record(e, "failed", stdout="bad 1\n"))
    store_record(page, record(e, "timeout", stdout="bad 2\n"))
    kept = load_records(page)["perf"]
    assert (kept["status"], kept["stdout"], kept["previous"]["stdout"]) == ("timeout", "bad 2\n",
                                                                            "good\n")
    store_record(page, record(e, stdout="good again\n"))
    assert "previous" not in load_records(page)["perf"]


def test_a_failing_write_leaves_the_old_page_and_record_whole(tmp_path, monkeypatch):
    page, e = tmp_path / "results.md", entry("perf")
    store_record(page, record(e, stdout="old output\n"))
    write_page(page, [e])
    before = page.read_bytes(), record_path(page, "perf").read_bytes()

    def broken(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", broken)
    with pytest.raises(OSError, match="disk full"):
        store_record(page, record(e, stdout="new output\n"))
    with pytest.raises(OSError, match="disk full"):
        write_page(page, [e, entry("other")])
    assert (page.read_bytes(), record_path(page, "perf").read_bytes()) == before
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["perf.json", "results", "results.md"]


def test_run_entries_runs_real_subprocesses_and_marks_the_failures(tmp_path):
    code = ("import os, sys; print('measured 1.5 s, baseline 3.0 s'); "
            "print(os.environ['PYTHONPATH'].split(os.pathsep)[0]); print('cwd', os.getcwd()); "
            "sys.stderr.write('a warning\\n')")
    good, bad = entry("good", code=code), entry("bad", code="print('half'); raise SystemExit(3)")
    page, log = tmp_path / "docs" / "results.md", []
    failed = run_entries([good, bad], [good, bad], ROOT, page, MACHINE, log.append)
    assert failed == ["bad"] and len(log) >= 4
    rec = load_records(page)
    ok = rec["good"]
    assert (ok["status"], ok["returncode"], ok["stderr_tail"]) == ("ok", 0, "a warning")
    assert ok["stdout"] == f"measured 1.5 s, baseline 3.0 s\n{ROOT}\ncwd {ROOT}\n"
    assert ok["command"] == good.command and good.command.startswith("python -c ")
    assert 0 < ok["wall_s"] < 60
    assert datetime.fromisoformat(ok["date"]).utcoffset().total_seconds() == 0
    assert ok["device"] == MACHINE["device"] and ok["git"] == MACHINE["git"]
    assert (rec["bad"]["status"], rec["bad"]["returncode"], rec["bad"]["stdout"]) == ("failed", 3,
                                                                                    "half\n")
    text = page.read_text()
    assert "measured 1.5 s, baseline 3.0 s" in text and "**Failed** (exit code 3)" in text


def test_a_run_past_its_time_limit_is_stopped_and_keeps_its_output(tmp_path):
    class Quick(Entry):
        timeout_s = 1.0  # instead of minutes
    e = Quick("slow", "Performance", "Slow", "Sleeps.",
              ("-c", "import time; print('started'); time.sleep(60)"), 0.1)
    page = tmp_path / "results.md"
    assert run_entries([e], [e], ROOT, page, MACHINE, lambda _: None) == ["slow"]
    rec = load_records(page)["slow"]
    assert (rec["status"], rec["returncode"], rec["stdout"]) == ("timeout", None, "started\n")
    assert rec["wall_s"] < 30 and "stopped at its time limit" in page.read_text()


def load_cli():
    spec = importlib.util.spec_from_file_location("results_page", ROOT / "benchmarks" /
                                                  "results_page.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_page_only_through_the_cli_in_a_tmp_dir(tmp_path):
    page = tmp_path / "site" / "results.md"
    real = next(e for e in MANIFEST if e.name == "real-array")
    store_record(page, record(real, stdout="forward + back 63.1 ms, ideal lattice 64.6 ms\n"))
    page.write_text("hand-written\n")
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "results_page.py"),
                           "--page-only", "--out", str(page)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    text = page.read_text()
    assert "forward + back 63.1 ms, ideal lattice 64.6 ms" in text and "hand-written" not in text
    for e in MANIFEST:
        assert f"### {e.title}" in text
        assert (e.name == "real-array") != (f"--only {e.name}`" in text)
    assert json.loads(record_path(page, "real-array").read_text())["stdout"].startswith("forward")


def test_cli_refuses_unknown_names_and_lists_the_manifest(capsys):
    cli = load_cli()
    with pytest.raises(SystemExit) as exc:
        cli.main(["--only", "nonsense"])
    assert exc.value.code == 2
    assert cli.main(["--list"]) == 0
    listed = capsys.readouterr().out
    assert all(e.command in listed for e in MANIFEST) and "total" in listed


def test_manifest_names_scripts_that_exist_within_the_time_budget():
    names = [e.name for e in MANIFEST]
    assert len(set(names)) == len(names)
    assert {e.section for e in MANIFEST} == set(SECTIONS)
    assert sum(e.minutes for e in MANIFEST) <= BUDGET_MINUTES
    for e in MANIFEST:
        assert e.argv[0] == "-m" or (ROOT / e.argv[0]).is_file(), e.argv
        assert e.method and not re.search(r"\b20\d\d-\d\d", e.method), e.name  # no dates
    assert any(e.argv[0] == "benchmarks/paper_pair.py" for e in MANIFEST)
    with pytest.raises(ValueError, match="section"):
        Entry("x", "Speed", "t", "m", ("a.py",), 1.0)
    with pytest.raises(ValueError, match="name"):
        Entry("X y", "Accuracy", "t", "m", ("a.py",), 1.0)


def test_machine_description_cpu_git_and_device(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: AMD  EPYC 7B13 64-Core Processor\n")
    assert describe_cpu(info)["model"] == "AMD EPYC 7B13 64-Core Processor"
    assert describe_cpu(tmp_path / "none")["cores"] == os.cpu_count()
    repo = tmp_path / "repo"
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo)]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / "a.py").write_text("1\n")
    subprocess.run([*git, "add", "a.py"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "a"], check=True)
    assert git_state(repo)["dirty"] is False and len(git_state(repo)["commit"]) >= 7
    (repo / "docs").mkdir()
    (repo / "docs" / "results.md").write_text("page\n")
    assert git_state(repo)["dirty"] is True
    assert git_state(repo, exclude=[repo / "docs" / "results.md"])["dirty"] is False
    assert git_state(tmp_path / "none") == {"commit": None, "dirty": None}
    device = describe_device()
    assert "error" in device or {"name", "platform", "platform_version"} <= device.keys()


def test_fences_outlast_backticks_in_the_output():
    assert results.fenced("a ```` b").startswith("`````text\n")
    assert results.fenced("") == "```text\n(no output)\n```"
