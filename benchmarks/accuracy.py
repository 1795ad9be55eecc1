"""Where the velocity error comes from, at the paper's optics and voxel size: the error
budget of issue 15, lateral and depth separately, as a function of seeding and depth.

    python benchmarks/accuracy.py [--seeding 0.01 0.02 0.05 0.1 0.2] [--lenses 96 64]
                                  [--motion uniform rotation] [--scenes 1]
                                  [--layout rectangular hexagonal]

Camera: the paper's optics (f = 50 mm, f/2.42, |M| = 0.66, 125 µm microlenses of
f = 500 µm, 7.4 µm pixels, about 17 px per lens) on a window of ``--lenses`` microlenses
(the full sensor has 289 x 193: the depth physics is the same, the run 9x shorter);
``--layout hexagonal``: a hexagonal array of the same pitch on the same sensor (issue
29), every layout given measured in the same run on the same grid. Grid:
the paper's voxel, 0.183 x 0.175 x 0.133 mm, over 20 mm of depth (150 voxels). Motions:
a uniform displacement of (2.3, -1.4, 1.7) voxels, and a solid-body rotation of 2 degrees
about the lateral x axis through the volume's centre (particles move in y and in depth,
up to about 2 voxels). Images: exact ray tracing, 0.8 px particle blur, photon noise, a
dark level with read noise.

For each motion, seeding (particles per microlens) and scene, in the same run:

- **windows only**: PIV on volumes rendered from the true particles (Gaussian blobs of
  1 voxel): what the interrogation windows themselves cannot resolve;
- **default**: ``plenocl.process_pair`` defaults (MLEM coarse-to-fine: 4 iterations on
  the voxels, then 7 over-relaxed ones on 3 x 3 lateral sub-voxels per voxel within the
  coarse support, summed back, docs/design.md §6.5; windows fitted to the volume; each
  window's vector refined by its matched particle pairs, fitted to the raw images): what
  the user gets;
- **30 sub-voxel iterations**: the default before (``--before``, 30 MLEM iterations on
  the sub-voxels from a uniform start), same images, with its seconds per pair;
- **sub-voxels, correlation only**: the default's volumes correlated without the
  particle refinement (``process_pair(particles=False)``): what the refinement adds;
- **before**: the same images reconstructed on the voxels themselves
  (``supersample=1``) and correlated, without the refinement: the chain before
  (the baseline);
- reconstruction quality: Q against the true-rendered volume, particles recovered, ghost
  intensity fraction, and seconds per pair (both reconstructions and the correlation).

Errors are RMS over the valid vectors against the true displacement at the window
centres (both motions are linear in space, so the window-averaged and the point-sampled
truth coincide), in voxels and mm; lateral is the RMS over x and y. By depth: in focus
(|z| < 2 mm, within about 2 depth resolutions of the focal plane), near (z < -2 mm) and
far (z > 2 mm). With ``--scenes N`` each seeding runs N scenes and the RMS over them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    ROTATION,
    ROWS,
    UNIFORM,
    budget_entries,
    budget_row,
    paper_setup,
)
from plenocl.bench.scripts import script_parser  # noqa: E402

MOTIONS = {"uniform": UNIFORM, "rotation": ROTATION}


def print_rows(rows: list[dict], grid) -> None:
    dz = grid.spacing[0]
    print(f"{'ppm':>5s} {'n':>5s} | {'windows only: lat':>17s} {'depth':>6s} | {'':28s} "
          f"{'lateral':>7s} {'depth':>6s} {'(mm)':>6s} {'focus':>6s} {'near':>6s} "
          f"{'far':>6s} {'valid':>6s} {'bias x y z':>17s} | {'Q':>5s} {'recov':>6s} "
          f"{'ghosts':>6s} {'s/pair':>7s}")
    for r, w, name, x, e in budget_entries(rows):
        print(f"{r['ppm']:5.2f} {r['particles']:5d} | {w['lateral']:17.3f} "
              f"{w['depth']:6.3f} | {name:28s} {e['lateral']:7.3f} {e['depth']:6.2f} "
              f"{e['depth'] * dz:6.3f} {e['in focus']:6.2f} {e['near']:6.2f} "
              f"{e['far']:6.2f} {e['valid']:6.0%} "
              f"{' '.join(f'{b:+.2f}' for b in e['bias']):>17s} | {x['Q']:5.2f} "
              f"{x['recovered']:6.0%} {x['ghosts']:6.0%} {x['seconds']:7.1f}", flush=True)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeding", type=float, nargs="+",
                        default=[0.01, 0.02, 0.05, 0.1, 0.2])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--motion", nargs="+", default=list(MOTIONS), choices=MOTIONS)
    parser.add_argument("--scenes", type=int, default=1)
    parser.add_argument("--before", action="store_true",
                        help="also the chain with 30 MLEM iterations on the sub-voxels")
    parser.add_argument("--layout", nargs="+", default=["rectangular"],
                        choices=["rectangular", "hexagonal"])
    args = parser.parse_args()
    queue = get_queue()
    for layout in args.layout:
        cam, grid, proj = paper_setup(tuple(args.lenses), queue, layout)
        run_layout(args, cam, grid, proj, queue)


def run_layout(args, cam, grid, proj, queue) -> None:
    """Every motion and seeding of ``args`` on one camera."""
    for name in args.motion:
        print(f"\n{MOTIONS[name].name}, {cam.ml_layout} array: RMS displacement error "
              "(voxels unless stated) over the valid vectors")
        rows = []
        for k, ppm in enumerate(args.seeding):
            for scene in range(args.scenes):
                row = budget_row(cam, grid, proj, ppm, seed=1 + k + 100 * scene, queue=queue,
                                 motion=MOTIONS[name], previous=args.before)
                row.pop("pair")
                rows.append(row)
                if args.scenes == 1:
                    print_rows([row], grid)
        if args.scenes > 1:
            print_rows(rows, grid)
            print_pooled(rows)


def print_pooled(rows: list[dict]) -> None:
    """RMS over the scenes of each seeding, default against before."""
    for ppm in sorted({r["ppm"] for r in rows}):
        sel = [r for r in rows if r["ppm"] == ppm]
        out = []
        for label in (k for k in ROWS if k in sel[0]):
            lat = np.sqrt(np.mean([r[label]["errors"]["lateral"] ** 2 for r in sel]))
            dep = np.sqrt(np.mean([r[label]["errors"]["depth"] ** 2 for r in sel]))
            out.append(f"{label} lateral {lat:.3f} depth {dep:.2f}")
        print(f"  {ppm:.2f} over {len(sel)} scenes: " + "; ".join(out))


if __name__ == "__main__":
    main()
