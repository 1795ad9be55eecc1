"""The particle refinement's per-window means (``plenocl.piv.refinement.window_means``,
docs/design.md §7.1), batched over the windows that hold the same number of pairs,
against the per-window loop over ``local_gradient``, ``near_median`` and
``window_estimate`` (``window_means_reference``) on the same pairs in the same run;
medians of repeated runs, and the largest differences of their results.

    python benchmarks/window_means.py [--pairs 5000] [--repeats 5] [--seed 1]

Case, of the paper's size: a 300 x 200 x 150 voxel volume, 32-voxel windows 8 voxels
apart (the final pass's 75 % overlap: 34 x 22 x 15 = 11,220 windows), pairs at uniform
random midpoints displaced by a smooth field (1-3.5 voxels, gradients up to 0.04) with
0.1 voxel of noise laterally and 0.5 in depth, 3 % of them outliers (up to 6 voxels
off), and the paper optics' focal zone (plane at depth 74.5, resolution 8.6 voxels).

Measured (2 CPU cores, another benchmark running beside it; medians of 5): 5,000 pairs
(17.7 per window, 133 per doubled window), seeds 1 and 2: loop 2.19 and 2.23 s, batched
0.41 and 0.41 s (5.4x, 5.5x); largest differences 3.6e-15 voxel in the means, 8.2e-16
and 1.2e-15 in the uncertainties, the same counts and refined windows. The batched cost
grows with the pairs per doubled window (medians of 3): 1,500 pairs 1.56 against 0.15 s
(10.5x, differences up to 1.0e-14), 20,000 pairs 4.46 against 1.86 s (2.4x).

With a device that has double precision, also ``window_means(..., device_means=...)``
(``kernels/windowmeans.cl``). Measured 2026-11-30 (2 cores, alone, medians of 5, seed 1):
loop 3.23 s, batched 0.59 s, device 0.14 s under Intel's CPU runtime (PoCL: 3.23, 0.60,
0.19 s; 0.23 and 0.31 s before the boxes' search moved to the device, with the loop at
4.7 s); the device's largest differences from the loop 3.6e-15 voxel in the means,
7.8e-16 in the uncertainties, the same counts and refined windows.
"""

from __future__ import annotations

import functools
import os

import numpy as np

from plenocl import get_queue
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.piv import PIVResult
from plenocl.piv.devicemeans import DeviceWindowMeans
from plenocl.piv.refinement import FocalZone, ParticlePairs, window_means  # noqa: E402
from plenocl.reference.refinement import window_means_reference

SHAPE = (150, 200, 300)  # (z, y, x) voxels
WINDOW, STEP = 32, 8


def flow(p: np.ndarray) -> np.ndarray:
    """A smooth displacement ``(..., 3)`` (voxels) at positions ``p`` ``(..., 3)`` ``(x, y,
    z)``: a shear in x, a slow swirl in y and z."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([2.0 + 1.5 * np.sin(y / 40.0),
                     0.5 * np.cos(x / 60.0) + 0.01 * (z - 75.0),
                     1.0 + 0.8 * np.sin(x / 50.0) * np.cos(y / 50.0)], axis=-1)


def paper_case(count: int, seed: int) -> tuple[ParticlePairs, PIVResult]:
    """``count`` pairs and the field grid of the paper's size (see the module docstring)."""
    z, y, x = (np.arange(WINDOW / 2 - 0.5, n - WINDOW / 2, STEP) for n in SHAPE)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    truth = flow(np.stack([xx, yy, zz], axis=-1))
    ones = np.ones(zz.shape, bool)
    field = PIVResult(x, y, z, truth[..., 0], truth[..., 1], truth[..., 2], ones,
                      np.full(zz.shape, np.nan), ~ones, ~ones, (WINDOW,) * 3)
    rng = np.random.default_rng(seed)
    mid = rng.uniform(0, SHAPE[::-1], (count, 3))
    disp = flow(mid) + rng.normal(0, [0.1, 0.1, 0.5], (count, 3))
    bad = rng.random(count) < 0.03
    disp[bad] += rng.uniform(-6.0, 6.0, (bad.sum(), 3))
    return ParticlePairs(mid, disp), field


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--pairs", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print(f"load average at start {os.getloadavg()[0]:.2f}")
    pairs, field = paper_case(args.pairs, args.seed)
    focus = FocalZone(plane=74.5, resolution=8.6)
    runs = {"loop": window_means_reference, "batched": window_means}
    queue = get_queue()
    if DeviceWindowMeans.supports(queue):
        runs["device"] = functools.partial(window_means,
                                           device_means=DeviceWindowMeans(queue))
        print(f"device: {queue.device.name.strip()}")
    out = {name: fn(pairs, field, focus=focus) for name, fn in runs.items()}
    times = {name: median_time(lambda fn=fn: fn(pairs, field, focus=focus), args.repeats,
                               warmup=False) for name, fn in runs.items()}
    print(f"{args.pairs} pairs, {field.u.size} windows ({field.u.shape}), "
          f"{out['loop'][2].mean():.1f} pairs per window; medians of {args.repeats}")
    for name, t in times.items():
        print(f"  {name:8s} {t:6.2f} s")
    for name in list(runs)[1:]:
        print(f"  {name} against the loop: {times['loop'] / times[name]:.1f}x")
        differences(out["loop"], out[name], name)
    print(f"load average at end {os.getloadavg()[0]:.2f}")


def differences(want, got, name: str) -> None:
    """Print the largest differences of one run's results from the loop's."""
    (mean, error, count), (mean_b, error_b, count_b) = want, got
    print(f"  {name}: largest difference: mean {np.nanmax(np.abs(mean_b - mean)):.1e}, "
          f"uncertainty {np.nanmax(np.abs(error_b - error)):.1e} voxel; "
          f"{np.count_nonzero(count_b != count)} counts and "
          f"{np.count_nonzero(np.isnan(mean_b[0]) != np.isnan(mean[0]))} refined windows "
          "differ")


if __name__ == "__main__":
    main()
