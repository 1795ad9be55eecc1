"""Where the error sits as the camera grows: the same optics, voxel and seeding on
96 x 64 to 289 x 193 microlenses, stage by stage, by field position and depth (issue 45).

    python benchmarks/field_size.py [--lenses 96 64 116 78 192 128 289 193]
                                    [--seeding 0.05] [--seed 3] [--motion uniform]

Camera: the paper's optics (``paper_optics``: f = 50 mm, f/2.42, |M| = 0.66, 125 µm
lenses of f = 500 µm, 7.4 µm pixels) on each window of lenses, the paper's voxel
(0.183 x 0.175 x 0.133 mm) over 20 mm of depth just inside the field of view. Scene:
ray-traced particles at ``--seeding`` per microlens with 0.8 px blur, photon and read
noise, a uniform displacement of (2.3, -1.4, 1.7) voxels (``--motion rotation``: the
budget's 2° rotation about x, the truth each particle's own motion and, for vectors, the
motion at the window centres). For each size the table gives
the RMS error (lateral / depth voxels, and the count) of every stage of the default
chain (:mod:`plenocl.bench.fieldsize`): the volume's particles, the pairs of the two
volumes' particles, the same pairs fitted to the raw images, the correlation's vectors
and the final vectors; over everything, by distance from the optical axis and by depth
(the focal zone |z| < 2 mm); and the volume's raw peaks per true particle and the share
recovered. The last lines sum up the final vectors per size and their error 20-25 mm off
the axis over that on it.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import ROTATION, UNIFORM, paper_setup  # noqa: E402
from plenocl.bench.fieldsize import off_axis_ratio, size_split, split_table  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs="+",
                        default=[96, 64, 116, 78, 192, 128, 289, 193],
                        help="pairs of lens counts (columns rows)")
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--motion", default="uniform", choices=["uniform", "rotation"])
    args = parser.parse_args()
    if len(args.lenses) % 2:
        parser.error("--lenses takes pairs of counts (columns rows)")
    queue = get_queue()
    summary = []
    for cols, rows in zip(args.lenses[::2], args.lenses[1::2]):
        cam, grid, proj = paper_setup((cols, rows), queue)
        motion = {"uniform": UNIFORM, "rotation": ROTATION}[args.motion]
        split = size_split(cam, grid, proj, args.seeding, args.seed, queue, motion)
        print(split_table(split), "\n", flush=True)
        final = split.stages[-1]
        lat, dep, _ = final.rms()
        summary.append(f"{cols:4d} x {rows:<4d} vectors: lateral {lat:.3f} depth {dep:.3f} voxel"
                       + ("; 20-25 mm off the axis over on it: lateral {:.2f}x, depth {:.2f}x"
                          .format(*off_axis_ratio(final))
                          if all(np.isfinite(off_axis_ratio(final))) else ""))
    print("\n".join(summary))


if __name__ == "__main__":
    main()
