"""The reconstruction's iteration schedule against the pair's errors (issue 28): coarse
voxel iterations, fine sub-voxel iterations and MLEM's relaxation, every schedule on the
same scenes in the same run, beside the default.

    python benchmarks/schedules.py [--schedules 10+10+1 5+7+1.5] [--seeds 3 103]
                                   [--lenses 96 64] [--seeding 0.05]

A schedule ``C+F+MU`` is ``C`` MLEM iterations on the voxels, then ``F`` on 3 x 3
lateral sub-voxels within the coarse support (1 % of the brightest voxel, grown by one),
both at relaxation ``MU`` (``E ← E (Wᵀ r / s)^MU``; ``MU > 1`` over-relaxes);
options after commas: ``co=CO`` runs the coarse iterations on the aperture sampled
``CO`` times per pixel footprint (default 0.625), ``o=O`` the projector (the fine
iterations) at ``O`` (default 1.25), ``e=E@EO`` the first ``E`` fine iterations at
``EO`` (default none: ``e=3@0.9`` is the default reconstruction's). Camera and
scenes as ``benchmarks/accuracy.py``: the paper's optics on ``--lenses`` microlenses,
the paper's voxel, ray-traced particles with 0.8 px blur, photon and read noise, a
uniform displacement and a rotation about x. Each schedule runs ``plenocl.process_pair``
(its other defaults: the particle refinement with the fit to the raw images) on the
same two raw images; per scene the lateral and depth RMS error of the valid vectors
(voxels), the particles the first volume recovered and the pair's seconds; then per
schedule the RMS over all scenes and the median seconds.

Measured (2026-11-26, PoCL, 2 cores, 96 x 64 lenses, seeds 3 and 103, both motions;
timings noisy, other work ran beside): 10 + 10 at μ = 1 (the default before) 0.038 /
0.369 voxel, 70 % recovered; 5 + 7 at μ = 1.5 (the default until 2026-11-26
evening) 0.038 / 0.368, 70 %; 5 + 10 at μ = 1 0.041 / 0.374; 10 + 5 at μ = 1
0.038 / 0.450, 56 %; 5 + 5 at μ = 2 0.060 / 0.546, 36 % (over-relaxation beyond 1.5
oscillates). With the samplings
(2026-11-26 evening, same scenes, one run): 5 + 7 at μ = 1.5, e=3@0.9 0.038 / 0.369,
71 %; 4 + 7 (the default now) 0.039 / 0.368, 71 %; e=3@0.75 0.040 / 0.381; e=4@0.9
0.039 / 0.381.
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
    budget_scene,
    pair_row,
    paper_setup,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402
from plenocl.projection import Projector  # noqa: E402
from plenocl.reconstruction import ReconstructionSettings  # noqa: E402
from plenocl.reconstruction.settings import (  # noqa: E402
    COARSE_OVERSAMPLE,
    EARLY_OVERSAMPLE,
)


def schedule(spec: str) -> tuple[ReconstructionSettings, float | None]:
    """``"C+F+MU[,co=CO][,o=O][,e=E@EO]"`` as the pair's reconstruction settings and the
    projector's aperture sampling ``O`` (``None``: the default projector)."""
    steps, *options = spec.split(",")
    coarse, fine, relax = steps.split("+")
    given = dict(option.split("=") for option in options)
    early, _, early_over = given.get("e", f"0@{EARLY_OVERSAMPLE}").partition("@")
    settings = ReconstructionSettings(
        supersample=3, coarse_iterations=int(coarse), iterations=int(fine),
        relax=float(relax), support=0.01,
        coarse_oversample=float(given.get("co", COARSE_OVERSAMPLE)),
        early_iterations=int(early), early_oversample=float(early_over))
    return settings, float(given["o"]) if "o" in given else None


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--schedules", nargs="+", default=["10+10+1,co=1.25", "4+7+1.5,e=3@0.9"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[3, 103])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--seeding", type=float, default=0.05)
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    projectors: dict[float, Projector] = {}  # other aperture samplings, built once
    rows: dict[str, list] = {spec: [] for spec in args.schedules}
    for motion in (UNIFORM, ROTATION):
        for seed in args.seeds:
            scene = budget_scene(cam, grid, args.seeding, seed, queue, motion=motion)
            for spec in args.schedules:
                settings, over = schedule(spec)
                if over is not None and over not in projectors:
                    projectors[over] = Projector(cam, grid, queue, oversample=over)
                t0 = time.perf_counter()
                pair = process_pair(scene.raw_a, scene.raw_b, projectors.get(over, proj),
                                    reconstruction=settings)
                seconds = time.perf_counter() - t0
                row = pair_row(pair, scene, grid, motion)
                e = row["errors"]
                rows[spec].append((e["lateral"], e["depth"], row["recovered"], seconds))
                print(f"{motion.name:18s} seed {seed:4d} {spec:9s} lateral "
                      f"{e['lateral']:.3f} depth {e['depth']:.3f} recovered "
                      f"{row['recovered']:.0%} {seconds:6.1f} s", flush=True)
    for spec, values in rows.items():
        a = np.array(values)
        print(f"{spec:9s} RMS lateral {np.sqrt(np.mean(a[:, 0] ** 2)):.3f} depth "
              f"{np.sqrt(np.mean(a[:, 1] ** 2)):.3f} recovered {a[:, 2].mean():.0%} "
              f"median {np.median(a[:, 3]):.1f} s per pair")


if __name__ == "__main__":
    main()
