"""Does the per-vector uncertainty cover the actual errors? (issues 15 and 16)

    python benchmarks/uncertainty.py [--quick] [--seed N]

``piv3d`` with default settings reports ``sigma_u, sigma_v, sigma_w`` (correlation
statistics on the final deformed volumes, ``plenocl.piv.direct``). For each case it
prints the RMS error of the valid vectors against the imposed uniform displacement, the
median reported sigma, and the fraction of errors within one sigma (a calibrated
standard uncertainty covers about 68 %):

1. rendered Gaussian particles with noise (``flows.volume_pair``), several densities,
   noise levels and windows: the random error the estimate is built for;
2. MLEM volumes reconstructed from ray-traced raw images at the paper's optics and voxel
   (``benchmarks/accuracy.py``'s camera on 96 x 64 microlenses, 0.8 px blur, photon and
   read noise), 0.02, 0.05 and 0.1 particles per microlens, a uniform displacement and a
   2-degree rotation about x: what users have. With ``process_pair`` defaults (3 x 3
   sub-voxels; each volume's particles fitted to its raw image, docs/design.md §7.2;
   each vector refined by the particle pairs in its window, sigma their standard error
   with the focal zone's systematic depth term and the particles' depth position
   carried through the local gradient, docs/design.md §7.1) and, on the same
   scene, the chain before (voxels, correlation only, sigma from correlation
   statistics). The last two rows pool every reconstructed scene: lateral (u and v) and
   depth.
"""

from __future__ import annotations

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
    ROTATION,
    UNIFORM,
    budget_scene,
    paper_optics,
)
from plenocl.bench.scripts import script_parser  # noqa: E402

RENDERED = [  # (density per voxel, particle sigma, noise, windows)
    (0.0004, 1.5, 0.02, (32, 24)), (0.001, 2.0, 0.1, (32, 24)),
    (0.002, 1.5, 0.2, (32, 24)), (0.001, 1.5, 0.05, (48, 32)),
]


def coverage_cells(errors, sigmas) -> str:
    """RMS error / median sigma / fraction within one sigma of pooled components."""
    err, sigma = np.concatenate(errors), np.concatenate(sigmas)
    known = np.isfinite(sigma)
    return (f"{np.sqrt(np.mean(err ** 2)):.3f} / {np.median(sigma[known]):.3f} / "
            f"{np.mean(np.abs(err[known]) < sigma[known]):.0%}")


def component_errors(res, truth) -> tuple[list, list]:
    """Errors and sigmas of the valid vectors, per component ``u, v, w``."""
    errors = [(getattr(res, c) - t)[res.valid] for c, t in zip("uvw", truth)]
    sigmas = [getattr(res, f"sigma_{c}")[res.valid] for c in "uvw"]
    return errors, sigmas


def coverage_row(label: str, res, truth) -> str:
    """Valid fraction, then per component u, v, w, lateral (u and v) and depth."""
    errors, sigmas = component_errors(res, truth)
    cells = [coverage_cells([e], [s]) for e, s in zip(errors, sigmas)]
    cells += [coverage_cells(errors[:2], sigmas[:2]), coverage_cells(errors[2:], sigmas[2:])]
    return f"| {label} | {res.valid.mean():.0%} | " + " | ".join(cells) + " |"


def rendered_rows(queue, cases) -> list[str]:
    shift = (2.31, -1.47, 0.68)
    rows = []
    for density, sigma, noise, windows in cases:
        pair = flows.volume_pair((64, 96, 128), flows.Uniform(shift), density=density,
                                 sigma=sigma, seed=3, noise=noise)
        res = piv3d(pair.vol_a, pair.vol_b, queue=queue, windows=windows)
        truth = [np.full(res.u.shape, s) for s in shift]
        rows.append(coverage_row(f"rendered: {density} /voxel, sigma {sigma}, noise {noise}, "
                                 f"windows {windows}", res, truth))
    return rows


def reconstructed_rows(queue, seedings, motions, seed: int = 0) -> list[str]:
    """Per seeding and motion: ``process_pair`` defaults (sub-voxels, particle
    refinement: sigma from the pairs and the focal zone) and the chain before (voxels,
    correlation only: sigma from correlation statistics), on the same scene; then every
    scene pooled."""
    cam, grid = paper_optics((96, 64))
    proj = Projector(cam, grid, queue)
    # per chain: errors and sigmas of every scene, by component u, v, w
    rows, pooled = [], {label: [[[] for _ in "uvw"] for _ in range(2)]
                        for label in ("default", "before")}
    for k, ppm in enumerate(seedings, start=1):
        for motion in motions:
            scene = budget_scene(cam, grid, ppm, seed=seed + k, queue=queue, motion=motion)
            before = dict(reconstruction=BASELINE_SETTINGS, particles=False)
            for label, kw in (("default", {}), ("before", before)):
                res = process_pair(scene.raw_a, scene.raw_b, proj, **kw).piv
                truth = motion.displacement(res, grid)
                rows.append(coverage_row(f"reconstructed, {label}: {motion.name}, {ppm} per "
                                         f"microlens, windows {res.window[0]}", res, truth))
                for store, new in zip(pooled[label], component_errors(res, truth)):
                    for by_comp, values in zip(store, new):
                        by_comp.append(values)
                print(rows[-1], flush=True)
    for label, ((err_u, err_v, err_w), (sig_u, sig_v, sig_w)) in pooled.items():
        rows.append(f"| pooled, {label}: every scene above | | | | | "
                    f"{coverage_cells(err_u + err_v, sig_u + sig_v)} | "
                    f"{coverage_cells(err_w, sig_w)} |")
    return rows


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="two rendered cases and one seeding (0.05)")
    parser.add_argument("--seed", type=int, default=0,
                        help="added to the reconstructed scenes' seeds (1, 2, 3 by "
                             "default): other scenes than those the uncertainty was "
                             "calibrated on")
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}")
    print("per component: RMS error / median sigma / errors within 1 sigma (voxels)\n")
    print("| case | valid | u | v | w | lateral | depth |\n|---|---|---|---|---|---|---|")
    for row in rendered_rows(queue, RENDERED[:2] if args.quick else RENDERED):
        print(row, flush=True)
    rows = reconstructed_rows(queue, [0.05] if args.quick else [0.02, 0.05, 0.1],
                              [UNIFORM] if args.quick else [UNIFORM, ROTATION], args.seed)
    print("\n".join(rows[-2:]))


if __name__ == "__main__":
    main()
