"""Particle recovery on the paper's synthetic case with cubic voxels (issues 15, 28):
``reconstruct()``'s default, which ``process_pair`` and the CLI share (coarse-to-fine
MLEM on 3 x 3 lateral sub-voxels per voxel), against the single-frame reconstruction on
the voxels themselves (``supersample=1``, ``reconstruct()``'s default before issue 28)
and other sub-voxel schedules, on the same unseen scenes in the same run.

    python benchmarks/cubic_recovery.py [--scenes 6] [--counts 20 60] [--fine 10 15 20 30]
                                        [--lens-weights paper extent]

Camera: the 850 x 850 px synthetic camera (50 x 50 microlenses, M = 1, f/2); grid: the
5 mm cube on 40^3 cubic voxels (0.125 mm: one microlens laterally, a quarter of the
camera's depth resolution in depth). Particles: uniform in the cube (0.2 mm from its
faces), ray traced with 20,000 rays each and a 1 px particle blur, seeds 1000 + k (used
by no test). Recovery: a peak within 1 voxel laterally and 2 in depth of a true
particle, one to one; ghosts: the share of intensity farther than (2, 4) voxels from
every particle; Q against the true particles rendered as Gaussians; seconds per
reconstruction. ``--lens-weights``: each reconstruction with each of the projector's lens
weights (``Projector(lens_weights=...)``, issue 47; by default both, the rows of the
paper's labelled so).

Then, per reconstruction, where its misses lie (issue 47), as shares of all the particles:
``pairs``, a particle within 2 voxels of another (depth counted half, the match's
scale), where one peak of the 40^3 grid often stands for both; ``focal``, the others
within the camera's depth resolution of the focal plane (0.5 mm), whose images a single
camera leaves ambiguous along lines through the lens edges (``benchmarks/focal_zone.py``);
``other``, the rest.

Measured (2026-12-03, Intel's CPU runtime, ``--scenes 12``): ``reconstruct()``'s default
recovers 91.7 % of 20 particles, missing 2.9 % in pairs, 4.6 % focal and 0.8 % other, and
90.4 % of 60 (2.8 / 6.0 / 0.8 %); 30 sub-voxel iterations from a uniform volume (five
times the time) 94.6 % (2.1 / 3.3 / 0.0 %) and 92.9 % (2.6 / 4.0 / 0.4 %). The pairs
take 2.1-3.1 % in every sub-voxel reconstruction, so a 95 % recovery of 20 leaves the
focal zone and the rest about 2 %.
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
from plenocl.metrics import (  # noqa: E402
    quality_q,
    recovered_particles,
    recovery,
    render_particles,
)
from plenocl.projection.projector import DEFAULT_LENS_WEIGHTS, LENS_WEIGHTS  # noqa: E402
from plenocl.reconstruction import ReconstructionSettings, reconstruct  # noqa: E402

CUBIC = Grid((40, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
#: A particle nearer another than this (voxels, depth counted half) is one of a close pair.
PAIR_DISTANCE = 2.0
#: The miss classes printed after the table.
MISS_CLASSES = ("pairs", "focal", "other")
#: The reconstructions compared (label: settings).
SETTINGS = {
    "voxels, 30 it. (supersample=1)": ReconstructionSettings(supersample=1),
    "3 x 3 sub-voxels, 30 it.": ReconstructionSettings(supersample=3, iterations=30,
                                                       coarse_iterations=0),
    "coarse-to-fine 10 + 10": ReconstructionSettings(supersample=3, iterations=10, relax=1.0,
                                                     coarse_iterations=10, support=1e-2),
    "reconstruct() default (4 + 7, μ 1.5)": ReconstructionSettings(),
    "5 + 10, μ 1.5": ReconstructionSettings(supersample=3, iterations=10, relax=1.5,
                                            coarse_iterations=5, support=1e-2),
}


def miss_classes(vol: np.ndarray, pos: np.ndarray, depth_resolution_mm: float
                 ) -> np.ndarray:
    """The particles a reconstruction missed (matched as :func:`plenocl.metrics.recovery`
    matches), counted per class of :data:`MISS_CLASSES`: ``(3,)`` int."""
    hit = recovered_particles(vol, CUBIC, pos)
    scaled = CUBIC.to_index(pos) / np.array([1.0, 1.0, 2.0])
    dist = np.linalg.norm(scaled[:, None] - scaled[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    pair = dist.min(axis=1) < PAIR_DISTANCE
    focal = ~pair & (np.abs(pos[:, 2]) < depth_resolution_mm)
    other = ~pair & ~focal
    return np.array([np.sum(~hit & c) for c in (pair, focal, other)])


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--counts", type=int, nargs="+", default=[20, 60])
    parser.add_argument("--fine", type=int, nargs="*", default=[],
                        help="also the default schedule with these many fine iterations")
    parser.add_argument("--lens-weights", nargs="+", choices=LENS_WEIGHTS,
                        default=list(LENS_WEIGHTS),
                        help="the projector's lens weights to compare (default: both)")
    args = parser.parse_args()
    settings = {**SETTINGS, **{f"default with {n} fine iterations":
                               ReconstructionSettings(iterations=n) for n in args.fine}}
    queue = get_queue()
    cam = Camera.synthetic_850()
    projectors = {w: Projector(cam, CUBIC, queue, lens_weights=w) for w in args.lens_weights}
    runs = {(label if w == DEFAULT_LENS_WEIGHTS else f"{label}, {w} weights"):
            (chosen, projectors[w])
            for label, chosen in settings.items() for w in args.lens_weights}
    print(f"device: {queue.device.name.strip()}; grid {CUBIC.shape}, voxel "
          f"{CUBIC.spacing[0]:.3f} mm; {args.scenes} scenes per count")
    print(f"{'particles':>9s} {'reconstruction':50s} {'recovered':>9s} {'min':>5s} "
          f"{'ghosts':>6s} {'Q':>5s} {'s':>5s}")
    for count in args.counts:
        stats = {label: [] for label in runs}
        misses = {label: np.zeros(len(MISS_CLASSES), int) for label in runs}
        for k in range(args.scenes):
            pos, inten, img = particle_scene(cam, count, 1000 + k, blur_px=1.0, queue=queue)
            truth = render_particles(CUBIC, pos, inten)
            for label, (chosen, proj) in runs.items():
                vol, t = timed(functools.partial(reconstruct, img, proj, settings=chosen), 1)
                rep = recovery(vol, CUBIC, pos)
                misses[label] += miss_classes(vol, pos, cam.depth_resolution_mm)
                stats[label].append((rep.fraction, rep.ghost_fraction, quality_q(vol, truth),
                                     t))
        for label, rows in stats.items():
            a = np.array(rows)
            print(f"{count:9d} {label:50s} {a[:, 0].mean():9.1%} {a[:, 0].min():5.0%} "
                  f"{a[:, 1].mean():6.1%} {a[:, 2].mean():5.2f} {np.median(a[:, 3]):5.1f}",
                  flush=True)
        total = count * args.scenes
        print(f"{'':9s} {'missed (share of the particles)':50s} "
              + " ".join(f"{c:>6s}" for c in MISS_CLASSES))
        for label, m in misses.items():
            print(f"{count:9d} {label:50s} " + " ".join(f"{v / total:6.1%}" for v in m))


if __name__ == "__main__":
    main()
