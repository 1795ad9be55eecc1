"""The image fit's cost against its accuracy: rays per particle and Gauss-Newton
iterations, on the same reconstructed volumes, in the same run.

    python benchmarks/image_fit.py [--seeding 0.02 0.05 0.1] [--lenses 96 64]
                                   [--variants default rays200 it4 rays200-it4]
                                   [--renderers numpy opencl-host opencl]
                                   [--repeat 3]

Scenes as ``benchmarks/accuracy.py`` (paper optics, ray-traced particles with blur and
noise, a uniform displacement and a rotation). Each scene is reconstructed and correlated
once with ``process_pair``'s defaults (``particles=False``); every variant then refines
the same field with the volumes' particles fitted to the raw images
(``refine_with_particles`` with an ``ImageFit``), once per renderer: ``numpy`` (the host's
``RayBundle``, float64), ``opencl-host`` (``DeviceRayBundle`` on the queue, float32, the
normal equations summed on the host: the previous path) and ``opencl`` (rendering and
sums on the device, ``DeviceFitSums``). Each run is repeated ``--repeat`` times, the
renderers taking turns, and timed by its median. Printed per variant and renderer: the
lateral and depth RMS error (voxels) of the valid vectors, and the seconds of the
particle stage (both exposures' fits and the pairing), medians over the scenes and the
RMS over them.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    ROTATION,
    UNIFORM,
    budget_errors,
    budget_scene,
    paper_setup,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402
from plenocl.piv.imagefit import ImageFit, ImageFitSettings  # noqa: E402
from plenocl.piv.refinement import FocalZone, SightLines, refine_with_particles  # noqa: E402

VARIANTS = {"default": ImageFitSettings(), "rays200": ImageFitSettings(rays=200),
            "it4": ImageFitSettings(iterations=4),
            "rays200-it4": ImageFitSettings(rays=200, iterations=4)}
#: The fit's renderers: the host's NumPy ``RayBundle`` or the device's kernel on the queue.
RENDERERS = {"numpy": (False, False), "opencl-host": (True, True), "opencl": (True, False)}


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeding", type=float, nargs="+", default=[0.02, 0.05, 0.1])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--renderers", nargs="+", default=list(RENDERERS), choices=RENDERERS)
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per fit (median)")
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    focus = FocalZone.of(cam, grid)
    runs = [(v, r) for v in args.variants for r in args.renderers]
    results = {run: [] for run in runs}
    for k, ppm in enumerate(args.seeding):
        for motion in (UNIFORM, ROTATION):
            scene = budget_scene(cam, grid, ppm, 1 + k, queue, motion=motion)
            pair = process_pair(scene.raw_a, scene.raw_b, proj, particles=False)
            timed = time_runs(runs, args.repeat, functools.partial(
                particle_stage, scene=scene, pair=pair, optics=(cam, grid, focus),
                queue=queue))
            for (name, renderer), (res, seconds) in timed.items():
                e = budget_errors(res, grid, motion)
                row = (e["lateral"], e["depth"], seconds)
                results[name, renderer].append(row)
                print(f"{ppm:5.2f} {motion.name:17s} {name:12s} {renderer:11s} lateral "
                      f"{row[0]:.3f} depth {row[1]:.3f} {row[2]:6.2f} s", flush=True)
    summary(results, len(args.seeding) * 2)


def particle_stage(run: tuple[str, str], scene, pair, optics: tuple, queue):
    """One run of the particle stage (``refine_with_particles`` with an ``ImageFit`` of
    ``run``'s variant and renderer); returns its result."""
    name, renderer = run
    cam, grid, focus = optics
    device, host_sums = RENDERERS[renderer]
    fit = ImageFit(cam, grid, (scene.raw_a, scene.raw_b), VARIANTS[name],
                   queue=queue if device else None, host_sums=host_sums)
    return refine_with_particles(pair.piv, pair.vol_a, pair.vol_b, focus=focus, fit=fit,
                                 sight=SightLines.of(cam, grid))


def time_runs(runs: list, repeat: int, call) -> dict:
    """``call(run)`` ``repeat`` times for every run, the runs taking turns (so a busy
    spell of a shared machine falls on all of them); per run its last result and the
    median seconds."""
    seconds = {run: [] for run in runs}
    out = {}
    for _ in range(max(repeat, 1)):
        for run in runs:
            t0 = time.perf_counter()
            out[run] = call(run)
            seconds[run].append(time.perf_counter() - t0)
    return {run: (out[run], float(np.median(seconds[run]))) for run in runs}


def summary(results: dict, scenes: int) -> None:
    """Per variant and renderer: RMS lateral and depth errors, median seconds."""
    print(f"\n{'variant':12s} {'render':11s} {'lateral':>8s} {'depth':>7s} {'s (median)':>10s}"
          f"  (RMS over {scenes} scenes)")
    for (name, renderer), rows in results.items():
        a = np.array(rows)
        print(f"{name:12s} {renderer:11s} {np.sqrt(np.mean(a[:, 0] ** 2)):8.3f} "
              f"{np.sqrt(np.mean(a[:, 1] ** 2)):7.3f} {np.median(a[:, 2]):10.2f}")


if __name__ == "__main__":
    main()
