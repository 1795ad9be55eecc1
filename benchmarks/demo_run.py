"""The built-in example's figures, from a fresh folder: what ``plenocl demo`` prints.

    python benchmarks/demo_run.py [--size small|paper] [--layout rectangular|hexagonal]

Runs the boundary-layer demo (the README's first command) in a new temporary folder, so
that nothing is resumed from an earlier run, and prints its summary: the velocity RMS
error against the window-averaged truth (lateral and depth, in voxels and % of U∞), the
valid vectors, the mean profile's error, and the particles recovered by the default
reconstruction beside the paper's MART on the same images (the baseline), with the
wall time.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.demo.boundary_layer import run_boundary_layer  # noqa: E402


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--size", choices=["small", "paper"], default="small")
    parser.add_argument("--layout", choices=["rectangular", "hexagonal"],
                        default="rectangular")
    args = parser.parse_args()
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


if __name__ == "__main__":
    sys.exit(main())
