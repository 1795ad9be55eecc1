"""The built-in example's figures, from a fresh folder: what ``plenocl demo`` prints.

    python benchmarks/demo_run.py [--size small|paper] [--layout rectangular|hexagonal]
                                  [--cameras 1|2]

Runs the boundary-layer demo (the README's first command) in a new temporary folder, so
that nothing is resumed from an earlier run, and prints its summary: the velocity RMS
error against the window-averaged truth (lateral and depth, in voxels and % of U∞), the
valid vectors, the mean profile's error, and the particles recovered by the default
reconstruction beside the paper's MART on the same images (the baseline), with the
wall time. ``--cameras 2``: the small demo seen by two cameras 25 degrees apart, each
calibrated (lenses, and pose from a dot target), against the first camera alone on the
same particles (the baseline).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.demo.boundary_layer import run_boundary_layer  # noqa: E402
from plenocl.demo.two_cameras import run_two_cameras  # noqa: E402


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--size", choices=["small", "paper"], default="small")
    parser.add_argument("--layout", choices=["rectangular", "hexagonal"],
                        default="rectangular")
    parser.add_argument("--cameras", type=int, choices=[1, 2], default=1)
    args = parser.parse_args()
    if args.cameras == 2:
        return two_cameras()
    with tempfile.TemporaryDirectory(prefix="plenocl-demo-") as out:
        start = time.perf_counter()
        s = run_boundary_layer(args.size, out, figures=False, layout=args.layout,
                               log=lambda line: None)
        wall = time.perf_counter() - start
    win = s["lateral_depth_error"]["window_averaged"]
    print(f"boundary layer, {args.size}, {args.layout} array: {wall:.0f} s")
    print(f"velocity RMS error {100 * s['velocity_rms_error']:.1f} % of U∞, "
          f"{100 * s['valid_fraction']:.0f} % of {s['vectors']} vectors valid")
    print(f"lateral {win['lateral_voxels']:.3f} voxel ({100 * win['lateral_u_inf']:.1f} %), "
          f"depth {win['depth_voxels']:.3f} voxel ({100 * win['depth_u_inf']:.1f} %), "
          "against the window-averaged truth")
    print(f"mean profile within {100 * s['mean_profile_rms_error']:.1f} % of U∞")
    print("| reconstruction | recovered | ghost intensity |")
    print("|---|---|---|")
    for label, rec in s["recovery"].items():
        print(f"| {label} | {100 * rec['recovered_fraction']:.0f} % of {rec['particles']} | "
              f"{100 * rec['ghost_fraction']:.0f} % |")
    return 0


def two_cameras() -> int:
    """The two-camera demo's summary, from a fresh folder."""
    with tempfile.TemporaryDirectory(prefix="plenocl-demo2-") as out:
        start = time.perf_counter()
        s = run_two_cameras(out, log=lambda line: None)
        wall = time.perf_counter() - start
    print(f"boundary layer, small, two cameras {s['apart_deg']:.0f} deg apart: {wall:.0f} s")
    print("| field | lateral (voxel, % U∞) | depth (voxel, % U∞) | valid | recovered | "
          "ghosts |")
    print("|---|---|---|---|---|---|")
    for label, f in s["fields"].items():
        print(f"| {label} | {f['lateral_voxels']:.3f}, {100 * f['lateral_u_inf']:.1f} % | "
              f"{f['depth_voxels']:.3f}, {100 * f['depth_u_inf']:.1f} % | "
              f"{100 * f['valid_fraction']:.0f} % | {100 * f['recovered_fraction']:.0f} % | "
              f"{100 * f['ghost_fraction']:.0f} % |")
    for k, p in enumerate(s["pose_errors"], start=1):
        print(f"camera {k}'s pose from the dot target: {p['angle_deg']:.4f} deg, "
              f"{p['translation_mm']:.4f} mm off the truth")
    return 0


if __name__ == "__main__":
    sys.exit(main())
