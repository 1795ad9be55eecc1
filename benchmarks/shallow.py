"""Depth motion in a volume hardly deeper than a correlation window (docs/design.md
§7.1, "shallow volumes"): the gain (measured / true) of a uniform depth displacement
through ``process_pair``'s default chain, in a shallow volume and in one twice as deep
on the same camera, beside the correlation alone (``particles=False``), in the same run.

    python benchmarks/shallow.py [--seeds 1 2] [--shifts 0.5 1 2] [--ppm 0.05 0.1]

The 850 x 850 px camera (50 x 50 lenses), grids by ``Grid.for_camera`` over depths -2 to
2 mm (shallow: the default windows leave one window in depth, its centre in the focal
zone's blind band) and -4 to 4 mm (deep), particles 0.3 mm inside the grid, 2,000 rays
each, 0.8 px blur, photon and read noise, a background. Per row: the median gain of the
valid vectors' w over seeds, shifts and seedings (min-max of the scenes' medians), the
same for the lateral components' median displacement (true 0), and whether the chain
warned that no window sees depth.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import (  # noqa: E402
    Camera,
    Grid,
    Projector,
    get_queue,
    process_pair,
    random_particles,
    simulate_image,
)
from plenocl.bench.scripts import script_parser  # noqa: E402

DEPTHS = {"shallow (-2 to 2 mm)": (-2.0, 2.0), "deep (-4 to 4 mm)": (-4.0, 4.0)}
CHAINS = {"default chain": {}, "correlation alone": {"particles": False}}


def pair(cam: Camera, grid: Grid, ppm: float, shift: float, seed: int, queue):
    """Two raw images of particles displaced ``shift`` depth voxels, centred on their
    mid-exposure positions."""
    box = ((grid.x[0] + 0.3, grid.x[1] - 0.3), (grid.y[0] + 0.3, grid.y[1] - 0.3),
           (grid.z[0] + 0.3, grid.z[1] - 0.3))
    count = round(ppm * cam.ml_count[0] * cam.ml_count[1])
    pos, inten = random_particles(box, count=count, seed=seed, intensity=2e4)
    step = np.array([0.0, 0.0, shift * grid.spacing[0]])
    kw = dict(rays_per_particle=2000, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue)
    return (simulate_image(cam, pos - step / 2, inten, seed=2 * seed, **kw),
            simulate_image(cam, pos + step / 2, inten, seed=2 * seed + 1, **kw))


def gains(res, shift: float) -> tuple[float, float]:
    """The valid vectors' median w over the true shift, and the largest median lateral
    displacement (voxels)."""
    ok = res.valid
    return (float(np.median(res.w[ok])) / shift,
            max(abs(float(np.median(res.u[ok]))), abs(float(np.median(res.v[ok])))))


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--shifts", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    parser.add_argument("--ppm", type=float, nargs="+", default=[0.05, 0.1])
    args = parser.parse_args()
    queue, cam = get_queue(), Camera.synthetic_850()
    print(f"device: {queue.device.name.strip()}; camera {cam.pixels} px, "
          f"{cam.ml_count} lenses; depth resolution {cam.depth_resolution_mm:.2f} mm")
    print(f"{'volume':22s} {'chain':18s} {'depth gain (min-max)':>24s} "
          f"{'lateral |median|':>17s} {'warned':>7s}")
    for name, z in DEPTHS.items():
        grid = Grid.for_camera(cam, z=z)
        proj = Projector(cam, grid, queue)
        rows = {chain: [] for chain in CHAINS}
        warned = {chain: False for chain in CHAINS}
        for ppm in args.ppm:
            for shift in args.shifts:
                for seed in args.seeds:
                    raw_a, raw_b = pair(cam, grid, ppm, shift, seed, queue)
                    for chain, options in CHAINS.items():
                        with warnings.catch_warnings(record=True) as caught:
                            warnings.simplefilter("always")
                            res = process_pair(raw_a, raw_b, proj, **options).piv
                        warned[chain] |= any("blind zone" in str(w.message) for w in caught)
                        rows[chain].append(gains(res, shift))
        for chain, values in rows.items():
            g = np.array(values)
            print(f"{name:22s} {chain:18s} {np.median(g[:, 0]):8.3f} "
                  f"({g[:, 0].min():.3f}-{g[:, 0].max():.3f}) {g[:, 1].max():17.3f} "
                  f"{'yes' if warned[chain] else 'no':>7s}")


if __name__ == "__main__":
    main()
