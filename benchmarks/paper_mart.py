"""The paper's method on the paper's synthetic case (issue 47): MART at its parameters (15
iterations, relaxation 0.7, no ratio floor) with the paper's weights on its voxels (the
baseline), against the same MART with the weighting true to the camera on 3 x 3 lateral
sub-voxels, without and with its default Gaussian smoothing of the raw image (1 px), from
the sub-voxels' start and after the coarse MLEM run that ``reconstruct(method="mart")``
takes by default; the default reconstruction beside them; on the same unseen scenes in the
same run.

    python benchmarks/paper_mart.py [--scenes 6] [--counts 20 60] [--smooth 1.0] [--smart]

Camera: the 850 x 850 px synthetic camera (50 x 50 microlenses, M = 1, f/2); grid: the
5 mm cube of ``benchmarks/mart_footprint.py`` (40 x 40 voxels of 0.125 mm, one microlens,
laterally; 20 of 0.25 mm in depth). Particles: uniform in the cube (0.2 mm from its
faces), 1e4 counts each, ray traced with 20,000 rays and a 1 px particle blur (seeds
2000 + k, used by no test); the noisy image adds photon noise, a dark level of 20 counts
and 3 counts of read noise to the same scene. Rows:

- ``paper's MART (its weights, voxels)``: ``reconstruct(img, Projector(...,
  lens_weights="paper"), "mart", 15, 0.7, supersample=1, smooth_px=0)``, the paper's
  method on the image as it is;
- ``MART, extent weights, 3 x 3, unsmoothed``: the same MART on sub-voxels
  (``supersample=3, coarse_iterations=0``) whose lens weights integrate each sub-voxel's
  extent (``lens_weights="extent"``, docs/design.md §6.4), on the image as it is;
- ``MART, extent weights, 3 x 3, smoothed``: the same with MART's default smoothing of
  the image (``smooth_px`` 1 px, docs/design.md §6.2);
- ``MART, its defaults (MLEM's coarse run)``: ``reconstruct(img, projector, "mart")``,
  what a user who names the paper's method gets: the same smoothed MART on the sub-voxels
  within the support of 4 MLEM iterations on the voxels (docs/design.md §6.5);
- ``default``, ``default, paper's weights`` and ``default, smoothed``: ``reconstruct()``'s
  defaults, with the paper's lens weights, and on the image smoothed by ``--smooth``
  pixels;
- ``--smart``: also SMART (30 iterations, μ = 1) with its defaults (the image smoothed by
  1 px, after MLEM's coarse run) and on the image as it is.

Recovery: a peak above 0.1 of the volume's maximum within 1 voxel laterally and 2 in
depth of a true particle, one to one; ghosts: the share of intensity farther than
(2, 4) voxels from every particle; Q against the true particles rendered as Gaussians;
seconds per reconstruction (median).
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Camera, Grid, Projector, get_queue  # noqa: E402
from plenocl.bench.core import particle_scene  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.metrics import quality_q, recovery, render_particles  # noqa: E402
from plenocl.reconstruction import ReconstructionSettings, reconstruct  # noqa: E402
from plenocl.simulate import simulate_image  # noqa: E402

GRID = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
PAPER_MART = dict(method="mart", iterations=15, relax=0.7)


def rows(smooth: float, smart: bool = False) -> dict[str, tuple[str, ReconstructionSettings]]:
    """Each row's lens weights and settings (``smart``: SMART's rows too)."""
    sub = dict(PAPER_MART, supersample=3, coarse_iterations=0)
    return {
        "paper's MART (its weights, voxels)":
            ("paper", ReconstructionSettings(**PAPER_MART, supersample=1, smooth_px=0)),
        "MART, extent weights, 3 x 3, unsmoothed":
            ("extent", ReconstructionSettings(**sub, smooth_px=0)),
        "MART, extent weights, 3 x 3, smoothed": ("extent", ReconstructionSettings(**sub)),
        "MART, its defaults (MLEM's coarse run)": ("extent", ReconstructionSettings("mart")),
        "default": ("extent", ReconstructionSettings()),
        "default, paper's weights": ("paper", ReconstructionSettings()),
        f"default, smoothed {smooth:g} px": ("extent", ReconstructionSettings(smooth_px=smooth)),
        **({"SMART, its defaults": ("extent", ReconstructionSettings("smart")),
            "SMART, unsmoothed": ("extent", ReconstructionSettings("smart", smooth_px=0))}
           if smart else {}),
    }


def scene_images(camera: Camera, count: int, seed: int, queue):
    """The particles, their truth volume, and the blurred (:func:`particle_scene`, the
    workload of ``benchmarks/cubic_recovery.py``) and the noisy raw image."""
    pos, inten, blurred = particle_scene(camera, count, seed, blur_px=1.0, queue=queue)
    noisy = simulate_image(camera, pos, inten, 20000, seed=seed, blur_px=1.0, queue=queue,
                           photon_noise=True, background=20.0, read_noise=3.0)
    images = {"1 px blur": blurred, "1 px blur, noisy": noisy}
    return pos, render_particles(GRID, pos, inten), images


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--counts", type=int, nargs="+", default=[20, 60])
    parser.add_argument("--smooth", type=float, default=1.0,
                        help="the smoothing's standard deviation (pixels)")
    parser.add_argument("--smart", action="store_true", help="SMART's rows too")
    args = parser.parse_args()
    queue = get_queue()
    cam = Camera.synthetic_850()
    projectors = {w: Projector(cam, GRID, queue, lens_weights=w) for w in ("paper", "extent")}
    table = rows(args.smooth, args.smart)
    print(f"device: {queue.device.name.strip()}; grid {GRID.shape} (z, y, x), voxel "
          f"{GRID.spacing[0]:.3f} x {GRID.spacing[1]:.3f} x {GRID.spacing[2]:.3f} mm; "
          f"{args.scenes} scenes per count")
    print(f"{'particles':>9s} {'image':17s} {'reconstruction':44s} {'recovered':>9s} "
          f"{'min':>5s} {'ghosts':>6s} {'Q':>5s} {'s':>5s}")
    for count in args.counts:
        stats: dict = {}
        for k in range(args.scenes):
            pos, truth, images = scene_images(cam, count, 2000 + k, queue)
            for image_name, img in images.items():
                for label, (weights, chosen) in table.items():
                    call = functools.partial(reconstruct, img, projectors[weights],
                                             settings=chosen)
                    vol, t = timed(call, 1)
                    rep = recovery(vol, GRID, pos)
                    stats.setdefault((image_name, label), []).append(
                        (rep.fraction, rep.ghost_fraction, quality_q(vol, truth), t))
        for (image_name, label), entries in stats.items():
            a = np.array(entries)
            print(f"{count:9d} {image_name:17s} {label:44s} {a[:, 0].mean():9.1%} "
                  f"{a[:, 0].min():5.0%} {a[:, 1].mean():6.1%} {a[:, 2].mean():5.2f} "
                  f"{np.median(a[:, 3]):5.1f}", flush=True)


if __name__ == "__main__":
    main()
