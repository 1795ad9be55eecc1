"""A user's grid on a rotated microlens array: ``process_pair`` on a grid in the sensor's
axes (projected through the lens-row frame and resampled, docs/design.md §5.1), beside
the lens-row grid of ``Grid.for_camera`` and (``--exact``) the general kernels, on the
same ray-traced images in the same run.

    python benchmarks/rotated_grid.py [--rotation 0.15] [--lenses 96 64] [--seeds 1 2]
                                      [--seeding 0.05] [--exact]

Camera: the paper's optics (``paper_optics``) with its array turned by ``--rotation``
degrees; scene: ``budget_scene`` (0.8 px blur, photon and read noise), uniform motion.
Errors are RMS over the valid vectors in voxels, the vectors turned into object space
first (the lens-row grid's axes are turned), lateral (over x and y) and depth.
"""

from __future__ import annotations

import time

import numpy as np

from plenocl import Camera, Grid, get_queue, process_pair
from plenocl.bench.accuracy_section import SHIFT_VOX, budget_scene, paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.projection import Projector


def object_space_errors(res, grid: Grid) -> tuple[float, float]:
    """Lateral and depth RMS errors (voxels) of a uniform motion's vectors, turned from
    the grid's axes into object space."""
    ok, (_, dy, dx) = res.valid, grid.spacing
    ux, uy = grid.to_world(res.u * dx, res.v * dy)
    err = [ux[ok] / dx - SHIFT_VOX[0], uy[ok] / dy - SHIFT_VOX[1], res.w[ok] - SHIFT_VOX[2]]
    lateral = np.sqrt(np.mean(err[0] ** 2 + err[1] ** 2) / 2)
    return float(lateral), float(np.sqrt(np.mean(err[2] ** 2)))


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--rotation", type=float, default=0.15)
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--exact", action="store_true", help="also the general kernels")
    args = parser.parse_args()
    queue = get_queue()
    aligned, grid = paper_optics(tuple(args.lenses))
    cam = Camera(50.0, 2.42, 0.66, 0.125, 0.5, aligned.ml_count, 0.0074, aligned.pixels,
                 ml_rotation_deg=args.rotation)
    lens_rows = Grid(grid.shape, grid.x, grid.y, grid.z, rotation_deg=args.rotation)
    cases = [("lens-row grid (baseline)", lens_rows, "resample"),
             ("sensor-axis grid, resampled", grid, "resample")]
    if args.exact:
        cases.append(("sensor-axis grid, general kernels", grid, "exact"))
    projectors = [(label, Projector(cam, g, queue, general=mode)) for label, g, mode in cases]
    print(f"device: {queue.device.name.strip()}; array turned {args.rotation:g} deg, "
          f"{args.lenses[0]} x {args.lenses[1]} lenses, {args.seeding} particles per microlens")
    for seed in args.seeds:
        scene = budget_scene(cam, grid, args.seeding, seed, queue)
        for label, proj in projectors:
            t0 = time.perf_counter()
            pair = process_pair(scene.raw_a, scene.raw_b, proj)
            lateral, depth = object_space_errors(pair.piv, proj.grid)
            print(f"seed {seed}  {label:36s} ({proj.path:9s}) lateral {lateral:.3f}  "
                  f"depth {depth:.3f} voxel  valid {pair.piv.valid.mean():.0%}  "
                  f"{time.perf_counter() - t0:6.1f} s per pair", flush=True)


if __name__ == "__main__":
    main()
