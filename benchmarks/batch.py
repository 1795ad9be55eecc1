"""Throughput of a batch run and of its PIV stage (issue 16).

Run from the repository root::

    python benchmarks/batch.py            # PIV at paper size (3 repeats) + batch (6 pairs)
    python benchmarks/batch.py --quick    # 1 repeat

1. **PIV at the paper's grid** (150 x 200 x 300 voxels): ``piv3d`` with default settings
   on a synthetic volume pair (Gaussian particles, sigma 1.5 voxels, 0.0004 per voxel,
   a uniform shift of (2.31, -1.47, 0.68) voxels, noise 0.02), the reference path
   (SciPy deformation on the host, SciPy pocketfft) against the default path of
   ``process_pair`` (deformation on the OpenCL device, FFTW), same volumes, same
   process: median seconds and RMS error.
2. **Pairs per hour**: the time-series demo's experiment (``plenocl demo time-series``,
   small camera, 6 pairs) processed serially and with ``--workers 2`` (a local Dask
   cluster), same machine, same run, each from an empty output folder; the stage split
   per pair from the serial run's ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import flows, get_queue, piv3d  # noqa: E402
from plenocl.batch import run  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.demo.time_series import run_time_series  # noqa: E402

SHIFT = (2.31, -1.47, 0.68)


def piv_rows(repeats: int, queue) -> list[str]:
    """Reference against default PIV at the paper's grid."""
    pair = flows.volume_pair((150, 200, 300), flows.Uniform(SHIFT), density=0.0004,
                             sigma=1.5, seed=1, noise=0.02)
    rows = []
    for label, kw in (("reference: SciPy deform + pocketfft", {"fft": "scipy"}),
                      ("default: device deform + FFTW", {"queue": queue})):
        res, seconds = timed(lambda kw=kw: piv3d(pair.vol_a, pair.vol_b, **kw), repeats)
        err = [float(np.sqrt(np.mean((c - s) ** 2))) for c, s in zip((res.u, res.v, res.w),
                                                                     SHIFT)]
        rows.append((label, seconds, err, res.passes))
    base = rows[0][1]
    out = ["| PIV path | median s | speed-up | RMS error u, v, w (voxels) | windows |",
           "|---|---|---|---|---|"]
    for label, seconds, err, passes in rows:
        out.append(f"| {label} | {seconds:.1f} | {base / seconds:.2f}x | "
                   + ", ".join(f"{e:.4f}" for e in err)
                   + f" | {' '.join(str(p['window'][0]) for p in passes)} |")
    return out


def batch_rows(queue) -> list[str]:
    """Pairs per hour serially and on 2 Dask workers, and the serial stage split."""
    work = Path(tempfile.mkdtemp(prefix="plenocl_batch_"))
    try:
        run_time_series(work / "A", pairs=6, queue=queue, log=lambda m: None,
                        progress=False)
        times = {}
        for label, kw in (("serial", {}), ("--workers 2", {"workers": 2})):
            out = work / label.strip("-").replace(" ", "")
            t0 = time.perf_counter()
            run(work / "A" / "experiment.toml", out, log=lambda m: None, progress=False, **kw)
            times[label] = time.perf_counter() - t0
        split = json.loads((work / "serial" / "summary.json").read_text())
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = ["| run (6 pairs, small camera) | wall s | pairs per hour |", "|---|---|---|"]
    out += [f"| {k} | {v:.1f} | {6 * 3600 / v:.0f} |" for k, v in times.items()]
    n = max(1, len(split["processed"]))
    out += ["", "| stage (serial) | s per pair |", "|---|---|"]
    out += [f"| {k} | {v / n:.2f} |" for k, v in split["stage_seconds"].items()]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat")
    parser.add_argument("--skip-piv", action="store_true")
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}\n")
    if not args.skip_piv:
        print("\n".join(piv_rows(1 if args.quick else 3, queue)) + "\n")
    print("\n".join(batch_rows(queue)))


if __name__ == "__main__":
    main()
