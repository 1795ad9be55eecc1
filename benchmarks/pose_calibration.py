"""Cameras' poses calibrated (docs/design.md §2.3, issue 49 item 4): from a dot target at
known world positions (``plenocl.calibrate_pose``), and refined from the particle images
themselves (``self_calibrate``), on ray-traced images with 0.8 px blur, photon and read
noise, against the true poses of the same run.

    python benchmarks/pose_calibration.py [--lenses 40 30] [--exposures 5] [--error 1.3]

Target: plates of 4 x 4 dots 1 mm apart at three depths, seen by one camera turned
-12.5 degrees about y, from a guess 0.65 degree and 0.2 mm off; the pose's angle and
translation errors and the dots' residual. Self-calibration: two cameras 25 degrees
apart (the first holds the world frame), the second's pose wrong by ``--error`` times
(0.05, 0.03, -0.08) degrees and (0.02, -0.025, 0.01) mm, ``--exposures`` exposures of 60
particles; per round each camera's systematic disparity (the RMS of its sensor
quadrants' mean disparity vectors) and single-particle RMS disparity; the true poses'
disparities on the same particles are the floor.
"""

from __future__ import annotations

import time

import numpy as np

from plenocl import Grid, calibrate_pose, get_queue, simulate_image
from plenocl.bench.accuracy_section import paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.camera import Pose
from plenocl.pipeline.posecal import self_calibrate

NOISE = dict(blur_px=0.8, photon_noise=True, background=20.0, read_noise=3.0)


def target_row(cam, queue) -> None:
    """The dot target's calibration of one camera."""
    true = Pose((2.0, -12.0, 1.0), (0.1, -0.15, 0.2))
    guess = Pose((2.5, -12.3, 1.2), (0.2, -0.05, 0.35))
    xs = np.linspace(-1.5, 1.5, 4)
    x, y = np.meshgrid(xs, 0.8 * xs)
    plates = [np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
              for z in (-3.0, 0.0, 3.0)]
    images = [simulate_image(cam.with_pose(true), dots, 2e4, 4000, seed=k, queue=queue,
                             **NOISE) for k, dots in enumerate(plates)]
    t0 = time.perf_counter()
    found = calibrate_pose(cam, images, plates, guess, queue=queue)
    shift = true.shift_mm(found.pose)
    print(f"dot target: guess off {true.turn_deg(guess):.3f} deg; found off "
          f"{true.turn_deg(found.pose):.4f} deg and {shift:.4f} mm; residual "
          f"{found.residual_px:.2f} px (at the guess {found.start_residual_px:.2f}); "
          f"{found.dots} dots, {found.rounds} rounds, {time.perf_counter() - t0:.1f} s")


def self_rows(cam, exposures: int, error: float, queue) -> None:
    """Self-calibration of a second camera's pose from the particles."""
    true = [Pose((0.0, -12.5, 0.0), (0, 0, 0)), Pose((0.0, 12.5, 0.0), (0, 0, 0))]
    wrong = Pose((0.05 * error, 12.5 + 0.03 * error, -0.08 * error),
                 (0.02 * error, -0.025 * error, 0.01 * error))
    grid = Grid((60, 30, 38), x=(-3.5, 3.5), y=(-2.6, 2.6), z=(-4.0, 4.0))
    rng = np.random.default_rng(3)
    images: list[list] = [[], []]
    for k in range(exposures):
        pos = rng.uniform([-3.0, -2.2, -3.5], [3.0, 2.2, 3.5], (60, 3))
        for c, pose in enumerate(true):
            images[c].append(simulate_image(cam.with_pose(pose), pos, 2e4, 4000,
                                            seed=10 * k + c, queue=queue, **NOISE))
    truth = self_calibrate([cam.with_pose(p) for p in true], images, grid, rounds=0,
                           queue=queue)
    t0 = time.perf_counter()
    found = self_calibrate([cam.with_pose(true[0]), cam.with_pose(wrong)], images, grid,
                           queue=queue)
    seconds = time.perf_counter() - t0
    print(f"\nself-calibration: {exposures} exposures, {found.particles} particles; "
          f"disparity (px): systematic camera 1, camera 2 | single particles")
    print(f"{'true poses (floor)':20s} {truth.disparity_px[0][0]:6.3f} "
          f"{truth.disparity_px[0][1]:6.3f} | {truth.scatter_px[0][0]:6.3f} "
          f"{truth.scatter_px[0][1]:6.3f}")
    for k, (sys_px, one_px) in enumerate(zip(found.disparity_px, found.scatter_px,
                                             strict=True)):
        label = "start" if k == 0 else f"round {k}"
        print(f"{label:20s} {sys_px[0]:6.3f} {sys_px[1]:6.3f} | {one_px[0]:6.3f} "
              f"{one_px[1]:6.3f}")
    print(f"{seconds:.1f} s; camera 2's pose off the truth {true[1].turn_deg(wrong):.3f} "
          f"deg before, {true[1].turn_deg(found.cameras[1].pose):.3f} after (what the "
          "particles cannot tell stays)")


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[40, 30])
    parser.add_argument("--exposures", type=int, default=5)
    parser.add_argument("--error", type=float, default=1.3)
    args = parser.parse_args()
    queue = get_queue()
    cam, _ = paper_optics(tuple(args.lenses))
    print(f"device: {queue.device.name.strip()}; the paper's optics on {args.lenses[0]} x "
          f"{args.lenses[1]} lenses")
    target_row(cam, queue)
    self_rows(cam, args.exposures, args.error, queue)


if __name__ == "__main__":
    main()
