"""Every CPU OpenCL driver present, side by side in one run: the projector, MLEM and the
small demo pair, with each driver's results compared against the first's.

    python benchmarks/drivers.py [--repeats 3] [--skip-paper] [--skip-demo]

Drivers are whatever the OpenCL loader lists (the PoCL wheel of the ``pocl`` extra,
Intel's CPU runtime of the ``intel`` extra, a system PoCL in /etc/OpenCL/vendors), in
plenocl's default order. A driver that cannot build plenocl's kernels is listed with
the reason. Rows:

- projector: forward + back projection of the paper's experiment (16 MP camera,
  300 x 200 x 150 voxels), device-resident, median of ``--repeats``;
- MLEM: 5 iterations on that grid from the simulated image of 1000 particles (voxels,
  ``supersample=1``), median of ``--repeats``;
- small demo: ``plenocl demo`` (the 850 x 850 px boundary layer: calibration, images,
  both reconstructions on 3 x 3 sub-voxels, MART, PIV with the particle fit) in a fresh
  folder, its stage times and its error in % of U infinity.
"""

from __future__ import annotations

import tempfile

import numpy as np

from plenocl import Camera, Grid, get_queue, random_particles
from plenocl.bench.scripts import script_parser
from plenocl.bench.stages import device_pair
from plenocl.bench.timing import median_time, timed
from plenocl.demo.boundary_layer import run_boundary_layer
from plenocl.opencl.device import build_problem, devices_by_preference, is_cpu
from plenocl.projection import Projector
from plenocl.reconstruction import reconstruct
from plenocl.simulate import simulate_image

PAPER_GRID = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0))


def driver_name(device) -> str:
    """Platform name and version, short."""
    version = device.platform.version.strip().replace("OpenCL ", "")
    return f"{device.platform.name.strip()} {version[:40]}"


def paper_rows(queue, image: np.ndarray, repeats: int) -> tuple[dict, np.ndarray]:
    """Projector and MLEM times at the paper's size, and the MLEM volume."""
    proj = Projector(Camera.paper_16mp(), PAPER_GRID, queue)
    vol = np.zeros(PAPER_GRID.shape, np.float32)
    vol[::7, ::9, ::11] = 1.0
    fwd, back, _ = device_pair(proj, vol)
    t_proj = median_time(lambda: (fwd(), back()), repeats)
    recon, t_mlem = timed(lambda: reconstruct(image, proj, "mlem", 5, supersample=1), repeats)
    return {"projector": t_proj, "mlem": t_mlem}, recon


def demo_row(queue) -> dict:
    """The small demo in a fresh folder: total seconds, reconstruction and PIV seconds,
    error in % of U infinity."""
    with tempfile.TemporaryDirectory() as out:
        summary = run_boundary_layer("small", out, queue=queue, figures=False,
                                     log=lambda _: None)
    sec = summary["seconds"]
    return {"demo": sum(sec.values()), "demo_recon": sec.get("reconstruction", np.nan),
            "demo_piv": sec.get("piv", np.nan), "error": 100 * summary["velocity_rms_error"]}


def main() -> None:
    ap = script_parser(__doc__, {"paper": None, "demo": None})
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    cpus = [d for d in devices_by_preference() if is_cpu(d)]
    image = None
    if not args.skip_paper:
        pos, inten = random_particles(((-25, 25), (-15, 15), (-8, 8)), count=1000, seed=1,
                                      intensity=2e4)
        image = simulate_image(Camera.paper_16mp(), pos, inten, 2000, seed=1)
    print(f"CPU OpenCL drivers, in plenocl's default order; medians of {args.repeats}")
    reference = None
    for dev in cpus:
        print(f"\n{driver_name(dev)}: {dev.name.strip()}")
        problem = build_problem(dev)
        if problem:
            print(f"  cannot build plenocl's kernels: {problem}")
            continue
        queue = get_queue(dev)
        if image is not None:
            rows, recon = paper_rows(queue, image, args.repeats)
            reference = recon if reference is None else reference
            diff = np.abs(recon - reference).max() / reference.max()
            print(f"  paper projector forward + back {rows['projector']:8.2f} s")
            print(f"  paper MLEM, 5 iterations       {rows['mlem']:8.2f} s  "
                  f"(max difference from the first driver {diff:.1e} of the peak)")
        if not args.skip_demo:
            d = demo_row(queue)
            print(f"  small demo                     {d['demo']:8.1f} s  (reconstruction "
                  f"{d['demo_recon']:.1f} s, PIV {d['demo_piv']:.1f} s; error "
                  f"{d['error']:.1f} % of U_inf)")


if __name__ == "__main__":
    main()
