"""A hexagonal microlens array against a rectangular one of the same lens count and pitch
(issue 29): forward + back projection and ``reconstruct()``'s default, seconds (medians)
and particle errors, in the same run.

    python benchmarks/hexagonal.py [--lenses 48 56] [--repeats 5] [--scenes 2]

The hexagonal camera projects through its axial view (``Camera.on_lens_lattice``: the
lenses on the leaning lattice ``q e1 + r e2``, padded with missing lenses), on the
separable kernels with the aperture sampled along the lattice's two steps
(docs/design.md §5.3); the rectangular one, aligned, on the separable path. Two more
rows turn the hexagonal array by 0.5° under a grid in the sensor's axes: projected
through its rows' frame and resampled (the default), and on the general kernels
(``general="exact"``: every hexagonal array's path before the rhombic sampling). All:
the paper's synthetic optics (M = 1, f/2, 0.125 mm lenses of ~17 px), the sensor cut to
the array, a grid over the middle 3 x 3 mm and 4 mm deep (24 x 24 x 32 voxels), 12
particles per scene ray traced through each camera's exact cells (1 px blur, photon
noise). Errors: RMS over the matched particles (within 1.5 voxel laterally, 4 in depth).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Camera, Grid, Projector, get_queue, simulate_image  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import median_time  # noqa: E402
from plenocl.metrics import matched_errors  # noqa: E402
from plenocl.reconstruction import reconstruct  # noqa: E402

GRID = Grid((32, 24, 24), x=(-1.5, 1.5), y=(-1.5, 1.5), z=(-2.0, 2.0))


#: The rows: label, layout, array rotation (degrees), projector options.
ROWS = (("rectangular", "rectangular", 0.0, {}), ("hexagonal", "hexagonal", 0.0, {}),
        ("hex 0.5°", "hexagonal", 0.5, {}),
        ("hex 0.5° exact", "hexagonal", 0.5, {"general": "exact"}))


def camera(layout: str, cols: int, rows: int, rotation_deg: float = 0.0) -> Camera:
    """The synthetic optics with ``cols x rows`` lenses, the sensor cut to the array (a
    turned array: one lens wider and taller)."""
    row_px = 16.98 * (np.sqrt(3) / 2 if layout == "hexagonal" else 1.0)
    pad = 17 if rotation_deg else 0
    cam = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (cols, rows), 0.0074,
                 (int(16.98 * cols) + 1 + pad, int(row_px * rows) + 1 + pad),
                 ml_layout=layout, ml_rotation_deg=rotation_deg)
    return cam.with_centers(cam.ideal_microlens_centers())


def errors(cam: Camera, proj: Projector, seed: int, queue) -> np.ndarray:
    """Per matched particle (x, y, z) errors (voxels) of one scene."""
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-1.0, 1.0, (12, 2)), rng.uniform(-1.6, 1.6, 12)])
    img = simulate_image(cam, pos, np.full(12, 2e4), 20000, seed=seed, blur_px=1.0,
                         photon_noise=True, queue=queue)
    return matched_errors(reconstruct(img, proj), GRID, pos, lateral=1.5, depth=4.0)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[48, 56])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--scenes", type=int, default=2)
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}; {args.lenses[0]} x {args.lenses[1]} lenses; "
          f"grid {GRID.shape}; medians of {args.repeats}")
    print(f"{'array':15s} {'path':9s} {'fwd+back s':>10s} {'reconstruct s':>13s} "
          f"{'lateral':>8s} {'depth':>6s} {'found':>6s}")
    for label, layout, rotation, options in ROWS:
        cam = camera(layout, *args.lenses, rotation)
        proj = Projector(cam, GRID, queue, **options)
        vol = np.random.default_rng(1).random(GRID.shape).astype(np.float32)
        fb = median_time(lambda p=proj, v=vol: p.back(p.forward(v)), args.repeats)
        img = simulate_image(cam, [[0.1, 0.2, 0.3]], [2e4], 20000, queue=queue)
        rec = median_time(lambda p=proj, i=img: reconstruct(i, p), args.repeats)
        d = np.vstack([errors(cam, proj, 100 + s, queue) for s in range(args.scenes)])
        print(f"{label:15s} {proj.path:9s} {fb:10.3f} {rec:13.2f} "
              f"{np.sqrt(np.mean(d[:, :2] ** 2)):8.3f} {np.sqrt(np.mean(d[:, 2] ** 2)):6.3f} "
              f"{len(d):3d}/{12 * args.scenes}", flush=True)


if __name__ == "__main__":
    main()
