"""Throughput of a batch run and of its PIV stage (issue 16).

Run from the repository root::

    python benchmarks/batch.py            # PIV at paper size (3 repeats) + batch (6 pairs)
    python benchmarks/batch.py --quick    # 1 repeat

1. **PIV at the paper's grid** (150 x 200 x 300 voxels): ``piv3d`` with default settings
   on a synthetic volume pair (Gaussian particles, sigma 1.5 voxels, 0.0004 per voxel,
   a uniform shift of (2.31, -1.47, 0.68) voxels, noise 0.02), the reference path
   (SciPy deformation on the host, SciPy pocketfft, every pass by FFT: the path before
   issue 16) against the FFT path with deformation on the OpenCL device and FFTW, and
   the default of ``process_pair`` (deformed passes correlated directly at the lags
   around zero, ``plenocl.piv.direct``), same volumes, same process: median seconds and
   RMS error.
2. **Pairs per hour**: the time-series demo's experiment (``plenocl demo time-series``,
   small camera, 6 pairs) processed serially and with ``--workers 2`` (a local Dask
   cluster), same machine, same run, each from an empty output folder; the stage split
   per pair from the serial run's ``summary.json``.
3. **Warm start**: the second exposure reconstructed from the first's volume against
   the default uniform start (Q, recovery, time), one pair of the small experiment.
4. **Stage split at the paper's size** (not with ``--quick``): the same experiment with
   the paper's 16 MP camera and 300 x 200 x 150 voxel grid, 2 pairs, serially.
"""

from __future__ import annotations

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
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.demo.time_series import run_time_series  # noqa: E402

SHIFT = (2.31, -1.47, 0.68)


def piv_rows(repeats: int, queue) -> list[str]:
    """Reference against default PIV at the paper's grid."""
    pair = flows.volume_pair((150, 200, 300), flows.Uniform(SHIFT), density=0.0004,
                             sigma=1.5, seed=1, noise=0.02)
    rows = []
    for label, kw in (("reference: SciPy deform + pocketfft, every pass by FFT",
                       {"fft": "scipy", "correlation": "fft", "queue": False}),
                      ("device deform + FFTW, every pass by FFT",
                       {"queue": queue, "correlation": "fft"}),
                      ("default: device deform, deformed passes direct",
                       {"queue": queue})):
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


def warm_start_rows(queue) -> list[str]:
    """Reconstructing the second exposure from the first's volume (issue 16: "start each
    reconstruction from the previous frame's where that measurably pays") against the
    default uniform start, on one pair of the time-series demo's experiment (small
    camera, ideal calibration): Q against the true particles, particles recovered, time.
    The start is the first volume blurred by one voxel plus 10 % of its mean, so that
    particles that moved are not pinned to the first volume's zeros."""
    from scipy import ndimage

    from plenocl import Projector, reconstruct
    from plenocl.demo.boundary_layer import (
        CameraFrameFlow,
        scenario,
        seed_particles,
        sensor_options,
    )
    from plenocl.metrics import quality_q, recovery, render_particles
    from plenocl.simulate import simulate_image

    sc = scenario("small")
    cam, grid = sc.physical_camera, sc.grid
    pos_a, pos_b, inten = seed_particles(sc, CameraFrameFlow(sc, 0), 1000)
    raw_a, raw_b = (simulate_image(cam, p, inten, sc.rays, queue=queue,
                                   **sensor_options(j)) for j, p in enumerate((pos_a, pos_b)))
    proj = Projector(cam, grid, queue)
    vol_a = reconstruct(raw_a, proj, supersample=1)
    start = ndimage.gaussian_filter(vol_a, 1.0) + 0.1 * float(vol_a.mean())
    truth = render_particles(grid, pos_b, inten, sigma_vox=1.0)
    out = ["| second exposure | iterations | s | Q | recovered |", "|---|---|---|---|---|"]
    for label, its, kw in (("uniform start (default)", sc.iterations, {}),
                           ("from the first volume", 10, {"start": start}),
                           ("from the first volume", 20, {"start": start}),
                           ("from the first volume", sc.iterations, {"start": start})):
        vol, seconds = timed(lambda its=its, kw=kw: reconstruct(raw_b, proj, "mlem", its,
                                                                supersample=1, **kw), 3)
        rep = recovery(vol, grid, pos_b)
        out.append(f"| {label} | {its} | {seconds:.2f} | {quality_q(vol, truth):.3f} | "
                   f"{rep.fraction:.0%} |")
    return out


def paper_rows(queue) -> list[str]:
    """Stage split per pair at the paper's size (16 MP, 300 x 200 x 150 voxels): the
    time-series demo's experiment at ``size="paper"``, 2 pairs, processed serially."""
    work = Path(tempfile.mkdtemp(prefix="plenocl_paper_"))
    try:
        t0 = time.perf_counter()
        doc = run_time_series(work, pairs=2, queue=queue, log=lambda m: None,
                              progress=False, size="paper")
        total = time.perf_counter() - t0
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = [f"paper size, 2 pairs: {doc['seconds_per_pair']:.1f} s per pair "
           f"({3600 / doc['seconds_per_pair']:.0f} pairs per hour) on one process; "
           f"{total:.0f} s with writing the white image and raw pairs",
           "", "| stage (paper size) | s per pair |", "|---|---|"]
    out += [f"| {k} | {v:.1f} |" for k, v in doc["stage_seconds_per_pair"].items()]
    return out


def main() -> None:
    parser = script_parser(__doc__, {"piv": None, "batch": None,
                                     "paper": "skip the stage split at paper size (minutes)"})
    parser.add_argument("--quick", action="store_true", help="1 repeat")
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}\n")
    if not args.skip_piv:
        print("\n".join(piv_rows(1 if args.quick else 3, queue)) + "\n")
    if not args.skip_batch:
        print("\n".join(batch_rows(queue)) + "\n")
        print("\n".join(warm_start_rows(queue)) + "\n")
    if not (args.skip_paper or args.quick):
        print("\n".join(paper_rows(queue)))


if __name__ == "__main__":
    main()
