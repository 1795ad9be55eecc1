"""Does the per-vector uncertainty cover the actual errors? (issues 15 and 16)

    python benchmarks/uncertainty.py [--quick]

``piv3d`` with default settings reports ``sigma_u, sigma_v, sigma_w`` (correlation
statistics on the final deformed volumes, ``plenocl.piv.direct``). For each case it
prints the RMS error of the valid vectors against the imposed uniform displacement, the
median reported sigma, and the fraction of errors within one sigma (a calibrated
standard uncertainty covers about 68 %):

1. rendered Gaussian particles with noise (``flows.volume_pair``), several densities,
   noise levels and windows: the random error the estimate is built for;
2. MLEM volumes reconstructed from ray-traced raw images at the paper's optics and voxel
   (``benchmarks/accuracy.py``'s camera on 96 x 64 microlenses, 0.8 px blur, photon and
   read noise), 0.02, 0.05 and 0.1 particles per microlens: what users have. With
   ``process_pair`` defaults (3 x 3 sub-voxels; each vector refined by the particle pairs
   in its window, sigma their standard error) and, on the same scene, the chain before
   (voxels, correlation only, sigma from correlation statistics).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import (  # noqa: E402
    Projector,
    flows,
    get_queue,
    piv3d,
    process_pair,
)
from plenocl.bench.accuracy_section import (  # noqa: E402
    BASELINE_SETTINGS,
    SHIFT_VOX,
    budget_scene,
    paper_optics,
)

RENDERED = [  # (density per voxel, particle sigma, noise, windows)
    (0.0004, 1.5, 0.02, (32, 24)), (0.001, 2.0, 0.1, (32, 24)),
    (0.002, 1.5, 0.2, (32, 24)), (0.001, 1.5, 0.05, (48, 32)),
]


def coverage_row(label: str, res, shift) -> str:
    """RMS error, median sigma and coverage per component."""
    cells = []
    for comp, s in zip("uvw", shift):
        err = (getattr(res, comp) - s)[res.valid]
        sigma = getattr(res, f"sigma_{comp}")[res.valid]
        known = np.isfinite(sigma)
        cells.append(f"{np.sqrt(np.mean(err ** 2)):.3f} / {np.median(sigma[known]):.3f} / "
                     f"{np.mean(np.abs(err[known]) < sigma[known]):.0%}")
    return f"| {label} | {res.valid.mean():.0%} | " + " | ".join(cells) + " |"


def rendered_rows(queue, cases) -> list[str]:
    shift = (2.31, -1.47, 0.68)
    rows = []
    for density, sigma, noise, windows in cases:
        pair = flows.volume_pair((64, 96, 128), flows.Uniform(shift), density=density,
                                 sigma=sigma, seed=3, noise=noise)
        res = piv3d(pair.vol_a, pair.vol_b, queue=queue, windows=windows)
        rows.append(coverage_row(f"rendered: {density} /voxel, sigma {sigma}, noise {noise}, "
                                 f"windows {windows}", res, shift))
    return rows


def reconstructed_rows(queue, seedings) -> list[str]:
    """Per seeding: ``process_pair`` defaults (sub-voxels, particle refinement: sigma is
    the pairs' standard error) and the chain before (voxels, correlation only: sigma from
    correlation statistics), on the same scene."""
    cam, grid = paper_optics((96, 64))
    proj = Projector(cam, grid, queue)
    rows = []
    for k, ppm in enumerate(seedings, start=1):
        scene = budget_scene(cam, grid, ppm, seed=k, queue=queue)
        for label, kw in (("default", {}), ("before", dict(settings=BASELINE_SETTINGS,
                                                              particles=False))):
            pair = process_pair(scene.raw_a, scene.raw_b, proj, **kw)
            rows.append(coverage_row(f"reconstructed, {label}: {ppm} per microlens, windows "
                                     f"{pair.piv.window[0]}", pair.piv, SHIFT_VOX))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="two rendered cases and one seeding (0.05)")
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}")
    print("per component: RMS error / median sigma / errors within 1 sigma (voxels)\n")
    print("| case | valid | u | v | w |\n|---|---|---|---|---|")
    for row in rendered_rows(queue, RENDERED[:2] if args.quick else RENDERED):
        print(row, flush=True)
    for row in reconstructed_rows(queue, [0.05] if args.quick else [0.02, 0.05, 0.1]):
        print(row, flush=True)


if __name__ == "__main__":
    main()
