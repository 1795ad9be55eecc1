"""Why the cubic case's focal zone resists (issue 47): the images a single plenoptic camera
makes there, what they allow a reconstruction to know, and where the default's misses fall.

    python benchmarks/focal_zone.py [--particles 12] [--scenes 6] [--counts 20 60]

Camera: the 850 x 850 px synthetic camera (50 x 50 microlenses, M = 1, f/2), whose
depth resolution is 0.5 mm; grid: ``benchmarks/cubic_recovery.py``'s 5 mm cube on 40^3
voxels of 0.125 mm, whose voxel edges fall on the lens cells' edges. Near the focal
plane a particle's defocus disc on the array (radius ``r = |z| / (2 x depth
resolution)`` lenses) lies in one lens cell or crosses an edge by a chord; behind each
lens the pixels see the aperture, so the image holds only where each crossed edge cuts
the aperture, ``u = e / r`` (``e``: the disc centre's distance to the edge, in lenses).
Scaling the particle's distance to the edge and its depth by one factor ``λ`` keeps every
cut: the image stays the same along that line through the edge at the focal plane, as
long as the disc reaches no other edge.

1. **The lines, ray traced**: particles in the focal zone whose disc crosses an edge
   (seeds 3000 + k, 400,000 rays, no blur), each against itself moved along its line
   (``λ`` 0.5 and 0.8, and 0.9 and 1.3 times the line's end, where the scaled disc
   reaches another edge) and against itself moved by the same depth alone; the relative
   difference of the images (``|a - b| / |a|``, one ray seed) beside the ray noise (the
   same particle with another seed).
2. **What the images allow**: on ``cubic_recovery.py``'s scenes (seeds 1000 + k, 1 px
   blur), each particle with ``|z|`` under the depth resolution by class: its disc in one
   cell (the depth known up to its sign: the best guess is the focal plane), crossing one
   edge, or two (a corner; the depth known up to the line: anywhere in ``(0, z_max]``,
   where the scaled disc reaches another edge; the best single guess is the middle). The
   share an estimator that knew each line could place within 2 voxels is the ceiling the
   images set.
3. **Where the default's misses fall** (``reconstruct()``'s default, a peak within 1 voxel
   laterally and 2 in depth, one to one, as ``cubic_recovery.py``): recovered per class,
   and each missed focal-zone particle's cut ``c = e / r`` (the smallest of the crossed
   edges') and the depth its nearest peak took.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Camera, Grid, Projector, get_queue  # noqa: E402
from plenocl.bench.core import particle_scene  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.metrics import match_particles  # noqa: E402
from plenocl.peaks import find_particles  # noqa: E402
from plenocl.projection.weighting import lens_index_map  # noqa: E402
from plenocl.reconstruction import reconstruct  # noqa: E402
from plenocl.simulate import simulate_image  # noqa: E402

CUBIC = Grid((40, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
#: The factors along each particle's line (part 1), inside every line.
FACTORS = (0.5, 0.8)
#: Rays per particle image in part 1, and the match's depth tolerance (voxels).
RAYS = 400_000
DEPTH_TOL = 2.0
CLASSES = ("one cell", "one edge", "corner")


def chief_lens(camera: Camera, positions: np.ndarray) -> np.ndarray:
    """``(n, 2)`` fractional lens indices (centres at integers, the weighting's
    :func:`lens_index_map`) where each point's chief ray (through the exit pupil's
    centre) meets the array: its defocus disc's centre (a rectangular array)."""
    image = camera.image_points(positions)
    hit = image[:, :2] * (camera.exit_pupil_distance_mm / image[:, 2])[:, None]
    return np.column_stack(lens_index_map(camera)(hit[:, 0], hit[:, 1]))


def disc_radius(camera: Camera, positions: np.ndarray) -> np.ndarray:
    """The defocus disc's radius on the array, in lenses, of each point."""
    dp = camera.image_points(positions)[:, 2]
    d = camera.exit_pupil_distance_mm
    return camera.exit_pupil_diameter_mm / 2 * np.abs(d - dp) / dp / camera.ml_pitch_mm


def edges(camera: Camera, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: the distance ``(n, 2)`` from its disc's centre to the nearest cell edge
    per axis (lenses), the sign ``(n, 2)`` towards it, and which axes' edges the disc
    crosses ``(n, 2)``."""
    t = chief_lens(camera, positions)
    off = t - np.round(t)
    e = 0.5 - np.abs(off)
    return e, np.where(off >= 0, 1.0, -1.0), e < disc_radius(camera, positions)[:, None]


def along_line(camera: Camera, position: np.ndarray, factor: float) -> np.ndarray:
    """``position`` moved along its line through the crossed edges at the focal plane:
    its disc centre's distance to each crossed edge and its depth times ``factor``."""
    e, toward, cross = (a[0] for a in edges(camera, position[None]))
    target = chief_lens(camera, position[None])[0] + np.where(cross, toward * e, 0.0) * (
        1.0 - factor)
    z = position[2] * factor
    # the chief ray's lens index is affine in the lateral position at one depth
    at = chief_lens(camera, np.array([[0.0, 0.0, z], [1.0, 1.0, z]]))
    return np.array([*((target - at[0]) / (at[1] - at[0])), z])


def line_images(camera: Camera, count: int, queue) -> dict[str, list[float]]:
    """Part 1: relative image differences along each particle's line (at the factors
    :data:`FACTORS` and at 0.9 and 1.3 times its end, :func:`line_extent`), by the same
    depths alone, and between ray seeds."""
    rng = np.random.default_rng(3000)
    out: dict[str, list[float]] = {}
    done = 0
    while done < count:
        p = np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(-0.45, 0.45)])
        if not edges(camera, p[None])[2].any():
            continue
        image = _traced(camera, p, 1, queue)
        norm = np.linalg.norm(image)
        out.setdefault("ray noise (another seed)", []).append(
            np.linalg.norm(image - _traced(camera, p, 2, queue)) / norm)
        end = line_extent(camera, p[None], free_to_centre=False)[1][0] / abs(p[2])
        for label, lam in [*((f"λ {f:g}", f) for f in FACTORS),
                           ("0.9 x the line's end", 0.9 * end), ("1.3 x its end", 1.3 * end)]:
            moved = along_line(camera, p, lam)
            depth_only = np.array([p[0], p[1], moved[2]])
            for kind, q in (("along the line", moved), ("depth alone", depth_only)):
                out.setdefault(f"{kind}, {label}", []).append(
                    np.linalg.norm(image - _traced(camera, q, 1, queue)) / norm)
        done += 1
    return out


def _traced(camera: Camera, position: np.ndarray, seed: int, queue) -> np.ndarray:
    """One particle's noise-free ray-traced image (float64)."""
    return simulate_image(camera, position[None], 3e4, RAYS, seed=seed,
                          queue=queue).astype(np.float64)


def line_extent(camera: Camera, positions: np.ndarray, free_to_centre: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per point: its class (0 one cell, 1 one edge, 2 corner) and the largest ``|z|``
    its images allow (mm): in one cell the disc's room in it, on a line where the scaled
    disc reaches another edge; ``free_to_centre``: an axis whose edges the disc does not
    cross may move to its cell's centre on the way (the image does not change), else it
    stays."""
    e, _, cross = edges(camera, positions)
    r = disc_radius(camera, positions)[:, None]
    kind = cross.sum(axis=1)
    free = 0.5 / r if free_to_centre else e / r
    lam = np.min(np.where(cross, 1.0 / (e + r), free), axis=1)
    room = np.min(e / r, axis=1) * np.abs(positions[:, 2])  # the disc as wide as it may be
    return kind, np.where(kind == 0, room, lam * np.abs(positions[:, 2]))


def ideal_depth_ok(camera: Camera, positions: np.ndarray, tol_mm: float) -> np.ndarray:
    """Whether the best single depth the images allow lies within ``tol_mm`` of each
    point's: the focal plane for a disc in one cell (its sign unknown), the middle of
    ``(0, z_max]`` on a line."""
    kind, z_max = line_extent(camera, positions)
    z = np.abs(positions[:, 2])
    guess = np.where(kind == 0, 0.0, z_max / 2.0)
    return np.abs(z - guess) <= tol_mm + 1e-12


def scene_rows(camera: Camera, projector: Projector, counts, scenes: int, queue):
    """Parts 2 and 3 on ``cubic_recovery.py``'s scenes: per focal-zone particle its class,
    whether the default recovered it, whether the ideal estimate would, its cut and its
    nearest peak's depth; and the recovery of all particles."""
    rows, totals = [], {}
    for count in counts:
        got = 0
        for k in range(scenes):
            pos, _, img = particle_scene(camera, count, 1000 + k, blur_px=1.0, queue=queue)
            found, _ = find_particles(reconstruct(img, projector), 0.1)
            truth = CUBIC.to_index(pos)
            matched = {t for t, _ in match_particles(found, truth, 1.0, DEPTH_TOL)}
            got += len(matched)
            rows += _focal_rows(camera, pos, found, truth, matched)
        totals[count] = got / (count * scenes)
    return rows, totals


def _focal_rows(camera: Camera, pos, found, truth, matched) -> list[tuple]:
    """The rows of one scene's focal-zone particles (see :func:`scene_rows`)."""
    focal = np.flatnonzero(np.abs(pos[:, 2]) < camera.depth_resolution_mm)
    if not len(focal):
        return []
    kind, _ = line_extent(camera, pos[focal])
    ideal = ideal_depth_ok(camera, pos[focal], DEPTH_TOL * CUBIC.spacing[0])
    e, _, cross = edges(camera, pos[focal])
    r = disc_radius(camera, pos[focal])
    cut = np.min(np.where(cross, e / r[:, None], np.inf), axis=1)
    out = []
    for i, t in enumerate(focal):
        d = found - truth[t]
        near = np.argmin(np.hypot(np.hypot(d[:, 0], d[:, 1]), d[:, 2] / DEPTH_TOL))
        peak_z = pos[t, 2] + d[near, 2] * CUBIC.spacing[0]
        out.append((int(kind[i]), t in matched, bool(ideal[i]), cut[i], pos[t, 2], peak_z))
    return out


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--particles", type=int, default=12)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--counts", type=int, nargs="+", default=[20, 60])
    args = parser.parse_args()
    queue = get_queue()
    cam = Camera.synthetic_850()
    print(f"device: {queue.device.name.strip()}; depth resolution "
          f"{cam.depth_resolution_mm:.3f} mm; voxel {CUBIC.spacing[0]:.3f} mm")
    print(f"1. {args.particles} focal-zone particles crossing an edge, {RAYS:,} rays: "
          "image difference |a - b| / |a|, median (max)")
    for label, values in line_images(cam, args.particles, queue).items():
        print(f"   {label:40s} {np.median(values):6.3f} ({np.max(values):.3f})")
    rows, totals = scene_rows(cam, Projector(cam, CUBIC, queue), args.counts, args.scenes,
                              queue)
    _print_scenes(rows, totals, len(args.counts) * args.scenes)


def _print_scenes(rows: list[tuple], totals: dict, scenes: int) -> None:
    """Parts 2 and 3."""
    a = np.array([r[:3] for r in rows], float)
    print(f"2-3. focal-zone particles (|z| < the depth resolution) of {scenes} scenes: "
          "class, count, the ideal estimate within 2 voxels, the default's recovered")
    for k, name in enumerate(CLASSES):
        sel = a[:, 0] == k
        print(f"   {name:9s} {int(sel.sum()):4d}   ideal {a[sel, 2].mean():6.1%}   "
              f"default {a[sel, 1].mean():6.1%}")
    print(f"   all      {len(a):4d}   ideal {a[:, 2].mean():6.1%}   default "
          f"{a[:, 1].mean():6.1%}")
    print("   recovered of all particles (default): " + ", ".join(
        f"{count}: {share:.1%}" for count, share in totals.items()))
    print("   the default's focal-zone misses: class, cut c = e / r, depth -> its nearest "
          "peak's (mm)")
    for kind, ok, _, cut, z, peak_z in sorted(rows, key=lambda r: (r[0], r[3])):
        if not ok:
            text = "-" if not np.isfinite(cut) else f"{cut:.2f}"
            print(f"     {CLASSES[kind]:9s} c {text:>5s}   z {z:+.2f} -> {peak_z:+.2f}")


if __name__ == "__main__":
    main()
