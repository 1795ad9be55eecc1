"""A thick main lens (issue 29): particles traced element by element through a two-element
objective (``plenocl.bench.objective``), reconstructed on the thick camera that describes
it, beside the baselines in the same run: a thin lens's own particles on its own camera
(the same image-side cone), the objective's particles on that thin lens (what users
computed by hand before), and the objective described by its nominal f-number alone (the
pupils ignored, calibrated centres given).

    python benchmarks/thick_lens.py [--scenes 3]

Per scene: 12 particles within 1.2 mm laterally and 1.7 mm of the focal plane, 20,000
rays each, 1 px blur, photon noise; ``reconstruct()``'s default on 24 x 24 x 32 voxels.
Errors: RMS over the matched particles of all scenes (within 1.5 voxels laterally, 4 in
depth), lateral and depth separately.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import Camera, Projector, get_queue, simulate_image  # noqa: E402
from plenocl.bench.objective import (  # noqa: E402
    GRID,
    MAGNIFICATION,
    thick_camera,
    thin_camera,
    trace_objective,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.metrics import matched_errors  # noqa: E402
from plenocl.reconstruction import reconstruct  # noqa: E402


def nominal_camera() -> Camera:
    """The objective as a thin lens of its focal length and nominal f-number, with the
    thick camera's (calibrated) centres: the pupils ignored."""
    cam = thick_camera()
    with warnings.catch_warnings():  # its micro-images overlap by 41 %: it says so
        warnings.simplefilter("ignore")
        return Camera(cam.focal_length_mm, cam.f_number, MAGNIFICATION, cam.ml_pitch_mm,
                      cam.ml_focal_length_mm, cam.ml_count, cam.pixel_pitch_mm, cam.pixels
                      ).with_centers(cam.ideal_microlens_centers())


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--scenes", type=int, default=3)
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}; thick camera: {thick_camera().describe()}")
    rows = {"thick camera, objective's particles": [], "thin lens, its own particles": [],
            "thin lens of the same cone, objective's": [],
            "nominal f-number (pupils ignored), objective's": []}
    for seed in range(args.scenes):
        rng = np.random.default_rng(11 + seed)
        pos = np.column_stack([rng.uniform(-1.2, 1.2, (12, 2)), rng.uniform(-1.7, 1.7, 12)])
        traced = rng.poisson(2e4 * trace_objective(thick_camera(), pos, 20_000, 3, 1.0))
        thin = simulate_image(thin_camera(), pos, np.full(12, 2e4), 20_000, seed=3,
                              blur_px=1.0, photon_noise=True, queue=queue)
        for out, (image, cam) in zip(rows.values(), (
                (traced, thick_camera()), (thin, thin_camera()), (traced, thin_camera()),
                (traced, nominal_camera()))):
            out.append(matched_errors(reconstruct(image, Projector(cam, GRID, queue)), GRID,
                                      pos, lateral=1.5, depth=4.0))
    print(f"{'camera':48s} {'lateral':>8s} {'depth':>6s} {'found':>6s}")
    for label, errs in rows.items():
        d = np.vstack(errs)
        print(f"{label:48s} {np.sqrt(np.mean(d[:, :2] ** 2)):8.3f} "
              f"{np.sqrt(np.mean(d[:, 2] ** 2)):6.3f} {len(d):3d}/{12 * args.scenes}")


if __name__ == "__main__":
    main()
