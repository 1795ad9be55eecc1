"""PIV's FFT correlation on the OpenCL device against the host's, in the same process.

    python benchmarks/fft_correlation.py [--repeats 5] [--shape 150 81 115]

Volumes: Gaussian particles (sigma 1 voxel, 0.004 per voxel) moved by (1.3, -0.7, 2.1)
voxels, of the 116 x 78 pair's grid by default (``--shape``, z y x; the paper's 16 MP
grid is 150 200 286). Each row times, medians of ``--repeats`` calls after one warm-up
each, ``DeviceCorrelation.correlate`` (``kernels/fftcorr.cl``) against the host's
``correlate`` (FFTW where pyfftw is installed), with the largest displacement difference:

* the first pass: every window of 48 voxels at overlap 0.5, zero-padded to 64, from host
  volumes (the device path uploads them, as ``piv3d``'s first pass does);
* a deformed pass's FFT windows: 1, 4, 30 and 200 of the 32-voxel windows at overlap
  0.75 with the Gaussian weight, from volumes on the device (the deformed volumes stay
  there: the host path gathers the windows on the device and takes only them).

Then what ``FFTRoute`` (``fft=None``, ``piv3d``'s default) chose for each, measured on the
first call (in this process alone, as every benchmark: ``bench.scripts.script_parser``
keeps no route on the machine). Measured (2 CPU cores, 2026-11-30): see docs/design.md §7.5.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from plenocl import flows, get_queue  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.piv.correlation import correlate, gaussian_weight, window_grid  # noqa: E402
from plenocl.piv.devicefft import DeviceCorrelation, FFTRoute, measured_routes  # noqa: E402


def compare(label: str, device, host, repeats: int) -> None:
    """Both calls warmed once, then timed; the medians and the largest difference."""
    device(), host()
    got, t_device = timed(device, repeats)
    want, t_host = timed(host, repeats)
    diff = float(np.abs(got.displacement - want.displacement)[:, want.signal].max(initial=0))
    print(f"{label:40s} device {t_device:7.4f} s  host {t_host:7.4f} s  "
          f"({t_host / t_device:4.2f}x)  largest difference {diff:.1e} voxel", flush=True)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--shape", type=int, nargs=3, default=(150, 81, 115))
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}; load average {os.getloadavg()[0]:.2f}; "
          f"medians of {args.repeats}")
    shape = tuple(args.shape)
    pair = flows.volume_pair(shape, flows.Uniform((1.3, -0.7, 2.1)), density=0.004,
                             sigma=1.0, seed=1)
    a, b = pair.vol_a, pair.vol_b
    engine = DeviceCorrelation(queue)
    first = window_grid(shape, (48, 48, 48), 0.5)
    compare(f"first pass, {int(np.prod(first.count))} windows 48 -> 64",
            lambda: engine.correlate(a, b, first, pad=True),
            lambda: correlate(a, b, first, pad=True), args.repeats)
    da, db = engine.upload(a), engine.upload(b)
    grid, weight = window_grid(shape, (32, 32, 32), 0.75), gaussian_weight((32,) * 3, 0.35)
    route = FFTRoute("fftw", queue)
    rng = np.random.default_rng(0)
    for count in (1, 4, 30, 200):
        select = np.zeros(grid.count, bool)
        select.flat[rng.choice(select.size, count, replace=False)] = True
        options = {"weight": weight, "select": select}
        compare(f"deformed pass, {count} windows of 32",
                lambda options=options: engine.correlate(da, db, grid, **options),
                lambda options=options: route.correlate(da, db, grid, **options),
                args.repeats)
    measured = FFTRoute(None, queue)
    measured.correlate(a, b, first, pad=True)
    measured.correlate(da, db, grid, weight=weight, select=select)
    for (_, box, resident, pad), (chosen, host_s, device_s) in measured_routes().items():
        padded = " (padded)" if pad else ""
        print(f"route for {box}{padded} from {resident} volumes: {chosen} (host {host_s:.4f} s, "
              f"device {device_s:.4f} s)")


if __name__ == "__main__":
    main()
