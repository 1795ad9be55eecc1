"""Several plenoptic cameras in one reconstruction (docs/design.md §6.7, issue 49): one
camera, the same camera turned, and two cameras either side of the axis, on the same
world particles at the paper's optics and voxel, in the same run: ``process_pair``'s
vectors (lateral and depth RMS error over the valid vectors), the first volume's
particles recovered and ghosts, and seconds per pair.

    python benchmarks/cameras.py [--lenses 116 78] [--apart 25 [10 40 ...]] [--three]
                                 [--fine-iterations 5 4] [--seeds 1] [--seeding 0.05]
                                 [--repeats 1]

Cameras: the paper's optics (``paper_optics``), each looking at the world origin (the
grid's centre), turned about the world's y axis; two cameras ``--apart`` degrees apart
stand at plus and minus half of it (each separation given); three cameras (``--three``)
at minus, zero and plus the first separation. Scene: ``budget_scene``'s particles (0.8 px blur,
photon and read noise), uniform motion, each camera's images ray traced from the same
world particles. Each row runs ``process_pair``'s default chain (several cameras: the
joint reconstruction, and the particles fitted to every camera's raw images at once).
Each camera's projectors are built once before the rows, as a batch worker does, and
timed apart; ``--repeats`` times each pair that many times (the median; the same
vectors each time). Errors are in the world grid's voxels (x, y lateral; z depth, the axis the
cameras' optical axes straddle).
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from plenocl import get_queue, process_pair, simulate_image
from plenocl.bench.accuracy_section import SHIFT_VOX, budget_scene, paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import timed
from plenocl.camera import Pose
from plenocl.metrics import recovery
from plenocl.projection import Projector
from plenocl.reconstruction import ReconstructionSettings
from plenocl.reconstruction.settings import COARSE_OVERSAMPLE, EARLY_OVERSAMPLE, SUPERSAMPLE

#: How ``budget_scene`` traces its images (the other cameras' the same way).
TRACE = dict(rays_per_particle=2000, blur_px=0.8, photon_noise=True, background=20.0,
             read_noise=3.0)


def errors(piv) -> tuple[float, float, float]:
    """Lateral and depth RMS error (world voxels) of the valid vectors, and their share."""
    ok = piv.valid
    err = [piv.u[ok] - SHIFT_VOX[0], piv.v[ok] - SHIFT_VOX[1], piv.w[ok] - SHIFT_VOX[2]]
    lateral = np.sqrt(np.mean(err[0] ** 2 + err[1] ** 2) / 2)
    return float(lateral), float(np.sqrt(np.mean(err[2] ** 2))), float(ok.mean())


def built(proj: Projector) -> Projector:
    """``proj`` with the projectors a default reconstruction runs on and their
    sensitivities built (a batch builds them once per worker)."""
    proj.refined(SUPERSAMPLE).sensitivity()
    proj.sampled(COARSE_OVERSAMPLE).sensitivity()
    proj.refined(SUPERSAMPLE).sampled(EARLY_OVERSAMPLE).sensitivity()
    proj.queue.finish()
    return proj


def setups(apart: list[float], three: bool) -> list[tuple[str, list[float | None]]]:
    """Each row's cameras as turns about y (``None``: unposed): one camera, the first
    separation's one camera turned, two cameras at each separation, and (``three``)
    three cameras at minus, zero and plus the first separation."""
    first = apart[0] / 2
    rows = [("one camera (baseline)", [None]), (f"one camera turned {first:g} deg", [first])]
    rows += [(f"two cameras {a:g} deg apart", [-a / 2, a / 2]) for a in apart]
    if three:
        rows.append((f"three cameras {apart[0]:g} deg apart", [-apart[0], 0.0, apart[0]]))
    return rows


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[116, 78])
    parser.add_argument("--apart", type=float, nargs="+", default=[25.0])
    parser.add_argument("--fine-iterations", type=int, nargs="*", default=[],
                        help="also the first separation's two cameras with these many "
                             "sub-voxel iterations (the default schedule has 7)")
    parser.add_argument("--three", action="store_true",
                        help="also three cameras, the first separation apart")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--repeats", type=int, default=1,
                        help="time each pair this many times: the median")
    args = parser.parse_args()
    queue = get_queue()
    camera, grid = paper_optics(tuple(args.lenses))
    print(f"device: {queue.device.name.strip()}; {args.lenses[0]} x {args.lenses[1]} "
          f"lenses, world grid {grid.shape} (z, y, x), {args.seeding} particles per "
          "microlens; errors in world voxels")
    projectors = {}
    for _, turns in setups(args.apart, args.three):
        for t in turns:
            if t not in projectors:
                t0 = time.perf_counter()
                projectors[t] = built(Projector(camera.with_pose(
                    None if t is None else Pose((0.0, t, 0.0), (0, 0, 0))), grid, queue))
                print(f"camera turned {t or 0:g} deg: its projectors (refined, sampled) "
                      f"and sensitivities built once ({projectors[t].path}): "
                      f"{time.perf_counter() - t0:.1f} s")
    rows: dict[str, list[tuple]] = {}
    for seed in args.seeds:
        print(f"\nseed {seed}\n{HEADER}")
        scene = budget_scene(camera, grid, args.seeding, seed, queue)
        for label, turns in setups(args.apart, args.three):
            cams = [camera.with_pose(None if t is None else Pose((0.0, t, 0.0), (0, 0, 0)))
                    for t in turns]
            projs = [projectors[t] for t in turns]
            raws = [[simulate_image(c, p, 2e4, seed=100 * seed + 10 * k + j, queue=queue,
                                    **TRACE) for j, p in enumerate((scene.pa, scene.pb))]
                    for k, c in enumerate(cams)]
            pair, seconds = timed(partial(run_pair, raws, projs), args.repeats)
            record(rows, label, pair, scene, grid, seconds)
            if len(cams) == 2 and turns[1] == args.apart[0] / 2:
                for n in args.fine_iterations:
                    t0 = time.perf_counter()
                    pair = process_pair([r[0] for r in raws], [r[1] for r in raws], projs,
                                        reconstruction=ReconstructionSettings(iterations=n))
                    record(rows, f"{label}, {n} it.", pair, scene, grid,
                           time.perf_counter() - t0)
    print(f"\nRMS over the {len(args.seeds)} scene(s) (errors; the rest their mean)\n{HEADER}")
    for label, runs in rows.items():
        table = np.array(runs)
        print(line(label, *np.sqrt(np.mean(table[:, :2] ** 2, axis=0)),
                   *table[:, 2:].mean(axis=0)))


def run_pair(raws: list, projs: list):
    """``process_pair``'s default chain on each camera's two raw images (``raws[k]``),
    one camera's or several cameras' at once."""
    if len(projs) == 1:
        return process_pair(raws[0][0], raws[0][1], projs[0])
    return process_pair([r[0] for r in raws], [r[1] for r in raws], projs)


def record(rows: dict, label: str, pair, scene, grid, seconds: float) -> None:
    """One pair's row: printed, and kept under ``label`` for the pooled table."""
    rep = recovery(pair.vol_a, grid, scene.pa)
    row = (*errors(pair.piv), rep.fraction, rep.ghost_fraction, seconds)
    rows.setdefault(label, []).append(row)
    print(line(label, *row), flush=True)


HEADER = (f"{'cameras':32s} {'lateral':>8s} {'depth':>6s} {'valid':>6s} {'recov':>6s} "
          f"{'ghosts':>6s} {'s/pair':>7s}")


def line(label: str, lateral: float, depth: float, valid: float, recovered: float,
         ghosts: float, seconds: float) -> str:
    """One row of the table."""
    return (f"{label:32s} {lateral:8.3f} {depth:6.3f} {valid:6.0%} {recovered:6.0%} "
            f"{ghosts:6.0%} {seconds:7.1f}")


if __name__ == "__main__":
    main()
