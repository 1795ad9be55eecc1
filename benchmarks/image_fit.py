"""The image fit's cost against its accuracy: rays per particle and Gauss-Newton
iterations, on the same reconstructed volumes, in the same run.

    python benchmarks/image_fit.py [--seeding 0.02 0.05 0.1] [--lenses 96 64]
                                   [--variants default rays200 it4 rays200-it4]

Scenes as ``benchmarks/accuracy.py`` (paper optics, ray-traced particles with blur and
noise, a uniform displacement and a rotation). Each scene is reconstructed and correlated
once with ``process_pair``'s defaults (``particles=False``); every variant then refines
the same field with the volumes' particles fitted to the raw images
(``refine_with_particles`` with an ``ImageFit``). Printed per variant: the lateral and
depth RMS error (voxels) of the valid vectors, and the seconds of the particle stage
(both exposures' fits and the pairing), medians over the scenes and the RMS over them.
"""

from __future__ import annotations

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
from plenocl.piv.tracking import FocalZone, refine_with_particles  # noqa: E402

VARIANTS = {"default": ImageFitSettings(), "rays200": ImageFitSettings(rays=200),
            "it4": ImageFitSettings(iterations=4),
            "rays200-it4": ImageFitSettings(rays=200, iterations=4)}


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeding", type=float, nargs="+", default=[0.02, 0.05, 0.1])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    focus = FocalZone.of(cam, grid)
    results = {v: [] for v in args.variants}
    for k, ppm in enumerate(args.seeding):
        for motion in (UNIFORM, ROTATION):
            scene = budget_scene(cam, grid, ppm, 1 + k, queue, motion=motion)
            pair = process_pair(scene.raw_a, scene.raw_b, proj, particles=False)
            for name in args.variants:
                fit = ImageFit(cam, grid, (scene.raw_a, scene.raw_b), VARIANTS[name])
                t0 = time.perf_counter()
                res = refine_with_particles(pair.piv, pair.vol_a, pair.vol_b, focus=focus,
                                            fit=fit)
                e = budget_errors(res, grid, motion)
                results[name].append((e["lateral"], e["depth"], time.perf_counter() - t0))
                print(f"{ppm:5.2f} {motion.name:17s} {name:12s} lateral {e['lateral']:.3f} "
                      f"depth {e['depth']:.3f} {results[name][-1][2]:6.1f} s", flush=True)
    print(f"\n{'variant':12s} {'lateral':>8s} {'depth':>7s} {'s (median)':>10s}  (RMS over "
          f"{len(args.seeding) * 2} scenes)")
    for name, rows in results.items():
        a = np.array(rows)
        print(f"{name:12s} {np.sqrt(np.mean(a[:, 0] ** 2)):8.3f} "
              f"{np.sqrt(np.mean(a[:, 1] ** 2)):7.3f} {np.median(a[:, 2]):10.1f}")


if __name__ == "__main__":
    main()
