"""Why the geometric-mean solvers (the paper's MART, SMART) lose particles MLEM keeps:
the weighting function's voxel footprint against a point particle's image.

    python benchmarks/mart_footprint.py

1. For voxels at several depths of the paper's synthetic case: the pixels the voxel's
   model footprint touches (docs/design.md §5: bilinear over 4 microlenses and 4 pixels), the
   pixels a point particle at the voxel's centre lights (200,000 rays), and the fraction
   of the voxel's model weight on pixels that particle leaves dark. A dark pixel's ratio
   is 0 (clamped to 1e-6, log -13.8), so a geometric-mean update multiplies the voxel
   by about exp(-13.8 * that fraction) per iteration.
2. Recovery and Q of MART, SMART and MLEM on the same particles from the simulated
   image, the simulated image with a 1 px particle blur (without and with photon noise,
   a dark level of 20 counts and read noise), and the model's own projection of the
   particles (rendered as Gaussians): the image the weighting function expects. MART
   and SMART also with a ratio floor of 0.1 and 0.3 (``ratio_floor``, docs/design.md
   §6.2) against their literal form; MLEM on each image is the baseline of the same run.
   Every method on the image as it is (``smooth_px=0``: MART and SMART smooth it by 1 px
   by default, docs/design.md §6.2, which ``benchmarks/paper_mart.py`` measures).
"""

from __future__ import annotations

import numpy as np

from plenocl import Camera, Grid, get_queue, random_particles
from plenocl.metrics import quality_q, recovery, render_particles
from plenocl.opencl.device import device_info
from plenocl.projection import Projector
from plenocl.reconstruction import DEFAULTS, METHODS, reconstruct
from plenocl.simulate import simulate_image

GRID = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
#: (method, ratio floor): the literal methods, then MART and SMART with a floor.
VARIANTS = [(m, None) for m in METHODS] + [(m, f) for m in ("mart", "smart")
                                            for f in (0.1, 0.3)]
VOXELS = [(10, 20, 20), (10, 21, 19), (5, 20, 20), (15, 13, 27), (0, 20, 20)]


def footprints(proj: Projector) -> None:
    """Model footprint against a point particle's lit pixels, per voxel."""
    print(f"{'voxel (z, y, x)':16s} {'z mm':>6s} {'model px':>9s} {'point px':>9s} "
          f"{'model weight on dark px':>24s}")
    axes = {a: GRID.axis_centers(a) for a in "xyz"}
    for iz, iy, ix in VOXELS:
        idx, w = proj.voxel_weights(iz, iy, ix)
        centre = np.array([[axes["x"][ix], axes["y"][iy], axes["z"][iz]]])
        img = simulate_image(proj.camera, centre, 1e4, 200_000, seed=1, queue=proj.queue)
        dark = w[img.ravel()[idx] <= 0].sum() / w.sum()
        print(f"{str((iz, iy, ix)):16s} {centre[0, 2]:6.2f} {len(idx):9d} "
              f"{int((img > 0).sum()):9d} {dark:24.2f}")


def solvers(proj: Projector, count: int) -> None:
    """Each method on the simulated, blurred and model-consistent images."""
    pos, inten = random_particles(((-2.3, 2.3),) * 3, count=count, seed=count, intensity=1e4)
    truth = render_particles(GRID, pos, inten)
    images = {
        "simulated (20,000 rays)": simulate_image(proj.camera, pos, inten, 20000, seed=count),
        "simulated, 1 px blur": simulate_image(proj.camera, pos, inten, 20000, seed=count,
                                               blur_px=1.0),
        "1 px blur, noisy": simulate_image(proj.camera, pos, inten, 20000, seed=count,
                                           blur_px=1.0, photon_noise=True, background=20.0,
                                           read_noise=3.0),
        "model's own projection": proj.forward(truth),
    }
    for name, img in images.items():
        for method, floor in VARIANTS:
            it, mu = DEFAULTS[method]
            vol = reconstruct(img, proj, method, it, mu, ratio_floor=floor, supersample=1,
                              smooth_px=0)
            rep = recovery(vol, GRID, pos)
            label = method if floor is None else f"{method} floor {floor:g}"
            print(f"{count:9d} {name:24s} {label:16s} {it:4d} {rep.fraction:6.2f} "
                  f"{rep.ghost_fraction:6.3f} {quality_q(vol, truth):5.2f}", flush=True)


def main() -> None:
    queue = get_queue()
    print(f"device: {device_info(queue).name}")
    proj = Projector(Camera.synthetic_850(), GRID, queue, lens_weights="paper")  # its model
    print(f"850 x 850 px camera, grid {GRID.shape} over a 5 mm cube\n")
    footprints(proj)
    print(f"\n{'particles':>9s} {'image':24s} {'method':16s} {'it':>4s} {'recov':>6s} "
          f"{'ghosts':>6s} {'Q':>5s}")
    for count in (20, 60):
        solvers(proj, count)


if __name__ == "__main__":
    main()
