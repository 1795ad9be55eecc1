"""The boundary-layer demo's errors by chain, in one run (issue 15)

    python benchmarks/demo_chains.py [--size paper|small] [--out DIR]

Runs ``plenocl demo --size SIZE`` into DIR (or resumes it: finished stages are skipped),
then, on the demo's raw images and sub-voxel volumes, in this process:

- **default**: the demo's chain (``process_pair``'s): correlation, then each window's
  vector from its particle pairs, the particles fitted to the raw images;
- **particles not fitted**: the same pairs at the volumes' peak positions;
- **correlation only**: the sub-voxel volumes correlated, no particle refinement;
- **before**: the single-frame MLEM reconstruction on the voxels themselves
  (``supersample=1``), correlation only: the chain before issue 15.

Each row: RMS error of the valid vectors against the truth averaged over each final
window and point-sampled, lateral (RMS over x and y) and depth, in voxels and % of U∞;
the depth / lateral ratio; valid fraction; seconds of the stage that differs. At paper
size about 20 minutes after the demo on 2 CPU cores (most of it the window-averaged
truth of each row).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Camera, Projector, get_queue, piv3d, reconstruct  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.demo.boundary_layer import (  # noqa: E402
    DT,
    CameraFrameFlow,
    lateral_depth_errors,
    measured_and_true,
    run_boundary_layer,
    scenario,
    window_averaged,
)
from plenocl.io import read_image  # noqa: E402
from plenocl.piv.imagefit import ImageFit  # noqa: E402
from plenocl.piv.refinement import FocalZone, SightLines, refine_with_particles  # noqa: E402
from plenocl.vectorfield import save_field  # noqa: E402
from plenocl.volumefile import load_volume  # noqa: E402


def errors(res, path: Path, sc, flow) -> dict:
    """Lateral and depth errors of a field against the window-averaged and point truth."""
    save_field(path, res, dt=DT, grid=sc.grid)
    meas, true, valid, coords = measured_and_true(path, sc, flow)
    averaged = window_averaged(res.window, coords, sc, flow)
    out = lateral_depth_errors(meas, {"window": averaged, "point": true}, valid, sc)
    out["valid"] = float(valid.mean())
    return out


def row(label: str, e: dict, seconds: float) -> str:
    w, p = e["window"], e["point"]
    return (f"| {label} | {w['lateral_voxels']:.3f} / {w['depth_voxels']:.3f} "
            f"({100 * w['lateral_u_inf']:.1f} / {100 * w['depth_u_inf']:.1f} %) | "
            f"**{w['depth_voxels'] / w['lateral_voxels']:.2f}** | "
            f"{p['lateral_voxels']:.3f} / {p['depth_voxels']:.3f} | "
            f"{p['depth_voxels'] / p['lateral_voxels']:.2f} | {e['valid']:.0%} | "
            f"{seconds:.0f} |")


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--size", default="paper", choices=["small", "paper"])
    parser.add_argument("--out", default=None, help="demo folder (default: demo_SIZE)")
    args = parser.parse_args()
    out = Path(args.out or f"demo_{args.size}")
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}")
    run_boundary_layer(args.size, out, queue=queue, figures=False)
    sc = scenario(args.size)
    flow = CameraFrameFlow(sc, 0)
    cam = Camera.from_toml(out / "camera_calibrated.toml")
    raws = [read_image(out / f"raw_{tag}.tif") for tag in "ab"]
    vol_a, vol_b = (load_volume(out / f"vol_{tag}.npz")[0] for tag in "ab")
    focus = FocalZone.of(sc.camera, sc.grid)
    t0 = time.perf_counter()
    corr = piv3d(vol_a, vol_b, windows=sc.windows, queue=queue)
    rows, t_corr = {}, time.perf_counter() - t0
    for label, fit in (("**default** (particles fitted to the raw images)",
                        ImageFit(cam, sc.grid, raws)), ("particles not fitted", None)):
        t0 = time.perf_counter()
        res = refine_with_particles(corr, vol_a, vol_b, focus=focus, fit=fit,
                                    sight=SightLines.of(sc.camera, sc.grid))
        rows[label] = (res, time.perf_counter() - t0)
    rows["correlation only (sub-voxels)"] = (corr, t_corr)
    t0 = time.perf_counter()
    proj = Projector(cam, sc.grid, queue)
    before = [reconstruct(raw, proj, "mlem", sc.iterations, supersample=1) for raw in raws]
    rows["before (voxels, correlation only)"] = (piv3d(*before, windows=sc.windows, queue=queue),
                                                 time.perf_counter() - t0)
    print(f"\n{args.size} demo, final window {corr.window} (z, y, x voxels)\n")
    print("| chain | window-averaged truth: lateral / depth voxels (% of U∞) | depth / "
          "lateral | point truth: lateral / depth | ratio | valid | s |")
    print("|---|---|---|---|---|---|---|")
    for k, (label, (res, seconds)) in enumerate(rows.items()):
        print(row(label, errors(res, out / f"field_chain{k}.npz", sc, flow), seconds),
              flush=True)


if __name__ == "__main__":
    main()
