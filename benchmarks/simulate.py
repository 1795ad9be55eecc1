"""Simulator throughput: rays per second of the OpenCL kernel against the NumPy reference
(the same rays, same process), medians of repeated runs.

    python benchmarks/simulate.py [--particles 200] [--rays 20000] [--repeats 5]
"""

from __future__ import annotations

import numpy as np

from plenocl import Camera, get_queue, reference
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.opencl.device import device_info
from plenocl.particles import random_particles
from plenocl.simulate import Simulator


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--rays", type=int, default=20000)
    parser.add_argument("--ref-rays", type=int, default=2000,
                        help="rays per particle for the (slow) NumPy reference")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    cam = Camera.synthetic_850()
    queue = get_queue()
    sim = Simulator(cam, queue)
    pos, inten = random_particles(((-2.5, 2.5),) * 3, count=args.particles, seed=1)
    n_dev, n_ref = args.particles * args.rays, args.particles * args.ref_rays

    t_dev = median_time(lambda: sim.trace(pos, inten, args.rays, seed=1), args.repeats)
    t_ref = median_time(lambda: reference.trace_particles(cam, pos, inten, args.ref_rays, 1),
                        args.repeats)
    t_small = median_time(lambda: sim.trace(pos, inten, args.ref_rays, seed=1), args.repeats)
    info = device_info(queue)
    print(f"device: {info.name} ({info.platform}); camera 850 x 850 px, 50 x 50 lenses")
    print(f"{'path':34s} {'rays':>12s} {'median s':>10s} {'Mrays/s':>10s}")
    print(f"{'OpenCL kernel':34s} {n_dev:12d} {t_dev:10.4f} {n_dev / t_dev / 1e6:10.2f}")
    print(f"{'OpenCL kernel (reference size)':34s} {n_ref:12d} {t_small:10.4f} "
          f"{n_ref / t_small / 1e6:10.2f}")
    print(f"{'NumPy reference':34s} {n_ref:12d} {t_ref:10.4f} {n_ref / t_ref / 1e6:10.2f}")
    print(f"speed-up at equal work: {t_ref / t_small:.1f}x; "
          f"kernel rays/s vs reference rays/s: {(n_dev / t_dev) / (n_ref / t_ref):.1f}x")
    same = np.corrcoef(sim.trace(pos, inten, args.ref_rays, 1).ravel(),
                       reference.trace_particles(cam, pos, inten, args.ref_rays, 1).ravel())[0, 1]
    print(f"kernel vs reference image correlation (same rays): {same:.7f}")


if __name__ == "__main__":
    main()
