"""Where the velocity error comes from, at the paper's optics and voxel size: the error
budget of issue 15, lateral and depth separately, as a function of seeding and depth.

    python benchmarks/accuracy.py [--seeding 0.01 0.02 0.05 0.1 0.2] [--lenses 96 64]

Camera: the paper's optics (f = 50 mm, f/2.42, |M| = 0.66, 125 µm microlenses of
f = 500 µm, 7.4 µm pixels, about 17 px per lens) on a window of ``--lenses`` microlenses
(the full sensor has 289 x 193: the depth physics is the same, the run 9x shorter). Grid:
the paper's voxel, 0.183 x 0.175 x 0.133 mm, over 20 mm of depth (150 voxels). Flow: a
uniform displacement of (2.3, -1.4, 1.7) voxels. Images: exact ray tracing, 0.8 px
particle blur, photon noise, a dark level with read noise.

For each seeding (particles per microlens), in the same run:

- **windows**: PIV on volumes rendered from the true particles (Gaussian blobs of
  1 voxel): what the interrogation windows themselves cannot resolve;
- **reconstruction**: PIV on volumes reconstructed from the raw images with
  ``plenocl.process_pair`` defaults (MLEM 30 iterations, median background, windows
  fitted to the volume and its particle count): what the user gets;
- **48-32-24**: the same reconstructed volumes with the fixed schedule the default
  replaced (the baseline of the window choice);
- reconstruction quality: Q against the true-rendered volume, particles recovered, ghost
  intensity fraction.

Errors are RMS over the valid vectors against the imposed displacement (uniform: the
window-averaged and the point-sampled truth coincide), in voxels and mm; lateral is the
RMS over x and y. By depth: in focus (|z| < 2 mm, within about 2 depth resolutions of
the focal plane), near (z < -2 mm) and far (z > 2 mm).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Projector, get_queue  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    budget_errors,
    budget_row,
    paper_optics,
)
from plenocl.piv import piv3d  # noqa: E402


def print_rows(rows: list[dict], grid) -> None:
    dz = grid.spacing[0]
    print(f"{'ppm':>5s} {'n':>5s} | {'windows only: lat':>17s} {'depth':>6s} | "
          f"{'reconstructed: lat':>18s} {'depth':>6s} {'(mm)':>6s} {'focus':>6s} "
          f"{'near':>6s} {'far':>6s} {'valid':>6s} {'final window':>13s} | "
          f"{'48-32-24: lat':>13s} {'depth':>6s} | {'Q':>5s} {'recov':>6s} {'ghosts':>6s}")
    for r in rows:
        w, e, f = r["windows"], r["reconstruction"], r["fixed"]
        print(f"{r['ppm']:5.2f} {r['particles']:5d} | {w['lateral']:17.3f} {w['depth']:6.3f} | "
              f"{e['lateral']:18.3f} {e['depth']:6.2f} {e['depth'] * dz:6.3f} "
              f"{e['in focus']:6.2f} {e['near']:6.2f} {e['far']:6.2f} {e['valid']:6.0%} "
              f"{str(r['final_window']):>13s} | {f['lateral']:13.3f} {f['depth']:6.2f} | "
              f"{r['Q']:5.2f} {r['recovered']:6.0%} {r['ghosts']:6.0%}")
    print("bias of the reconstructed field (voxels, x y z):",
          "; ".join(f"{r['ppm']:.2f}: " + " ".join(f"{b:+.2f}" for b in r["reconstruction"]
                                                 ["bias"]) for r in rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeding", type=float, nargs="+",
                        default=[0.01, 0.02, 0.05, 0.1, 0.2])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    args = parser.parse_args()
    queue = get_queue()
    cam, grid = paper_optics(tuple(args.lenses))
    proj = Projector(cam, grid, queue)
    print(f"device: {queue.device.name.strip()}; load average {os.getloadavg()[0]:.2f}")
    print(f"camera: {cam.describe()}; {cam.pixels[0]} x {cam.pixels[1]} px")
    print(f"grid {grid.shape} (z, y, x), voxel {grid.spacing[2]:.4f} x {grid.spacing[1]:.4f}"
          f" x {grid.spacing[0]:.4f} mm; displacement [2.3, -1.4, 1.7] voxels (x, y, z)")
    print("RMS displacement error (voxels unless stated) over the valid vectors:")
    rows = []
    for k, ppm in enumerate(args.seeding):
        row = budget_row(cam, grid, proj, ppm, seed=k + 1, queue=queue)
        pair = row.pop("pair")
        row["fixed"] = budget_errors(piv3d(pair.vol_a, pair.vol_b, windows=(48, 32, 24)), grid)
        rows.append(row)
        print(f"  seeding {ppm}: " + ", ".join(f"{k} {v:.1f} s" for k, v in
                                               row["seconds"].items()), flush=True)
    print_rows(rows, grid)


if __name__ == "__main__":
    main()
