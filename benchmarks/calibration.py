"""Calibration accuracy: microlens-centre RMS error against the simulator's truth for
clean, noisy, rotated/shifted, missing/vignetted and saturated white images, and for
real-camera cases (lenses off the lattice, dark-subtracted negatives, dead pixels, a dust
shadow, a dimmed edge ring): a plain box centroid (the paper's), plenocl's windowed
centroid (``method="centroid"``), the grid model (``method="fit"``) and the two combined
by their uncertainties (``method="combined"``, the default), all from the same detection
and matching, in the same run.

    python benchmarks/calibration.py [--camera synthetic|paper] [--seeds 3]

Scale rows (issue 29, ``--skip-scales`` leaves them out): 720 x 720 px images of the sizes
another light-field project publishes with true centres, traced by plenocl: hexagonal at
13 and 65 px per lens, at full aperture (f/2) and stopped down, and rectangular at
7.7 px rotated 2 degrees at full aperture; blur 0.8 px, 400 rays per lens pixel area,
100,000 counts per lens, no noise.

Hexagonal rows (issue 29): the same camera's lenses in a hexagonal array of the same
pitch (rows 0.866 pitch apart, odd rows half a pitch along; as many columns, as many
rows as the sensor holds, and the sensor's height cut to them), stopped down and at full
aperture.

The truth is ``camera.ideal_microlens_centers()`` of the camera that made the image;
the calibration sees only the nominal camera (no rotation, no offset).
"""

from __future__ import annotations

import statistics
import time

from plenocl import Camera, get_queue
from plenocl.bench.core import hexagonal_cut
from plenocl.bench.lightfield_section import (
    CALIBRATION_CASES,
    box_centroids,
    rms,
    white_case,
)
from plenocl.bench.scripts import script_parser
from plenocl.calibration import find_centers

#: A normally exposed 12-bit white image (peak about 1600 counts), photon and read noise.
EXPOSED = dict(photon_noise=True, read_noise=3.0, bit_depth=12, intensity=1e4,
               rays_per_lens=20000)
CASES = {**CALIBRATION_CASES,
         "rotated -2 deg, shifted": (dict(ml_rotation_deg=-2.0, ml_offset_mm=(-0.05, 0.02)),
                                     dict(photon_noise=True)),
         "saturated (8-bit)": (dict(), dict(intensity=6000.0, bit_depth=8, photon_noise=True)),
         "0.15 deg, lenses 0.1 px off, dark-subtracted": (
             dict(ml_rotation_deg=0.15), dict(EXPOSED, lens_shift_px=0.1, dark_subtracted=0.009)),
         "2 deg, lenses 0.1 px off, dark-subtracted": (
             dict(ml_rotation_deg=2.0), dict(EXPOSED, lens_shift_px=0.1, dark_subtracted=0.009)),
         "dim, lenses 0.1 px off (1000 counts/lens)": (
             dict(ml_rotation_deg=0.15), dict(photon_noise=True, lens_shift_px=0.1)),
         "small spots 0.6 px, 0.2 deg, lenses 0.1 px off": (
             dict(ml_rotation_deg=0.2), dict(EXPOSED, blur_px=0.3, lens_shift_px=0.1)),
         "full aperture (f/2 disks), 0.3 deg, vign. 50 %": (
             dict(ml_rotation_deg=0.3), dict(EXPOSED, stop_f_number=2.0, vignetting=0.5,
                                             intensity=1e5, rays_per_lens=50000))}


#: The hexagonal array's cases (the true layout is hexagonal in each).
HEX_CASES = {
    "hex: clean": (dict(), dict()),
    "hex: rotated +2 deg, shifted, noisy": (
        dict(ml_rotation_deg=2.0, ml_offset_mm=(0.04, -0.03)),
        dict(photon_noise=True, read_noise=2.0, bit_depth=16)),
    "hex: odd rows -0.5, -1 deg, noisy": (dict(ml_odd_row_shift=-0.5, ml_rotation_deg=-1.0),
                                          dict(photon_noise=True)),
    "hex: small spots, 0.2 deg, lenses 0.1 px off": (
        dict(ml_rotation_deg=0.2), dict(EXPOSED, blur_px=0.3, lens_shift_px=0.1)),
    "hex: full aperture, 0.3 deg, vign. 50 %": (
        dict(ml_rotation_deg=0.3), dict(EXPOSED, stop_f_number=2.0, vignetting=0.5,
                                        intensity=1e5, rays_per_lens=50000)),
}


def scale_camera(pitch_px: float, layout: str) -> Camera:
    """The synthetic optics on a 720 x 720 px sensor whose pixels make a microlens image
    ``pitch_px`` wide, as many lenses (columns, rows) as fill it."""
    pp = 0.125 * (1 + 0.5 / 100.0) / pitch_px
    row = pitch_px * (3**0.5 / 2 if layout == "hexagonal" else 1.0)
    return Camera(50.0, 2.0, 1.0, 0.125, 0.5, (int(719 / pitch_px), int(719 / row)), pp,
                  (720, 720), ml_layout=layout)


def scale_cases() -> list:
    """``(camera, name, (layout, white image))`` of the 720 px scale rows."""
    out = []
    for pitch, layout, rot, stop in [(13, "hexagonal", 0.0, 2.0), (13, "hexagonal", 1.0, 16.0),
                                     (65, "hexagonal", 0.0, 2.0), (65, "hexagonal", 0.5, 16.0),
                                     (7.7, "rectangular", 2.0, 2.0)]:
        name = f"720 px: {layout[:4]}. {pitch:g} px, {rot:g} deg, f/{stop:g}"
        sim = dict(stop_f_number=stop, intensity=1e5, rays_per_lens=int(400 * pitch**2))
        out.append((scale_camera(pitch, layout), name, (dict(ml_rotation_deg=rot), sim)))
    return out


def run_case(base: Camera, layout: dict, sim: dict, seed: int, queue) -> tuple:
    """One white image: (box, centroid, model, combined RMS, found, lenses, seconds)."""
    white, truth = white_case(base, layout, sim, seed, queue)
    t0 = time.perf_counter()
    fit = find_centers(white, base)
    seconds = time.perf_counter() - t0
    model = find_centers(white, base, method="fit")
    box = box_centroids(white, fit.centroids, int(0.4 * base.pixels_per_microlens))
    return (rms(box, truth), rms(fit.centroids, truth), rms(model.centers, truth),
            rms(fit.centers, truth), int(fit.found.sum()), fit.found.size, seconds)


def main() -> None:
    parser = script_parser(__doc__, {"scales": "leave out the 720 px scale rows"})
    parser.add_argument("--camera", choices=["synthetic", "paper"], default="synthetic")
    parser.add_argument("--seeds", type=int, default=3, help="images per case")
    args = parser.parse_args()
    base = Camera.synthetic_850() if args.camera == "synthetic" else Camera.paper_16mp()
    queue = get_queue()
    print(f"camera: {base.describe()}; {base.pixels[0]} x {base.pixels[1]} px")
    print("white images: f/16 stop, 2000 rays per lens, 1000 counts per lens, blur 0.8 px; "
          f"median over {args.seeds} seeds")
    print("centre RMS error (px, 2-D) against the truth:")
    print(f"{'case':46s} {'box cen.':>9s} {'win cen.':>9s} {'model':>7s} {'combined':>9s} "
          f"{'found':>12s} {'calib s':>8s}")
    cases = [(base, name, case) for name, case in CASES.items()]
    cases += [(hexagonal_cut(base, case[0].get("ml_odd_row_shift", 0.5)), name, case)
              for name, case in HEX_CASES.items()]
    cases += [] if args.skip_scales else scale_cases()
    for camera, name, (layout, sim) in cases:
        runs = [run_case(camera, layout, sim, seed, queue) for seed in range(args.seeds)]
        box, cen, fit, comb, found, total, sec = (statistics.median(r[i] for r in runs)
                                                  for i in range(7))
        print(f"{name:46s} {box:9.4f} {cen:9.4f} {fit:7.4f} {comb:9.4f} "
              f"{int(found):6d}/{int(total):<5d} {sec:8.3f}")


if __name__ == "__main__":
    main()
