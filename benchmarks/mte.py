"""Motion-tracking enhancement (MTE) against single-frame reconstruction, on the same
scenes in the same run (issue 15, item 2). Both on ``process_pair``'s reconstruction (3 x 3
lateral sub-voxels) and particle refinement.

    python benchmarks/mte.py [--seeding 0.02 0.05 0.1] [--scenes 1] [--lenses 96 64]

The error-budget case of ``benchmarks/accuracy.py``: the paper's optics and voxel, a
uniform displacement of (2.3, -1.4, 1.7) voxels, ray-traced raw images with 0.8 px blur
and noise. For each scene: ``process_pair`` single frame (MLEM 30 iterations, then
``piv3d``), then MTE cycles continued from it (each cycle: the smoothed field warps each
volume onto the other exposure's time, the two are combined, each image reconstructed
again for 10 MLEM iterations from that guess, and correlated). Printed per row: RMS
error of the valid vectors (lateral, depth, depth by zone), valid fraction, the share of
errors within one estimated sigma (the per-vector uncertainty), Q, particles recovered,
ghost intensity, and seconds per pair (both reconstructions and every correlation).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import get_queue, piv3d  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    SHIFT_VOX,
    budget_errors,
    budget_scene,
    paper_setup,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.metrics import quality_q, recovery  # noqa: E402
from plenocl.pipeline import MTESettings, motion_tracking_enhancement, process_pair  # noqa: E402
from plenocl.piv.refinement import refine_with_particles  # noqa: E402
from plenocl.reconstruction import ReconstructionSettings  # noqa: E402

VARIANTS = {"geometric": MTESettings(cycles=1), "mean": MTESettings(cycles=1, combine="mean"),
            "min": MTESettings(cycles=1, combine="min")}


def coverage(res) -> float:
    """Share of the valid vectors' component errors within one estimated sigma."""
    ok = res.valid
    inside = [np.abs(getattr(res, c)[ok] - s) <= getattr(res, f"sigma_{c}")[ok]
              for c, s in zip("uvw", SHIFT_VOX)]
    return float(np.mean(np.concatenate(inside)))


def row(label: str, scene, grid, vol_a, res, seconds: float) -> dict:
    e, rep = budget_errors(res, grid), recovery(vol_a, grid, scene.pa)
    return {"label": label, **e, "coverage": coverage(res),
            "Q": quality_q(vol_a, scene.true_a), "recovered": rep.fraction,
            "ghosts": rep.ghost_fraction, "seconds": seconds}


def run_scene(scene, proj, grid, cycles: int, variants: list[str]) -> list[dict]:
    """Single frame (``process_pair`` defaults without MTE), then each variant's cycles
    continued from its correlation; every row's field refined by the particle pairs, as
    ``process_pair`` does after the last cycle."""
    pair = process_pair(scene.raw_a, scene.raw_b, proj, mte=MTESettings(cycles=0),
                        particles=False)
    t_single = sum(pair.seconds.values())
    rows = [row("single frame", scene, grid, pair.vol_a,
                refine_with_particles(pair.piv, pair.vol_a, pair.vol_b), t_single)]
    for name in variants:
        a, b, res, total = pair.vol_a, pair.vol_b, pair.piv, t_single
        for c in range(cycles):
            a, b, res, _, sec = motion_tracking_enhancement(
                scene.raw_a, scene.raw_b, proj, a, b, res, ReconstructionSettings(),
                VARIANTS[name], lambda x, y: piv3d(x, y, queue=proj.queue))
            total += sec
            rows.append(row(f"MTE {name}, {c + 1} cycle{'s' * (c > 0)}", scene, grid, a,
                            refine_with_particles(res, a, b), total))
    return rows


def print_rows(rows: list[dict]) -> None:
    print(f"  {'':28s} {'lateral':>7s} {'depth':>6s} {'focus':>6s} {'near':>6s} "
          f"{'far':>6s} {'valid':>6s} {'in 1σ':>6s} {'Q':>6s} {'recov':>6s} {'ghosts':>6s} "
          f"{'s/pair':>7s}")
    for r in rows:
        print(f"  {r['label']:28s} {r['lateral']:7.3f} {r['depth']:6.2f} {r['in focus']:6.2f} "
              f"{r['near']:6.2f} {r['far']:6.2f} {r['valid']:6.0%} {r['coverage']:6.0%} "
              f"{r['Q']:6.3f} {r['recovered']:6.0%} {r['ghosts']:6.0%} {r['seconds']:7.1f}",
              flush=True)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeding", type=float, nargs="+", default=[0.02, 0.05, 0.1])
    parser.add_argument("--scenes", type=int, default=1)
    parser.add_argument("--cycles", type=int, default=2)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    print("RMS displacement error in voxels over the valid vectors")
    for ppm in args.seeding:
        for k in range(args.scenes):
            scene = budget_scene(cam, grid, ppm, seed=100 + k, queue=queue)
            print(f"seeding {ppm} particles per lens ({scene.count}), scene {k + 1}")
            print_rows(run_scene(scene, proj, grid, args.cycles, args.variants))


if __name__ == "__main__":
    main()
