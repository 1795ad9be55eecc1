"""The lens weights that integrate the voxel's extent against the paper's bilinear ones
(issue 47; ``Projector(lens_weights=...)``, docs/design.md §6.4): the default chain's
velocity error and recovery on the same ray-traced pairs.

    python benchmarks/lens_weights.py [--lenses 96 64] [--seeding 0.05] [--scenes 2]
                                      [--motion uniform rotation]

The error budget's scenes (``benchmarks/accuracy.py``: the paper's optics and voxel,
0.8 px blur, photon and read noise); per motion and scene, ``plenocl.process_pair``
defaults (coarse-to-fine MLEM on 3 x 3 sub-voxels, the particle refinement and the fit
to the raw images) with the paper's weights (the baseline) and with the extent weights,
on the same images in the same run: lateral and depth RMS error of the valid vectors
(voxels), depth in focus (|z| < 2 mm), particles recovered, ghost intensity and
seconds per pair; then the RMS over the scenes.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

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

MOTIONS = {"uniform": UNIFORM, "rotation": ROTATION}
WEIGHTS = ("paper", "extent")


def line(label: str, row: dict) -> str:
    """One printed row of :func:`plenocl.bench.accuracy_section.pair_row`'s figures."""
    e = row["errors"]
    return (f"{label:18s} {e['lateral']:8.3f} {e['depth']:7.3f} {e['in focus']:7.3f} "
            f"{100 * row['recovered']:6.0f}% {100 * row['ghosts']:6.0f}% "
            f"{row['seconds']:7.1f}")


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--motion", nargs="+", choices=list(MOTIONS),
                        default=list(MOTIONS))
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    projectors = {w: proj.weighted(w) for w in ("paper", "extent")}
    head = f"{'weights':18s} {'lateral':>8s} {'depth':>7s} {'focus':>7s} {'recov':>7s} " \
           f"{'ghosts':>7s} {'s/pair':>7s}"
    for name in args.motion:
        motion = MOTIONS[name]
        print(f"\n{name}, {args.seeding:g} particles per microlens")
        rows = {w: [] for w in WEIGHTS}
        for seed in range(1, args.scenes + 1):
            scene = budget_scene(cam, grid, args.seeding, seed, queue, motion=motion)
            print(f"scene {seed}, {scene.count} particles\n{head}")
            for w in WEIGHTS:
                pair = process_pair(scene.raw_a, scene.raw_b, projectors[w])
                rows[w].append(pair_row(pair, scene, grid, motion))
                print(line(w, rows[w][-1]), flush=True)
        print(f"RMS over the {args.scenes} scenes\n{head}")
        for w in WEIGHTS:
            errs = [r["errors"] for r in rows[w]]
            rms = {k: float(np.sqrt(np.mean([e[k] ** 2 for e in errs])))
                   for k in ("lateral", "depth", "in focus")}
            mean = {k: float(np.mean([r[k] for r in rows[w]]))
                    for k in ("recovered", "ghosts", "seconds")}
            print(line(w, {"errors": rms, **mean}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
