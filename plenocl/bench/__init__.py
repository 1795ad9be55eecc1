"""The one-command benchmark report: every stage timed against a baseline from the same run.

``plenocl bench --size ci|small|paper --out DIR`` (or :func:`run_report`) runs the stage
benchmarks and writes ``DIR/report.md`` with PNG plots beside it:

- simulator: rays per second of the OpenCL kernel against the NumPy reference (same rays);
- calibration: centre error against time for the paper's box centroid, a windowed
  centroid and the grid-model fit, on clean, noisy, rotated and vignetted white images;
- refocusing: a focal stack by the kernel against SciPy shift-and-add;
- projector: matrix-free forward + back against ``scipy.sparse`` CSR products of the same
  weights, and the memory of both;
- reconstruction: run time against error (recovery, ghosts, Q) for each method and
  setting on the paper's synthetic case, with Pareto fronts;
- skipping: speed-up and error cost of active slices, cropping, dark microlenses, masking
  and early stop;
- PIV: run time against RMS error for window schedules, deformation orders and final
  iterations (and openpiv's 3-D PIV when it is importable);
- scaling: time and memory against voxels, pixels, particles and iterations, with fitted
  log-log slopes, set against the device's memory and the measured throughput;
- cross-device agreement: the same small workloads on every visible OpenCL device,
  against stated tolerances (:mod:`plenocl.bench.agreement`).

Sizes: ``ci`` (about 1-2 minutes on 2 CPU cores), ``small`` (10-15 minutes), ``paper``
(``small`` plus the paper's full 16 MP, 300 x 200 x 150 experiment) and an internal
``test`` size (a tiny camera; seconds). Times are medians of repeated runs after a
warm-up of the kernels; the report states the repeat counts.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.atomic import write_text
from ..opencl.device import DeviceLike, device_info, get_queue
from ..version import __version__
from .accuracy_section import section_accuracy
from .core import SIZES, BenchRun, bench_sizes, loglog_slope, md_table, pareto_front, repeats_text
from .devices import section_devices
from .lightfield_section import section_calibration, section_refocus
from .piv_section import piv_flows, section_piv
from .results import describe_cpu
from .scaling import section_scaling
from .stages import section_projector, section_reconstruction, section_simulator, section_skipping

__all__ = ["SIZES", "loglog_slope", "md_table", "pareto_front", "piv_flows", "run_report"]


# ---- the report -----------------------------------------------------------------------
SECTIONS: tuple[tuple[str, Callable[[BenchRun], str]], ...] = (
    ("simulator", section_simulator),
    ("calibration", section_calibration),
    ("refocusing", section_refocus),
    ("projector", section_projector),
    ("reconstruction", section_reconstruction),
    ("skipping", section_skipping),
    ("PIV", section_piv),
    ("accuracy", section_accuracy),
    ("scaling", section_scaling),
    ("cross-device", section_devices),
)


def _machine() -> str:
    """CPU model and core count (:func:`.results.describe_cpu`), memory, OS."""
    cpu = describe_cpu()
    try:
        mem = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM"
    except (ValueError, OSError, AttributeError):
        mem = ""
    return (f"{cpu['cores']} CPU cores ({cpu['model']}){mem}, {platform.system()} "
            f"{platform.release()}")


def _load() -> str:
    return " / ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"


def _header(run: BenchRun, load_start: str, end: tuple[str, float] | None) -> str:
    import pyopencl
    import scipy

    info, dev = device_info(run.queue), run.queue.device
    status = (f"load average (1 / 5 / 15 min) at end {end[0]}; total {end[1]:.0f} s"
              if end else "**incomplete: the run is still going (or stopped)**")
    return (f"# plenocl benchmark report (size `{run.cfg.name}`)\n\n"
            f"- generated {time.strftime('%Y-%m-%d %H:%M:%S')} by `plenocl bench --size "
            f"{run.cfg.name}`; plenocl {__version__}, Python {platform.python_version()}, "
            f"NumPy {np.__version__}, SciPy {scipy.__version__}, PyOpenCL "
            f"{pyopencl.VERSION_TEXT}\n"
            f"- device: **{info.name}** (platform {info.platform}, "
            f"{dev.platform.version.strip()}), {info.type}, {info.compute_units} compute "
            f"units, {info.global_mem_bytes / 2**30:.1f} GiB global memory\n"
            f"- machine: {_machine()}; load average (1 / 5 / 15 min) at start {load_start}; "
            f"{status}\n"
            f"- repeats: medians of {repeats_text(run.repeats)} for the simulator, projector "
            f"and scaling; {repeats_text(run.heavy)} for reconstruction, skipping and PIV (one "
            "warm-up first where stated)\n"
            + (f"- headline: {'; '.join(run.notes)}\n" if run.notes else "") + "\n")


def run_report(size: str, out_dir: str | Path, repeats: int | None = None,
               queue: DeviceLike = None, log: Callable[..., None] = print) -> Path:
    """Run the stage benchmarks and write ``report.md`` and PNG plots into ``out_dir``.

    Parameters
    ----------
    size
        ``"ci"`` (about 1-2 minutes on 2 CPU cores), ``"small"`` (10-15 minutes),
        ``"paper"`` (``small`` plus the paper's 16 MP experiment) or ``"test"`` (a tiny
        camera, for the test suite).
    out_dir
        Folder of the report (created); files are replaced atomically. The report is
        rewritten after every section, marked incomplete until the end.
    repeats
        Runs per timing (the median is reported) for every section; by default per size
        (``ci``: 3 for cheap stages, 2 for reconstruction, skipping and PIV).
    queue
        OpenCL queue, device or name substring (:func:`plenocl.opencl.device.get_queue`).
    log
        Progress messages (``print`` by default).

    Returns
    -------
    pathlib.Path
        The report's path.
    """
    sizes = bench_sizes()
    if size not in sizes:
        raise ValueError(f"size must be one of {SIZES}, got {size!r}")
    if repeats is not None and repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}")
    cfg, out = sizes[size], Path(out_dir)
    run = BenchRun(cfg, get_queue(queue), out, log, repeats or cfg.repeats,
               repeats or cfg.heavy_repeats)
    load_start, t0, parts = _load(), time.perf_counter(), []
    path = out / "report.md"
    for title, section in SECTIONS:
        log(f"bench: {title} ...")
        t1 = time.perf_counter()
        parts.append(section(run))
        log(f"bench: {title} done in {time.perf_counter() - t1:.1f} s")
        write_text(path, _header(run, load_start, None) + "\n".join(parts))
    end = (_load(), time.perf_counter() - t0)
    write_text(path, _header(run, load_start, end) + "\n".join(parts))
    return path
