"""MART against MLEM at the paper's full size: one iteration with every set-up cost
included (a fresh projector: sensitivity, and MART's view blocks), and the cost of each
further iteration, in the same run.

    python benchmarks/solver_setup.py [--repeats 3] [--rotation 0.15]

Scene: the paper's experiment (16 MP camera, 289 x 193 microlenses, 300 x 200 x 150
voxels over 55 x 35 x 20 mm), 0.05 particles per microlens, ray-traced with 0.8 px
blur. The array may be rotated (``--rotation``); the grid then follows its lens rows
(Grid.for_camera), so both solvers run the separable projector path.
"""

from __future__ import annotations

import os
import statistics
import time

import numpy as np

from plenocl import Camera, Grid, Projector, get_queue, random_particles, simulate_image
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.opencl.device import device_info
from plenocl.reconstruction import reconstruct


def paper_scene(rotation: float, queue):
    """The paper camera (array rotated by ``rotation`` degrees), its grid and an image."""
    cam = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280),
                 ml_rotation_deg=rotation)
    frame = Grid.for_camera(cam, z=(-10.0, 10.0))
    grid = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0),
                rotation_deg=frame.rotation_deg)
    n = int(0.05 * 289 * 193)
    pos, inten = random_particles(((-27, 27), (-17, 17), (-9.5, 9.5)), count=n, seed=4,
                                  intensity=2e4)
    image = simulate_image(cam, pos, inten, 2000, seed=4, blur_px=0.8, queue=queue)
    return cam, grid, image


def timed_first(cam, grid, image, queue, method: str, iterations: int, repeats: int):
    """Median time of ``iterations`` iterations on a fresh projector each time (its
    construction not counted): the set-up a new projector pays, included."""
    times = []
    for _ in range(repeats):
        proj = Projector(cam, grid, queue)
        t0 = time.perf_counter()
        reconstruct(image, proj, method, iterations=iterations, supersample=1, smooth_px=0)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), proj


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rotation", type=float, default=0.15)
    args = parser.parse_args()
    queue = get_queue()
    info = device_info(queue)
    print(f"device: {info.name}; load average at start {os.getloadavg()[0]:.2f}")
    cam, grid, image = paper_scene(args.rotation, queue)
    print(f"paper experiment, array rotated {args.rotation:g} deg, grid frame "
          f"{grid.rotation_deg:.4f} deg, {np.count_nonzero(image > 0) / image.size:.0%} of "
          f"pixels lit; medians of {args.repeats}")
    first, warm = {}, {}
    for method in ("mlem", "mart"):
        first[method], proj = timed_first(cam, grid, image, queue, method, 1, args.repeats)
        # the same (warm) projector: the cost of each further iteration
        t3, t1 = (median_time(lambda n=n, p=proj, m=method: reconstruct(
                                  image, p, m, iterations=n, supersample=1, smooth_px=0),
                              args.repeats, warmup=False) for n in (3, 1))
        warm[method] = (t3 - t1) / 2
        print(f"  {method.upper():4s} ({proj.path} path): 1 iteration with set-up "
              f"{first[method]:.2f} s; each further iteration {warm[method]:.2f} s")
    print(f"  MART / MLEM: first iteration with set-up {first['mart'] / first['mlem']:.2f}x, "
          f"per iteration {warm['mart'] / warm['mlem']:.2f}x (MART projects 4 view blocks "
          "per iteration)")
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
