"""A region of interest off the sensor's centre (docs/design.md §2): particles seen
through the region against the same particles seen by the whole sensor on the same
grid, in the same run, and against the region described as a sensor of its own (its
axis at its own centre: what a camera file made for the region by hand gives).

    python benchmarks/region.py [--scenes 2] [--camera paper|synthetic]

``paper``: the paper's 16 MP camera (4904 x 3280 px, 289 x 193 lenses), a 1200 x 900 px
region whose centre lies 1148 px right of and 710 px below the sensor's (12.9 mm and
8.0 mm in the object). ``synthetic``: the 850 x 850 px camera, a 578 x 850 px region
136 px right of centre (the audit's scene of 2026-11-30). Per scene: particles at 0.05
per microlens of the region in its grid (``Grid.for_camera`` of the region's calibrated
camera, depths -2 to 2 mm), ray traced on the whole sensor with a 0.8 px blur, photon
noise and a background; the region's image is the whole frame's cut. Each camera is
calibrated from its own white image (the whole sensor's, or the region's cut of it) and
reconstructed by ``reconstruct()``'s default on that grid. Rows: particles matched
within 1.5 voxels laterally and 4 in depth, their RMS error (voxels), and the median
offset of every peak from its nearest true particle (mm; the frame's shift).
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import (  # noqa: E402
    Camera,
    Grid,
    Projector,
    calibrate,
    get_queue,
    random_particles,
    reconstruct,
    simulate_image,
    simulate_white_image,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.metrics import matched_errors  # noqa: E402
from plenocl.peaks import find_particles  # noqa: E402

#: (whole camera, region origin (column, row), region size (columns, rows))
SCENES = {"paper": (Camera.paper_16mp, (3000, 1900), (1200, 900)),
          "synthetic": (Camera.synthetic_850, (272, 0), (578, 850))}
ROWS = ("whole sensor (baseline)", "region, axis kept (crop_origin + full_pixels)",
        "region as a sensor of its own")


def own_sensor(region: Camera) -> Camera:
    """The region described as a camera of its own: its lenses and pixels, no record of
    where it lies on the sensor (its axis at its own centre)."""
    return Camera(region.focal_length_mm, region.f_number, region.magnification,
                  region.ml_pitch_mm, region.ml_focal_length_mm, region.ml_count,
                  region.pixel_pitch_mm, region.pixels)


def peak_offset(vol: np.ndarray, grid: Grid, truth: np.ndarray) -> np.ndarray:
    """Median offset (mm, x y z) of the volume's peaks from their nearest true particle."""
    idx, _ = find_particles(vol, 0.1)
    found = grid.from_index(idx)
    d = np.linalg.norm(found[:, None, :] - truth[None], axis=-1)
    return np.median(found - truth[d.argmin(1)], axis=0)


def scene(whole: Camera, origin, size, seed: int, queue) -> dict:
    """One scene's three rows: matched errors, peak offsets, particles, seconds."""
    region = whole.cropped(origin, size)
    white = simulate_white_image(whole, queue=queue)
    cut = (slice(origin[1], origin[1] + size[1]), slice(origin[0], origin[0] + size[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the region's count and the depth range's notes
        cams = (calibrate(white, whole), calibrate(white[cut], region),
                calibrate(white[cut], own_sensor(region)))
    grid = Grid.for_camera(cams[1], z=(-2.0, 2.0))
    count = max(4, round(0.05 * region.ml_count[0] * region.ml_count[1]))
    pos, inten = random_particles((grid.x, grid.y, grid.z), count=count, seed=seed,
                                  intensity=(2e4, 4e4))
    frame = simulate_image(whole, pos, inten, 3000, seed=seed, blur_px=0.8,
                           background=5.0, photon_noise=True, queue=queue)
    grids = (grid, grid, Grid.for_camera(cams[2], z=(-2.0, 2.0)))
    out = {}
    for label, cam, g, image in zip(ROWS, cams, grids, (frame, frame[cut], frame[cut])):
        start = time.perf_counter()
        vol = reconstruct(image, Projector(cam, g, queue))
        out[label] = (matched_errors(vol, g, pos, lateral=1.5, depth=4.0),
                      peak_offset(vol, g, pos), len(pos), time.perf_counter() - start)
    return out


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--camera", choices=sorted(SCENES), default="paper")
    args = parser.parse_args()
    queue = get_queue()
    make, origin, size = SCENES[args.camera]
    whole = make()
    print(f"device: {queue.device.name.strip()}; {args.camera} camera {whole.pixels} px, "
          f"region {size} px from {origin}")
    runs = [scene(whole, origin, size, 7 + k, queue) for k in range(args.scenes)]
    print(f"{'camera':48s} {'found':>9s} {'lateral':>8s} {'depth':>6s}  "
          f"{'peak offset x, y, z (mm)':>26s} {'s':>6s}")
    for label in ROWS:
        errs = np.vstack([run[label][0] for run in runs])
        offset = np.median([run[label][1] for run in runs], axis=0)
        total = sum(run[label][2] for run in runs)
        seconds = np.median([run[label][3] for run in runs])
        lat = np.sqrt(np.mean(errs[:, :2] ** 2)) if len(errs) else np.nan
        dep = np.sqrt(np.mean(errs[:, 2] ** 2)) if len(errs) else np.nan
        print(f"{label:48s} {len(errs):4d}/{total:<4d} {lat:8.3f} {dep:6.3f}  "
              f"{offset[0]:+8.3f} {offset[1]:+8.3f} {offset[2]:+8.3f} {seconds:6.1f}")


if __name__ == "__main__":
    main()
