"""A real calibrated microlens array on the projector's fast path: forward + back against
its ideal lattice, and its images against the general path it took before.

    python benchmarks/real_array.py [--camera CALIBRATED.toml --grid GRID.toml] [--repeats 7]

Default camera: :func:`plenocl.bench.realarray.replica_camera`, the lattice ``plenocl
calibrate`` found on cicwi/plenoptomos' ``letters_ULF_M1_white.png`` (27 x 20 lenses,
rows turned 0.1322°, columns 0.0053° off square), with the grid ``plenocl grid --z -10
10`` writes for it (48 x 20 x 27 voxels in the rows' frame). ``--camera``/``--grid``
take any calibrated camera and grid files instead (that image calibrated here gives the
same figures). Rows, each in the same run:

* the ideal lattice (the nominal optics, a grid in the sensor's axes): the baseline;
* the calibrated array as projected now (``Projector`` defaults);
* the calibrated array on the general kernels, as it was projected before (no lattice
  term dropped: ``shear_tol=-1, general="exact"``).

Then the calibrated array's images: now against the general kernels on the same
weighting model (float32 agreement), against before (the leaning aperture samples against
the square ones), and before against four times finer aperture samples (the model's own
sampling error, for scale); and 7 MLEM iterations on the voxels from one simulated
image, now against before.
"""

from __future__ import annotations

import copy
import dataclasses
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from plenocl import Camera, Grid, Projector, get_queue, simulate_image  # noqa: E402
from plenocl.bench.realarray import (  # noqa: E402
    agreement,
    replica_camera,
    skew_drift,
    sparse_volume,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import run_times  # noqa: E402
from plenocl.particles import random_particles  # noqa: E402
from plenocl.reconstruction import reconstruct  # noqa: E402

#: The grid ``plenocl grid --z -10 10`` writes for the replica (and for the image).
REPLICA_GRID = dict(shape=(48, 20, 27), x=(-4.05, 4.05), y=(-3.0, 3.0), z=(-10.0, 10.0))


def forward_back_ms(proj: Projector, repeats: int) -> list[float]:
    """Milliseconds of one forward and one back projection of a random volume."""
    vol = np.random.default_rng(0).random(proj.grid.shape).astype(np.float32)

    def once():
        proj.back(proj.forward(vol))
        proj.queue.finish()
    return [1e3 * t for t in run_times(once, repeats)]


def projectors(cam: Camera, grid: Grid, queue) -> dict[str, Projector]:
    """The three rows' projectors (the before row's general-path warning silenced)."""
    ideal = dataclasses.replace(cam, microlens_centers=None, calibrated=False)
    ideal_grid = Grid(grid.shape, grid.x, grid.y, grid.z)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        before = Projector(cam, grid, queue, shear_tol=-1.0, general="exact")
    return {"ideal lattice": Projector(ideal, ideal_grid, queue),
            "calibrated, now": Projector(cam, grid, queue),
            "calibrated, before": before}


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--camera", help="calibrated camera TOML (default: the replica)")
    parser.add_argument("--grid", help="grid TOML for it")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    queue = get_queue()
    cam = Camera.from_toml(args.camera) if args.camera else replica_camera()
    grid = Grid.from_toml(args.grid) if args.grid else Grid(
        **REPLICA_GRID, rotation_deg=0.1321747472983671)
    print(f"device: {queue.device.name.strip()}; camera {cam.ml_count[0]} x "
          f"{cam.ml_count[1]} lenses, columns' drift across the rows "
          f"{skew_drift(cam):.4f} lenses; grid {grid.shape} turned {grid.rotation_deg:.4f}°")
    procs = projectors(cam, grid, queue)
    base = None
    for name, proj in procs.items():
        ms = forward_back_ms(proj, args.repeats)
        base = base or float(np.median(ms))
        print(f"{name:20s} {proj.path:10s} forward + back median {np.median(ms):7.1f} ms "
              f"({min(ms):.1f}-{max(ms):.1f}, {len(ms)} runs)  {np.median(ms) / base:5.2f}x "
              "the ideal lattice", flush=True)
    now, before = procs["calibrated, now"], procs["calibrated, before"]
    report_agreement(cam, grid, now, before, queue)


def report_agreement(cam: Camera, grid: Grid, now: Projector, before: Projector,
                     queue) -> None:
    """The calibrated array's images and reconstructions, now against before."""
    kernels_model = copy.copy(now.frame.model if now.frame else now.model)
    kernels_model.path = "general"
    target = now.frame or now
    kernels = Projector(cam, target.grid, queue, model=kernels_model, general="exact")
    vol = sparse_volume(grid, 300, seed=1)
    img = np.random.default_rng(2).random(now.image_shape).astype(np.float32)
    same = agreement(target.forward(vol), kernels.forward(vol), cam)
    back = target.back(img)
    print(f"now against the general kernels on its model: images {same.peak:.1e} of the "
          f"peak, back projections {np.abs(back - kernels.back(img)).max() / back.max():.1e}")
    fine = Projector(cam, grid, queue, shear_tol=-1.0, general="exact",
                     oversample=4 * before.model.oversample)
    a, b, f = now.forward(vol), before.forward(vol), fine.forward(vol)
    for label, x, y in (("now against before", a, b),
                        ("before against 4x finer aperture samples", b, f)):
        g = agreement(x, y, cam)
        print(f"{label:42s} images {g.peak:.2e} of the peak, totals {g.total:.1e}, lens "
              f"images' centroids {g.centroid_px:.4f} px")
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    pos, inten = random_particles(box, count=60, seed=3, intensity=2e4)
    raw = simulate_image(cam, pos, inten, rays_per_particle=2000, blur_px=0.8, queue=queue)
    va, vb = (reconstruct(raw, p, supersample=1, coarse_iterations=0, iterations=7)
              for p in (now, before))
    print(f"reconstructions (7 MLEM iterations on the voxels): now against before "
          f"{np.abs(va - vb).max() / vb.max():.2e} of the peak, totals "
          f"{abs(va.sum() - vb.sum()) / vb.sum():.1e}")


if __name__ == "__main__":
    main()
