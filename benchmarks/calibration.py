"""Calibration accuracy: microlens-centre RMS error against the simulator's truth for
clean, noisy, rotated/shifted, missing/vignetted and saturated white images: a plain
box centroid (the paper's), plenocl's windowed centroid (``method="centroid"``) and its
grid-model fit (``method="fit"``, the default), all from the same detection and matching.

    python benchmarks/calibration.py [--camera synthetic|paper] [--seeds 3]

The truth is ``camera.ideal_microlens_centers()`` of the camera that made the image;
the calibration sees only the nominal camera (no rotation, no offset).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from plenocl import Camera, get_queue
from plenocl.calibration import find_centers
from plenocl.simulate import simulate_white_image

CASES = {
    "clean": (dict(), dict()),
    "noisy (shot+read, 8-bit)": (dict(), dict(photon_noise=True, read_noise=3.0,
                                              background=5.0, bit_depth=8)),
    "rotated +2 deg, shifted": (dict(ml_rotation_deg=2.0, ml_offset_mm=(0.04, -0.03)),
                                dict(photon_noise=True, read_noise=2.0, bit_depth=16)),
    "rotated -2 deg, shifted": (dict(ml_rotation_deg=-2.0, ml_offset_mm=(-0.05, 0.02)),
                                dict(photon_noise=True)),
    "missing 1 %, vignetted 70 %": (dict(), dict(vignetting=0.7, photon_noise=True,
                                                 read_noise=2.0, missing="1%")),
    "saturated (8-bit)": (dict(), dict(intensity=6000.0, bit_depth=8, photon_noise=True)),
}


def rms(centres: np.ndarray, truth: np.ndarray) -> float:
    """2-D RMS distance (px) over the lenses that have a centre."""
    d2 = ((centres - truth) ** 2).sum(-1)
    return float(np.sqrt(np.nanmean(d2)))


def box_centroids(white: np.ndarray, near: np.ndarray, half: int) -> np.ndarray:
    """Plain centroids in a ``2 half + 1`` box around each (rounded) centre, above the
    image median (the paper's "simple centroid fit")."""
    img = np.asarray(white, np.float64) - np.median(white)
    out = np.full(near.shape, np.nan)
    h, w = img.shape
    for idx in zip(*np.nonzero(np.isfinite(near).all(-1))):
        c, r = np.rint(near[idx]).astype(int)
        r0, r1 = max(r - half, 0), min(r + half + 1, h)
        c0, c1 = max(c - half, 0), min(c + half + 1, w)
        win = np.clip(img[r0:r1, c0:c1], 0, None)
        if win.sum() > 0:
            rr, cc = np.mgrid[r0:r1, c0:c1]
            out[idx] = ((win * cc).sum() / win.sum(), (win * rr).sum() / win.sum())
    return out


def run_case(base: Camera, layout: dict, sim: dict, seed: int, queue) -> tuple:
    """One white image: (box RMS, centroid RMS, fit RMS, found, lenses, seconds)."""
    true = Camera(base.focal_length_mm, base.f_number, base.magnification, base.ml_pitch_mm,
                  base.ml_focal_length_mm, base.ml_count, base.pixel_pitch_mm, base.pixels,
                  **layout)
    sim = dict(sim)
    if sim.get("missing") == "1%":
        sim["missing"] = np.random.default_rng(seed).random(base.ml_count[::-1]) < 0.01
    white = simulate_white_image(true, seed=seed, queue=queue, **sim)
    t0 = time.perf_counter()
    fit = find_centers(white, base)
    seconds = time.perf_counter() - t0
    truth = true.ideal_microlens_centers()
    box = box_centroids(white, fit.centroids, int(0.4 * base.pixels_per_microlens))
    return (rms(box, truth), rms(fit.centroids, truth), rms(fit.centers, truth),
            int(fit.found.sum()), fit.found.size, seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--camera", choices=["synthetic", "paper"], default="synthetic")
    parser.add_argument("--seeds", type=int, default=3, help="images per case")
    args = parser.parse_args()
    base = Camera.synthetic_850() if args.camera == "synthetic" else Camera.paper_16mp()
    queue = get_queue()
    print(f"camera: {base.describe()}; {base.pixels[0]} x {base.pixels[1]} px")
    print("white images: f/16 stop, 2000 rays per lens, 1000 counts per lens, blur 0.8 px; "
          f"median over {args.seeds} seeds")
    print("centre RMS error (px, 2-D) against the truth:")
    print(f"{'case':30s} {'box centroid':>13s} {'win centroid':>13s} {'grid fit':>9s} "
          f"{'found':>12s} {'calib s':>8s}")
    for name, (layout, sim) in CASES.items():
        runs = [run_case(base, layout, sim, seed, queue) for seed in range(args.seeds)]
        box, cen, fit, found, total, sec = (statistics.median(r[i] for r in runs)
                                            for i in range(6))
        print(f"{name:30s} {box:13.4f} {cen:13.4f} {fit:9.4f} {int(found):6d}/{int(total):<5d} "
              f"{sec:8.3f}")


if __name__ == "__main__":
    main()
