"""``docs/results.md`` written by one command: a manifest of benchmark runs, one record
per run, and the page assembled from the records.

``python benchmarks/results_page.py`` runs every :class:`Entry` of
:data:`plenocl.bench.results_manifest.MANIFEST` as a subprocess (``python
benchmarks/X.py ARGS`` from the repository root), stores what it printed with the
machine it ran on as a JSON record (``results/NAME.json`` beside the page: see
:func:`run_entry`), and writes the page from every record present
(:func:`render_page`), so that an entry not rerun keeps its last record. Each script
prints its own tables with the baseline measured in the same run beside each figure;
the page shows that output verbatim under the entry's method paragraph, with the
command, device, CPU, date, commit and wall time of the run.

Every file is written atomically (:func:`plenocl.io.atomic.write_text`): a run that
fails or is interrupted leaves the previous page and records whole. A script that fails
(non-zero exit, or past its entry's time limit) gets a failed record holding its exit
code and the end of its error output, and keeps the last successful run beside it
(``previous``), which the page still shows.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from ..io.atomic import write_json, write_text
from ..version import __version__

__all__ = ["SECTIONS", "Entry", "describe_cpu", "describe_device", "describe_machine",
           "git_state", "load_records", "record_path", "records_dir", "render_page",
           "run_entries", "run_entry", "store_record", "write_page"]

#: The page's sections, in order.
SECTIONS = ("Accuracy", "Performance", "Tracking", "Calibration", "Agreement")
#: The command that writes the page (named on it).
PAGE_COMMAND = "python benchmarks/results_page.py"
#: Lines of a failed script's error output kept in its record.
STDERR_LINES = 40
#: What an entry's name may be.
NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")


@dataclass(frozen=True)
class Entry:
    """One benchmark run of the results page.

    Parameters
    ----------
    name
        The record's name (``results/NAME.json``) and ``--only``'s key: lower case,
        digits, ``-`` and ``_``.
    section
        One of :data:`SECTIONS`.
    title
        The entry's heading on the page.
    method
        What is measured and against which baseline: methods only, no figures or dates
        (those come from the run's output).
    argv
        The arguments after ``python``: a script path relative to the repository root
        and its options, or ``-m``/``-c`` and theirs.
    minutes
        The expected run time on 2 CPU cores with PoCL (``--list``; the time limit is
        five times it plus five minutes).
    """

    name: str
    section: str
    title: str
    method: str
    argv: tuple[str, ...]
    minutes: float

    def __post_init__(self) -> None:
        if not NAME.fullmatch(self.name):
            raise ValueError(f"entry name {self.name!r}: use lower case, digits, - and _")
        if self.section not in SECTIONS:
            raise ValueError(f"entry {self.name!r}: section {self.section!r} is not one of "
                             f"{', '.join(SECTIONS)}")

    @property
    def command(self) -> str:
        """The command line as a user types it from the repository root."""
        return "python " + shlex.join(self.argv)

    @property
    def timeout_s(self) -> float:
        """Seconds after which the run is stopped and recorded as failed."""
        return 300.0 + 5 * 60.0 * self.minutes


def records_dir(page: str | Path) -> Path:
    """The folder of the records of ``page``: ``results/`` beside it."""
    return Path(page).parent / "results"


def record_path(page: str | Path, name: str) -> Path:
    """The record file of entry ``name`` of ``page``."""
    return records_dir(page) / f"{name}.json"


# ---------------------------------------------------------------------------- machine


def describe_cpu(cpuinfo: str | Path = "/proc/cpuinfo") -> dict:
    """The host CPU: its model name (``/proc/cpuinfo``, else the platform's processor
    string) and its logical core count."""
    model = platform.processor() or platform.machine()
    try:
        text = Path(cpuinfo).read_text(encoding="utf-8", errors="replace")
    except OSError:
        text = ""
    found = re.search(r"^model name\s*:\s*(.+)$", text, re.MULTILINE)
    if found:
        model = " ".join(found.group(1).split())
    return {"model": model, "cores": os.cpu_count()}


def describe_device() -> dict:
    """The OpenCL device the benchmark scripts pick (``PYOPENCL_CTX``, else plenocl's
    default choice): device name, type and OpenCL version, platform name and version;
    ``{"error": why}`` where there is none."""
    try:
        import pyopencl as cl

        from ..opencl.device import get_queue

        device = get_queue().device
        return {"name": device.name.strip(), "type": cl.device_type.to_string(device.type),
                "version": " ".join(device.version.split()),
                "platform": device.platform.name.strip(),
                "platform_version": " ".join(device.platform.version.split()),
                "compute_units": int(device.max_compute_units)}
    except Exception as exc:  # no OpenCL here: the record says so, the run goes on
        return {"error": f"{type(exc).__name__}: {exc}"}


def git_state(root: str | Path, exclude: Sequence[str | Path] = ()) -> dict:
    """``{"commit": short hash, "dirty": bool}`` of the checkout at ``root``; dirty:
    tracked or untracked changes outside the paths ``exclude`` (the page and its
    records). ``{"commit": None, "dirty": None}`` outside a git checkout."""
    root = Path(root)

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                              check=True, timeout=60).stdout.strip()

    skip = [f":(exclude){Path(p).resolve().relative_to(root.resolve())}" for p in exclude
            if Path(p).resolve().is_relative_to(root.resolve())]
    try:
        commit = git("rev-parse", "--short", "HEAD")
        changes = git("status", "--porcelain", "--", ".", *skip)
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": bool(changes)}


def describe_machine(root: str | Path, page: str | Path) -> dict:
    """What every record of one run shares: the OpenCL device, the CPU, the commit of
    ``root`` (whether anything but ``page`` and its records differs from it), plenocl's
    version and ``PYOPENCL_CTX``."""
    return {"device": describe_device(), "cpu": describe_cpu(),
            "git": git_state(root, exclude=[page, records_dir(page)]),
            "plenocl_version": __version__,
            "pyopencl_ctx": os.environ.get("PYOPENCL_CTX") or None}


# ---------------------------------------------------------------------------- running


def script_env(root: str | Path) -> dict[str, str]:
    """The scripts' environment: this one with ``root`` first on ``PYTHONPATH``,
    unbuffered output (what a stopped script printed is kept) and matplotlib's file
    backend."""
    env = dict(os.environ)
    paths = [str(Path(root).resolve())] + [p for p in env.get("PYTHONPATH", "").split(
        os.pathsep) if p]
    env.update(PYTHONPATH=os.pathsep.join(paths), PYTHONUNBUFFERED="1", MPLBACKEND="Agg")
    return env


def _text(data: bytes | str | None) -> str:
    if data is None:
        return ""
    return data.decode("utf-8", errors="replace") if isinstance(data, bytes) else data


def tail(text: str, lines: int = STDERR_LINES) -> str:
    """The last ``lines`` lines of ``text``."""
    return "\n".join(text.rstrip().splitlines()[-lines:])


def _execute(entry: Entry, root: Path) -> tuple[int | None, str, str, float]:
    """Run ``entry``: exit code (``None``: stopped at its time limit), stdout, stderr,
    wall seconds."""
    t0 = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, *entry.argv], cwd=root, env=script_env(root),
                              capture_output=True, timeout=entry.timeout_s)
    except subprocess.TimeoutExpired as exc:
        return None, _text(exc.stdout), _text(exc.stderr), time.perf_counter() - t0
    return done.returncode, _text(done.stdout), _text(done.stderr), time.perf_counter() - t0


def user_command(entry: Entry, machine: Mapping) -> str:
    """``entry``'s command line, with ``PYOPENCL_CTX=...`` before it where it was set."""
    ctx = machine.get("pyopencl_ctx")
    return (f"PYOPENCL_CTX={shlex.quote(ctx)} " if ctx else "") + entry.command


def run_entry(entry: Entry, root: str | Path, machine: Mapping) -> dict:
    """Run ``entry`` from ``root`` and return its record.

    Parameters
    ----------
    entry
        The run.
    root
        The repository root (the working directory; first on ``PYTHONPATH``).
    machine
        :func:`describe_machine`'s description, copied into the record.

    Returns
    -------
    dict
        ``name``, ``section``, ``title``, ``method``, ``command`` (as a user types it),
        ``argv``, ``status`` (``"ok"``, ``"failed"`` or ``"timeout"``), ``returncode``,
        ``stdout``, ``stderr_tail``, ``wall_s``, ``date`` (UTC, ISO 8601, the start) and
        the machine's keys.
    """
    date = datetime.now(UTC).isoformat(timespec="seconds")
    code, out, err, wall = _execute(entry, Path(root))
    status = "ok" if code == 0 else ("timeout" if code is None else "failed")
    return {"name": entry.name, "section": entry.section, "title": entry.title,
            "method": entry.method, "command": user_command(entry, machine),
            "argv": list(entry.argv), "status": status, "returncode": code,
            "stdout": out, "stderr_tail": tail(err), "wall_s": round(wall, 2),
            "date": date, **dict(machine)}


# ---------------------------------------------------------------------------- records


def load_record(path: str | Path) -> dict | None:
    """The record at ``path``; ``None`` where there is none or it is not a record."""
    try:
        record = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "name" in record else None


def load_records(page: str | Path) -> dict[str, dict]:
    """Every record of ``page``, by name."""
    out = {}
    for path in sorted(records_dir(page).glob("*.json")):
        record = load_record(path)
        if record is not None and record["name"] == path.stem and NAME.fullmatch(path.stem):
            out[path.stem] = record
    return out


def store_record(page: str | Path, record: dict) -> Path:
    """Write ``record`` (atomically) as its entry's record of ``page``; a failed one
    keeps the last successful run's record under ``previous``."""
    path = record_path(page, record["name"])
    if record["status"] != "ok":
        old = load_record(path)
        last = old if old and old.get("status") == "ok" else (old or {}).get("previous")
        if last:
            record = {**record, "previous": last}
    write_json(path, record)
    return path


# ---------------------------------------------------------------------------- the page


def fenced(text: str, info: str = "text") -> str:
    """``text`` verbatim in a fenced code block whose fence no line of it can close."""
    longest = max((len(run) for run in re.findall(r"`+", text)), default=0)
    fence = "`" * max(3, longest + 1)
    body = text.rstrip("\n")
    return f"{fence}{info}\n{body}\n{fence}" if body else f"{fence}{info}\n(no output)\n{fence}"


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(round(seconds), 60)
    return f"{minutes} min {secs} s" if minutes < 60 else f"{minutes // 60} h {minutes % 60} min"


def _device_text(device: Mapping) -> str:
    if "error" in device:
        return f"no OpenCL device ({device['error']})"
    return (f"{device.get('name', '?')} on {device.get('platform', '?')} "
            f"({device.get('platform_version', '?')})")


def _date_text(iso: str) -> str:
    try:
        return datetime.fromisoformat(iso).astimezone(UTC).strftime("%Y-%m-%d %H:%M UTC")
    except (TypeError, ValueError):
        return str(iso)


def run_line(record: Mapping) -> str:
    """The record's command, device, CPU, date, commit, plenocl version and wall time."""
    cpu, git = record.get("cpu", {}), record.get("git", {})
    commit = git.get("commit") or "no git commit"
    if git.get("dirty"):
        commit += " with uncommitted changes"
    return (f"`{record.get('command', '?')}` — {_device_text(record.get('device', {}))}; "
            f"CPU {cpu.get('model', '?')} ({cpu.get('cores', '?')} cores); "
            f"{_date_text(record.get('date', '?'))}; commit {commit}; "
            f"plenocl {record.get('plenocl_version', '?')}; "
            f"wall time {_duration(float(record.get('wall_s', 0.0)))}.")


def _failure_lines(record: Mapping) -> list[str]:
    how = (f"stopped at its time limit after {_duration(float(record.get('wall_s', 0)))}"
           if record.get("status") == "timeout" else f"exit code {record.get('returncode')}")
    lines = [f"**Failed** ({how}): {run_line(record)} What it printed, then the end of "
             "its error output:", "", fenced(record.get("stdout", "")), "",
             fenced(record.get("stderr_tail", ""))]
    previous = record.get("previous")
    if previous:
        lines += ["", f"The last successful run: {run_line(previous)}", "",
                  fenced(previous.get("stdout", ""))]
    return lines


def render_entry(entry: Entry, record: Mapping | None, orphan: bool = False) -> str:
    """One entry of the page: heading, method, then its run (or how to measure it)."""
    lines = [f"### {entry.title}", "", entry.method.strip(), ""]
    refresh = f"`{PAGE_COMMAND} --only {entry.name}`"
    if orphan:
        lines += [f"No longer in the manifest: this record stays until `results/{entry.name}"
                  ".json` beside the page is deleted.", ""]
    if record is None:
        lines += [f"Not yet measured: run {refresh} (it runs `{entry.command}`, about "
                  f"{entry.minutes:g} min on 2 CPU cores)."]
    elif record.get("status") != "ok":
        lines += _failure_lines(record)
    else:
        lines += [run_line(record), "", fenced(record.get("stdout", ""))]
    if record is not None and not orphan and record.get("argv") != list(entry.argv):
        lines += ["", f"The manifest now runs `{entry.command}`: refresh with {refresh}."]
    return "\n".join(lines)


def _orphan_entry(record: Mapping) -> Entry:
    """An :class:`Entry` rebuilt from a record whose name left the manifest."""
    section = record.get("section") if record.get("section") in SECTIONS else SECTIONS[-1]
    return Entry(record["name"], section, record.get("title") or record["name"],
                 record.get("method", ""), tuple(record.get("argv", ())), 0.0)


def page_header() -> str:
    """The page's title and its paragraph on how it is made."""
    return (
        "# Results: accuracy and performance\n\n"
        f"This page is generated by `{PAGE_COMMAND}`: do not edit it by hand. That command "
        "runs every benchmark of its manifest (`plenocl/bench/results_manifest.py`; "
        f"`{PAGE_COMMAND} --list` lists them with their expected run times), stores each "
        "run's output with the machine it ran on in `results/NAME.json` beside this page "
        f"and writes this page from every record there. To refresh one entry run `{PAGE_COMMAND} "
        f"--only NAME`; `{PAGE_COMMAND} --page-only` rebuilds the page from the records "
        "alone. Each entry gives what is measured and against which baseline, the command, "
        "device, CPU, date, commit and wall time of its run, and the script's output "
        "verbatim: each script prints the baseline it measured in the same run beside "
        "each figure.")


def render_page(manifest: Iterable[Entry], records: Mapping[str, Mapping]) -> str:
    """The page: the header, then per section (in :data:`SECTIONS` order) each entry of
    ``manifest`` with its record, and the records of entries no longer in it."""
    manifest = list(manifest)
    known = {e.name for e in manifest}
    pairs = [(e, records.get(e.name), False) for e in manifest]
    pairs += [(_orphan_entry(r), r, True) for n, r in sorted(records.items()) if n not in known]
    parts = [page_header()]
    for section in SECTIONS:
        entries = [render_entry(e, r, orphan) for e, r, orphan in pairs if e.section == section]
        if entries:
            parts += [f"## {section}", *entries]
    return "\n\n".join(parts) + "\n"


def write_page(page: str | Path, manifest: Iterable[Entry]) -> Path:
    """Write ``page`` (atomically) from ``manifest`` and every record present."""
    write_text(page, render_page(manifest, load_records(page)))
    return Path(page)


def run_entries(entries: Sequence[Entry], manifest: Iterable[Entry], root: str | Path,
                page: str | Path, machine: Mapping | None = None,
                log: Callable[[str], object] = print) -> list[str]:
    """Run ``entries`` one after the other, storing each record and rewriting ``page``
    (from ``manifest`` and every record) after each; return the names that failed."""
    manifest = list(manifest)
    machine = describe_machine(root, page) if machine is None else machine
    failed = []
    for k, entry in enumerate(entries, 1):
        log(f"[{k}/{len(entries)}] {entry.name}: {entry.command} (about {entry.minutes:g} min)")
        record = run_entry(entry, root, machine)
        store_record(page, record)
        write_page(page, manifest)
        log(f"    {record['status']} in {_duration(record['wall_s'])}")
        if record["status"] != "ok":
            failed.append(entry.name)
            log(tail(record["stderr_tail"], 5))
    return failed
