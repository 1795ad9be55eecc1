"""The particle refinement's window means (docs/design.md §7.1): weighted by the pairs'
fitted uncertainties (the default) against the robust rule with the pairs alike (the
default of the early morning of 2026-11-29) and the search range alone with the pairs
alike (the refinement before it), on the same volumes, fits and pairs in the same run:
one camera and two cameras 25 degrees apart at the paper's optics.

    python benchmarks/robust_means.py [--lenses 116 78] [--seeds 1 2 3] [--seeding 0.05]

Scenes and cameras as ``benchmarks/cameras.py`` (``budget_scene``: 0.8 px blur, photon
and read noise, uniform motion; each camera's images ray traced from the same world
particles). Each pair is reconstructed and correlated once (``process_pair`` without
the particle refinement); the refinement (the fit to the raw images, the pairing and the
window means, ``plenocl.pipeline.velocity.refine_particles``) then runs once per rule
of :data:`RULES` on it. Errors: RMS of the valid vectors against the true
displacement, lateral and depth, in the world grid's voxels, the valid share, and the
RMS over every vector that is not masked (the outliers' replacements included: a
refinement that only flagged more vectors would not gain there).
"""

from __future__ import annotations

import numpy as np
from cameras import TRACE, built, errors

from plenocl import get_queue, process_pair, simulate_image
from plenocl.bench.accuracy_section import SHIFT_VOX, budget_scene, paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.camera import Pose
from plenocl.pipeline import PairSettings
from plenocl.pipeline.pair import known_backgrounds
from plenocl.pipeline.velocity import refine_particles
from plenocl.piv.refinement import ROBUST_SPREAD
from plenocl.projection import Projector

#: The rows: each camera's turn about y (``None``: unposed).
SETUPS = {"one camera": [None], "two cameras 25 deg apart": [-12.5, 12.5]}
#: The window means compared (``refine_particles``' ``spread`` and ``weighted``): the
#: default first.
RULES = {"fit-weighted (default)": dict(spread=None, weighted=True),
         f"robust (spread {ROBUST_SPREAD:g}), alike": dict(spread=ROBUST_SPREAD,
                                                           weighted=False),
         "search range alone, alike": dict(spread=None, weighted=False)}


def refined_both(raws: list, projs: list) -> dict[str, tuple]:
    """One pair's volumes and correlation, refined with each of :data:`RULES`."""
    several = len(projs) > 1
    args = (([r[0] for r in raws], [r[1] for r in raws], projs) if several
            else (raws[0][0], raws[0][1], projs[0]))
    pair = process_pair(*args, particles=False)
    if several:
        cams = [p.camera for p in projs]
        back = [known_backgrounds(a, b) for a, b in zip(pair.info_a.cameras,
                                                        pair.info_b.cameras, strict=True)]
        images = [[a, b] for a, b in raws]
    else:
        cams, back, images = projs[0].camera, known_backgrounds(pair.info_a, pair.info_b), raws[0]
    rows = {}
    for label, rule in RULES.items():
        piv = refine_particles(pair.piv, pair.vol_a, pair.vol_b, projs[0].grid,
                               PairSettings(), projs[0].queue, camera=cams, raws=images,
                               backgrounds=back, **rule)
        rows[label] = (*errors(piv), *every_vector(piv))
    return rows


def every_vector(piv) -> tuple[float, float]:
    """Lateral and depth RMS error over every vector not masked, replacements included."""
    ok = ~piv.masked
    err = [c[ok] - s for c, s in zip((piv.u, piv.v, piv.w), SHIFT_VOX)]
    return (float(np.sqrt(np.mean(err[0] ** 2 + err[1] ** 2) / 2)),
            float(np.sqrt(np.mean(err[2] ** 2))))


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[116, 78])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--seeding", type=float, default=0.05)
    args = parser.parse_args()
    queue = get_queue()
    camera, grid = paper_optics(tuple(args.lenses))
    print(f"device: {queue.device.name.strip()}; {args.lenses[0]} x {args.lenses[1]} lenses, "
          f"{args.seeding} particles per microlens; errors in world voxels")
    cams = {t: camera.with_pose(None if t is None else Pose((0.0, t, 0.0), (0, 0, 0)))
            for turns in SETUPS.values() for t in turns}
    projs = {t: built(Projector(c, grid, queue)) for t, c in cams.items()}
    pooled: dict[tuple[str, str], list] = {}
    print(f"{'seed':>4s} {'cameras':26s} {'window means':28s} {'lateral':>8s} {'depth':>6s} "
          f"{'valid':>6s} {'all: lat':>9s} {'depth':>6s}")
    for seed in args.seeds:
        scene = budget_scene(camera, grid, args.seeding, seed, queue)
        for name, turns in SETUPS.items():
            raws = [[simulate_image(cams[t], p, 2e4, seed=100 * seed + 10 * k + j,
                                    queue=queue, **TRACE)
                     for j, p in enumerate((scene.pa, scene.pb))]
                    for k, t in enumerate(turns)]
            for label, row in refined_both(raws, [projs[t] for t in turns]).items():
                pooled.setdefault((name, label), []).append(row)
                print(f"{seed:4d} {name:26s} {label:28s} {row[0]:8.3f} {row[1]:6.3f} "
                      f"{row[2]:6.0%} {row[3]:9.3f} {row[4]:6.3f}", flush=True)
    print(f"\nRMS over {len(args.seeds)} scene(s) (valid: mean)")
    for (name, label), rows in pooled.items():
        table = np.array(rows)
        lat, dep, _, all_lat, all_dep = np.sqrt(np.mean(table ** 2, axis=0))
        print(f"     {name:26s} {label:28s} {lat:8.3f} {dep:6.3f} {table[:, 2].mean():6.0%} "
              f"{all_lat:9.3f} {all_dep:6.3f}")


if __name__ == "__main__":
    main()
