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

Odd-rows row (issue 44, ``--skip-odd-rows`` leaves it out): a hexagonal array of 65 px
lenses whose odd rows sit 0.46 pitch from the even ones while the camera file says 0.5,
0.2 px jitter, full aperture, the lattice alone beside the per-lens default.

The truth is ``camera.ideal_microlens_centers()`` of the camera that made the image;
the calibration sees only the nominal camera (no rotation, no offset).

Per-lens rows (issue 44, ``--skip-per-lens`` leaves them out): full-aperture white images
(f/2 disks) of ``--lenses`` x ``--lenses`` lenses of the synthetic optics (17 px each;
hexagonal: as many rows as the same sensor holds), rotated 0.3 degrees, every lens off
its lattice node by 0.2 px RMS per axis and by a radial distortion of the main lens
(1.5 px at the outermost lens, ``plenocl.simulate.lens_displacements_mm``), 50 % vignetting
or none, a camera's exposure (about 2000 of 4096 counts, photon and read noise; 100,000
rays per lens add the rays' own sampling noise). Side by side: the lattice alone
(``method="fit"``, the grid model of the disk centroids), the smooth model refitted to
the per-lens fits, each lens's own disk fit, and the two combined by their uncertainties
(the default), with the time of each calibration. The truth is each lens's own
``c_k`` (``ideal_microlens_centers()`` plus ``centre_shift_px`` of its displacement).

``--paper-timing`` times the full-aperture calibration (lattice only and per-lens) of
the paper's 289 x 193-lens, 4904 x 3280 px camera on one white image (2,000 rays per
lens: the time, not the accuracy, is measured).
"""

from __future__ import annotations

import dataclasses
import statistics
import time

import numpy as np

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
from plenocl.simulate import centre_shift_px, lens_displacements_mm, simulate_white_image

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


#: The per-lens rows' white images: a camera's exposure at full aperture (f/2 disks).
FULL_EXPOSURE = dict(photon_noise=True, read_noise=3.0, bit_depth=12, intensity=4e5,
                     rays_per_lens=100_000)


def per_lens_camera(lenses: int, layout: str) -> Camera:
    """The synthetic optics with ``lenses`` x ``lenses`` lenses (17 px each), rotated 0.3°;
    hexagonal: as many rows as the same sensor holds."""
    syn = Camera.synthetic_850()
    cam = dataclasses.replace(syn, ml_count=(lenses, lenses), pixels=(17 * lenses,) * 2,
                              microlens_centers=None, calibrated=False,
                              ml_rotation_deg=0.3)
    return hexagonal_cut(cam) if layout == "hexagonal" else cam


def run_per_lens(layout: str, vignetting: float, lenses: int, seed: int, queue) -> tuple:
    """RMS (px, 2-D) of the lattice alone, the smooth model of the per-lens fits, the
    per-lens fits, the combined centres; lenses found, lenses; the two times (s)."""
    cam = per_lens_camera(lenses, layout)
    shift = lens_displacements_mm(cam, jitter_px=0.2, distortion_px=1.5, seed=seed)
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, vignetting=vignetting,
                                 lens_shift_mm=shift, seed=seed, queue=queue, **FULL_EXPOSURE)
    nominal = dataclasses.replace(cam, ml_rotation_deg=0.0)
    t0 = time.perf_counter()
    lattice = find_centers(white, nominal, method="fit")
    t1 = time.perf_counter()
    fit = find_centers(white, nominal)
    t2 = time.perf_counter()
    smooth = np.where(fit.found[..., None], fit.model, np.nan)
    return (rms(lattice.centers, truth), rms(smooth, truth), rms(fit.centroids, truth),
            rms(fit.centers, truth), int(fit.found.sum()), fit.found.size, t1 - t0, t2 - t1)


def per_lens_rows(lenses: int, seeds: int, queue) -> None:
    """Print the per-lens table (module docstring)."""
    print(f"\nfull aperture, lenses off the lattice (0.2 px RMS jitter, 1.5 px radial "
          f"distortion), {lenses} x {lenses} lenses of 17 px (hexagonal: the rows the "
          f"sensor holds), 0.3 deg, 12-bit photon + read noise; median over {seeds} seeds")
    print("centre RMS error (px, 2-D) against each lens's own c_k:")
    print(f"{'case':28s} {'lattice':>8s} {'smooth':>7s} {'own fit':>8s} {'per-lens':>9s} "
          f"{'found':>10s} {'lattice s':>9s} {'per-lens s':>10s}")
    for layout in ("rectangular", "hexagonal"):
        for vignetting in (0.0, 0.5):
            runs = [run_per_lens(layout, vignetting, lenses, seed, queue)
                    for seed in range(seeds)]
            lat, smooth, own, comb, found, total, t_lat, t_comb = (
                statistics.median(r[i] for r in runs) for i in range(8))
            name = f"{layout[:4]}., vignetting {vignetting:.0%}"
            print(f"{name:28s} {lat:8.4f} {smooth:7.4f} {own:8.4f} {comb:9.4f} "
                  f"{int(found):5d}/{int(total):<4d} {t_lat:9.2f} {t_comb:10.2f}")


def odd_rows_camera(cols: int = 11, rows: int = 12) -> Camera:
    """Issue 44 finding 3's array: the synthetic optics with 65 px lenses, hexagonal,
    rotated 0.3 degrees, the sensor cut to the array."""
    syn = Camera.synthetic_850()
    pixel = syn.pixel_pitch_mm * syn.pixels_per_microlens / 65.0
    return dataclasses.replace(
        syn, ml_count=(cols, rows), ml_layout="hexagonal", ml_odd_row_shift=0.5,
        pixels=(int((cols + 0.5) * 65) + 1, int(rows * 65 * 3**0.5 / 2) + 1),
        pixel_pitch_mm=pixel, ml_rotation_deg=0.3, microlens_centers=None, calibrated=False)


def run_odd_rows(seed: int, queue) -> tuple:
    """RMS (px, 2-D) of the lattice alone and of the per-lens default on the odd-rows
    array (its odd rows 0.46 pitch from the even ones, 0.2 px jitter), and the lens
    scatter the default reads."""
    cam = odd_rows_camera()
    turn = np.radians(cam.ml_rotation_deg)
    shift = np.zeros((cam.ml_count[1], cam.ml_count[0], 2))
    shift[1::2] = -0.04 * cam.ml_pitch_mm * np.array([np.cos(turn), np.sin(turn)])
    shift += lens_displacements_mm(cam, jitter_px=0.2, seed=seed)
    truth = cam.ideal_microlens_centers() + centre_shift_px(cam, shift)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, lens_shift_mm=shift,
                                 seed=seed, queue=queue,
                                 **dict(FULL_EXPOSURE, intensity=6e6, rays_per_lens=200_000))
    nominal = dataclasses.replace(cam, ml_rotation_deg=0.0)
    lattice = find_centers(white, nominal, method="fit")
    fit = find_centers(white, nominal)
    return rms(lattice.centers, truth), rms(fit.centers, truth), fit.lattice_scatter_px


def odd_rows_row(seeds: int, queue) -> None:
    """Print the odd-rows row (module docstring)."""
    runs = [run_odd_rows(seed, queue) for seed in range(seeds)]
    lat, comb, scatter = (statistics.median(r[i] for r in runs) for i in range(3))
    print(f"\nhexagonal, 65 px lenses, odd rows 0.46 pitch off (the camera file: 0.5), "
          f"0.2 px jitter, full aperture; median over {seeds} seeds: lattice {lat:.4f} px, "
          f"per-lens {comb:.4f} px (2-D RMS); lens scatter read {scatter:.3f} px (true 0.2)")


def paper_timing(queue) -> None:
    """Time the full-aperture calibration of the paper's camera, lattice and per-lens."""
    cam = Camera.paper_16mp()
    shift = lens_displacements_mm(cam, jitter_px=0.2, distortion_px=1.5, seed=0)
    white = simulate_white_image(cam, stop_f_number=cam.f_number, lens_shift_mm=shift,
                                 photon_noise=True, read_noise=3.0, bit_depth=12,
                                 intensity=4e5, rays_per_lens=2000, queue=queue)
    times = []
    for method in ("fit", "combined"):
        t0 = time.perf_counter()
        fit = find_centers(white, cam, method=method)
        times.append(time.perf_counter() - t0)
    print(f"\npaper camera ({cam.ml_count[0]} x {cam.ml_count[1]} lenses, {cam.pixels[0]} x "
          f"{cam.pixels[1]} px), full aperture: lattice only {times[0]:.1f} s, per-lens "
          f"{times[1]:.1f} s ({int(fit.found.sum())} lenses found)")


def existing_rows(base: Camera, args, queue) -> None:
    """The stopped-down, hexagonal and scale rows (module docstring)."""
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


def main() -> None:
    parser = script_parser(__doc__, {"scales": "leave out the 720 px scale rows",
                                     "per-lens": "leave out the full-aperture per-lens rows",
                                     "stopped": "leave out the rows before the per-lens ones",
                                     "odd-rows": "leave out the 0.46-pitch odd-rows row"})
    parser.add_argument("--camera", choices=["synthetic", "paper"], default="synthetic")
    parser.add_argument("--seeds", type=int, default=3, help="images per case")
    parser.add_argument("--lenses", type=int, default=30,
                        help="lenses per side of the per-lens rows' arrays")
    parser.add_argument("--paper-timing", action="store_true",
                        help="time the full-aperture calibration of the paper's camera")
    args = parser.parse_args()
    base = Camera.synthetic_850() if args.camera == "synthetic" else Camera.paper_16mp()
    queue = get_queue()
    if not args.skip_stopped:
        existing_rows(base, args, queue)
    if not args.skip_per_lens:
        per_lens_rows(args.lenses, args.seeds, queue)
    if not args.skip_odd_rows:
        odd_rows_row(args.seeds, queue)
    if args.paper_timing:
        paper_timing(queue)


if __name__ == "__main__":
    main()
