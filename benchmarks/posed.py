"""A world grid projected through a posed camera (docs/design.md §5.5, issue 49 item 2)
beside the unposed camera on the same grid, in the same run: the projector's forward +
back time on the voxels and on 3 x 3 sub-voxels (medians), a default reconstruction's
time and the particles it recovers, and (``--pair``) ``process_pair``'s vectors.

    python benchmarks/posed.py [--lenses 116 78] [--angles 12.5 25] [--repeats 5]
                               [--seeding 0.05] [--seed 1] [--pair]

Camera: the paper's optics (``paper_optics``) and its grid; a posed camera is turned by
each angle about the world's y axis and looks at the world origin (the grid's centre),
as one of two cameras that many degrees apart from the axis would. Scene:
``budget_scene`` (0.8 px blur, photon and read noise), uniform motion, the particles in
world coordinates; errors are RMS over the valid vectors in the world grid's voxels.
"""

from __future__ import annotations

import time

import numpy as np

from plenocl import get_queue, process_pair, reconstruct
from plenocl.bench.accuracy_section import SHIFT_VOX, budget_scene, paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.camera import Pose
from plenocl.metrics import recovery
from plenocl.projection import Projector


def projection_seconds(proj: Projector, repeats: int) -> float:
    """Median seconds of one forward and one back projection of a sparse volume."""
    rng = np.random.default_rng(0)
    vol = np.where(rng.random(proj.grid.shape) < 0.01, 1.0, 0.0).astype(np.float32)
    slabs = proj.volume_to_device(vol)
    img = proj.forward_device(slabs)

    def once():
        proj.forward_device(slabs, img)
        proj.back_device(img)
        proj.queue.finish()
    return median_time(once, repeats)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[116, 78])
    parser.add_argument("--angles", type=float, nargs="+", default=[12.5, 25.0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--pair", action="store_true", help="also process_pair's vectors")
    args = parser.parse_args()
    queue = get_queue()
    camera, grid = paper_optics(tuple(args.lenses))
    print(f"device: {queue.device.name.strip()}; {args.lenses[0]} x {args.lenses[1]} "
          f"lenses, world grid {grid.shape} (z, y, x), {args.seeding} particles per "
          f"microlens, seed {args.seed}")
    print(f"{'camera':24s} {'path':9s} {'frame grid':16s} {'fwd+back s':>10s} "
          f"{'x unposed':>9s} {'3x3 s':>7s} {'x unposed':>9s} {'rec s':>6s} {'recov':>6s}"
          + ("   lateral  depth  valid  s/pair" if args.pair else ""))
    base = {}
    for angle in [0.0, *args.angles]:
        pose = None if angle == 0 else Pose((0.0, angle, 0.0), (0.0, 0.0, 0.0))
        cam = camera.with_pose(pose)
        proj = Projector(cam, grid, queue)
        coarse = projection_seconds(proj, args.repeats)
        fine = projection_seconds(proj.refined(3), max(2, args.repeats // 2))
        base = base or {"coarse": coarse, "fine": fine}
        scene = budget_scene(cam, grid, args.seeding, args.seed, queue)
        reconstruct(scene.raw_a, proj)  # the refined and sampled projectors built
        t0 = time.perf_counter()
        vol = reconstruct(scene.raw_a, proj)
        rec_s = time.perf_counter() - t0
        label = "unposed (baseline)" if pose is None else f"turned {angle:g} deg about y"
        shape = "-" if proj.frame is None else "x".join(map(str, proj.frame.grid.shape))
        line = (f"{label:24s} {proj.path:9s} {shape:16s} {coarse:10.3f} "
                f"{coarse / base['coarse']:8.2f}x {fine:7.2f} {fine / base['fine']:8.2f}x "
                f"{rec_s:6.1f} {recovery(vol, grid, scene.pa).fraction:6.0%}")
        if args.pair:
            line += pair_line(scene, proj)
        print(line, flush=True)


def pair_line(scene, proj: Projector) -> str:
    """``process_pair``'s lateral and depth RMS error (world voxels), valid share and
    seconds."""
    t0 = time.perf_counter()
    piv = process_pair(scene.raw_a, scene.raw_b, proj).piv
    ok = piv.valid
    err = [piv.u[ok] - SHIFT_VOX[0], piv.v[ok] - SHIFT_VOX[1], piv.w[ok] - SHIFT_VOX[2]]
    lateral = np.sqrt(np.mean(err[0] ** 2 + err[1] ** 2) / 2)
    return (f"   {lateral:7.3f} {np.sqrt(np.mean(err[2] ** 2)):6.3f} {ok.mean():6.0%} "
            f"{time.perf_counter() - t0:7.1f}")


if __name__ == "__main__":
    main()
