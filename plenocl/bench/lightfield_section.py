"""Report sections: calibration (run time against centre error) and refocusing (the
kernel against SciPy shift-and-add); also the baselines ``benchmarks/calibration.py``
and ``benchmarks/refocus.py`` use."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy import ndimage

from ..calibration import find_centers
from ..camera import Camera
from ..lightfield import LightField
from ..reference.refocus import output_lens_coordinates
from ..simulate import centre_shift_px, simulate_image, simulate_white_image
from .core import BenchRun, md_table, repeats_text
from .timing import median_time, timed

#: White-image cases: (true layout of the array, simulation options).
CALIBRATION_CASES = {
    "clean": (dict(), dict()),
    "noisy (shot+read, 8-bit)": (dict(), dict(photon_noise=True, read_noise=3.0,
                                              background=5.0, bit_depth=8)),
    "rotated +2 deg, shifted": (dict(ml_rotation_deg=2.0, ml_offset_mm=(0.04, -0.03)),
                                dict(photon_noise=True, read_noise=2.0, bit_depth=16)),
    "missing 1 %, vignetted 70 %": (dict(), dict(vignetting=0.7, photon_noise=True,
                                                 read_noise=2.0, missing="1%")),
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
    for idx in zip(*np.nonzero(np.isfinite(near).all(-1)), strict=True):
        c, r = np.rint(near[idx]).astype(int)
        r0, r1 = max(r - half, 0), min(r + half + 1, h)
        c0, c1 = max(c - half, 0), min(c + half + 1, w)
        win = np.clip(img[r0:r1, c0:c1], 0, None)
        if win.sum() > 0:
            rr, cc = np.mgrid[r0:r1, c0:c1]
            out[idx] = ((win * cc).sum() / win.sum(), (win * rr).sum() / win.sum())
    return out


def white_case(base: Camera, layout: dict, sim: dict, seed: int, queue):
    """A white image of the array ``layout`` describes, and its true centres.

    ``sim`` may ask for ``missing="1%"`` (dead lenses), ``lens_shift_px=s`` (every lens off
    its lattice node by ``s`` px RMS per axis, manufacturing errors) and
    ``dark_subtracted=f`` (read noise of ``f`` times the spot peak about a subtracted dark
    level: negative pixels)."""
    true = dataclasses.replace(base, microlens_centers=None, calibrated=False, **layout)
    sim, rng = dict(sim), np.random.default_rng(seed)
    if sim.get("missing") == "1%":
        sim["missing"] = rng.random(base.ml_count[::-1]) < 0.01
    truth = true.ideal_microlens_centers()
    shift_px = sim.pop("lens_shift_px", 0.0)
    if shift_px:
        per_px = centre_shift_px(true, np.ones(2))[0]
        sim["lens_shift_mm"] = rng.normal(0.0, shift_px / per_px, (*base.ml_count[::-1], 2))
        truth = truth + centre_shift_px(true, sim["lens_shift_mm"])
    dark = sim.pop("dark_subtracted", 0.0)
    white = simulate_white_image(true, seed=seed, queue=queue, **sim)
    if dark:
        white = white + dark * float(np.percentile(white, 99.9)) * rng.standard_normal(
            white.shape)
    return white, truth


def section_calibration(run: BenchRun) -> str:
    """Centre RMS error against time: box centroid (the paper's), windowed centroid, fit."""
    base, rows = run.camera, []
    half = max(1, int(0.4 * base.pixels_per_microlens))
    for name, (layout, sim) in CALIBRATION_CASES.items():
        white, truth = white_case(base, layout, sim, seed=1, queue=run.queue)
        cen, t_cen = timed(lambda w=white: find_centers(w, base, method="centroid"),
                           run.repeats)
        fit, t_fit = timed(lambda w=white: find_centers(w, base), run.repeats)
        box, t_box = timed(lambda w=white, c=cen: box_centroids(w, c.centroids, half),
                           run.repeats)
        found = f"{int(fit.found.sum())}/{fit.found.size}"
        rows += [[name, "box centroid (the paper's)", f"{t_cen + t_box:.3f}",
                  f"{rms(box, truth):.4f}", found],
                 [name, "windowed centroid", f"{t_cen:.3f}", f"{rms(cen.centers, truth):.4f}",
                  found],
                 [name, "model + centroid by uncertainty (default)", f"{t_fit:.3f}",
                  f"{rms(fit.centers, truth):.4f}", found]]
        run.log(f"  calibration: {name} done")
    return (f"## Calibration: run time against centre error\n\nWhite images of the "
            f"{base.pixels[0]} x {base.pixels[1]} px camera ({base.ml_count[0]} x "
            f"{base.ml_count[1]} lenses) from the simulator; the calibration sees only the "
            "nominal camera. Error: 2-D RMS distance (px) of the found centres from the "
            f"truth. Time: median of {repeats_text(run.repeats)} of `find_centers` (detection, "
            "matching, centroids and, for the default, the grid model and the combination); "
            "the box centroid adds "
            "its own pass to the windowed-centroid run whose spots it reuses.\n\n"
            + md_table(["white image", "method", "time s", "RMS error px", "lenses found"],
                       rows))


def scipy_shift_and_add(views: np.ndarray, shifts: np.ndarray, supersample: int) -> np.ndarray:
    """Per plane and view: interpolate value and validity at the shifted output grid, add.

    Interpolating ``value * valid`` and ``valid`` separately and dividing gives the same
    weighted mean over existing samples as the kernel; ``order=2`` without the spline
    prefilter is the kernel's quadratic B-spline smoothing (design.md §4).
    """
    nuv, ny, nx = views.shape
    kx, ky = output_lens_coordinates(nx, ny, supersample)
    grid_y, grid_x = np.meshgrid(ky, kx, indexing="ij")
    valid = np.isfinite(views)
    filled = np.where(valid, views, 0.0).astype(np.float32)
    out = np.zeros((len(shifts), len(ky), len(kx)), np.float32)
    for p, plane in enumerate(shifts):
        acc = np.zeros(grid_x.shape, np.float32)
        wsum = np.zeros(grid_x.shape, np.float32)
        for n in range(nuv):
            if not valid[n].any():
                continue
            coords = np.stack([grid_y + plane[n, 1], grid_x + plane[n, 0]])
            acc += ndimage.map_coordinates(filled[n], coords, order=2, prefilter=False,
                                           mode="grid-constant")
            wsum += ndimage.map_coordinates(valid[n].astype(np.float32), coords, order=2,
                                            prefilter=False, mode="grid-constant")
        out[p] = np.divide(acc, wsum, out=np.zeros_like(acc), where=wsum > 1e-6)
    return out


def section_refocus(run: BenchRun, planes: int = 9) -> str:
    """Focal-stack time of the kernel against SciPy shift-and-add on the same light field."""
    cam = run.camera.with_centers(run.camera.ideal_microlens_centers())
    rng = np.random.default_rng(0)
    half = np.array([b - a for a, b in run.cfg.box]) / 2
    pts = rng.uniform(-half, half, (200, 3))
    raw = simulate_image(cam, pts, 1e4, 2000, seed=1, queue=run.queue)
    t0 = time.perf_counter()
    lf = LightField(raw, cam, queue=run.queue)
    t_build = time.perf_counter() - t0
    z = np.linspace(-half[2], half[2], planes)
    shifts = lf.shifts(cam.alpha(z))
    views = lf.views.reshape(-1, *lf.shape)
    t_dev = median_time(lambda: lf.focal_stack(z), run.repeats)
    t_scipy = median_time(lambda: scipy_shift_and_add(views, shifts, 1), run.repeats)
    a, b = lf.focal_stack(z), scipy_shift_and_add(views, shifts, 1)
    diff = float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
    rows = [["OpenCL kernel", f"{t_dev:.4f}", f"{planes / t_dev:.1f}", f"{t_scipy / t_dev:.1f}x"],
            ["SciPy shift-and-add (ndimage, quadratic B-spline)", f"{t_scipy:.4f}",
             f"{planes / t_scipy:.1f}", "1.0x"]]
    return (f"## Refocusing\n\nA focal stack of {planes} planes (z from {-half[2]:g} to "
            f"{half[2]:g} mm) of 200 particles on the {cam.pixels[0]} x {cam.pixels[1]} px "
            f"camera, {lf.shape[1]} x {lf.shape[0]} output pixels; medians of "
            f"{repeats_text(run.repeats)}. Light-field resampling (host, once per image): "
            f"{t_build:.3f} s. Kernel against SciPy: max difference {diff:.1e} of the peak "
            "(the same weighted shift-and-add).\n\n"
            + md_table(["path", "median s", "planes/s", "speed-up"], rows))
