"""Benchmark report section: where the velocity error comes from (the error budget).

At the paper's optics and voxel, for a uniform displacement, per seeding density: PIV on
volumes rendered from the true particles (what the windows cannot resolve), on volumes
reconstructed from ray-traced raw images with ``process_pair`` defaults (what users get),
and the reconstruction's quality (Q, particles recovered, ghost intensity). Lateral and
depth separately, depth also by zone (in focus, near, far). ``benchmarks/accuracy.py``
runs the same rows for any seeding from the command line.
"""

from __future__ import annotations

import time

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..metrics import quality_q, recovery, render_particles
from ..particles import random_particles
from ..pipeline import process_pair
from ..piv.multipass import piv3d
from ..projection import Projector
from ..simulate import simulate_image
from .core import BenchRun, md_table

SHIFT_VOX = np.array([2.3, -1.4, 1.7])  # (x, y, z) voxels
VOXEL_MM = (0.1833, 0.175, 0.1333)      # (x, y, z): the paper's 300 x 200 x 150 grid


def paper_optics(lenses: tuple[int, int]) -> tuple[Camera, Grid]:
    """The paper's optics (f = 50 mm, f/2.42, |M| = 0.66, 125 µm lenses of f = 500 µm,
    7.4 µm pixels) on ``lenses`` microlenses, and the paper's voxel over 20 mm of depth
    just inside their field of view."""
    pitch_px = 0.125 * (1 + 0.5 / (50.0 * 1.66)) / 0.0074
    pixels = tuple(int(np.ceil(n * pitch_px)) + 2 for n in lenses)
    cam = Camera(50.0, 2.42, 0.66, 0.125, 0.5, lenses, 0.0074, pixels)
    half = [n * 0.125 / 0.66 / 2 * 0.96 for n in lenses]
    shape = (150, int(2 * half[1] / VOXEL_MM[1]), int(2 * half[0] / VOXEL_MM[0]))
    grid = Grid(shape, x=(-shape[2] * VOXEL_MM[0] / 2, shape[2] * VOXEL_MM[0] / 2),
                y=(-shape[1] * VOXEL_MM[1] / 2, shape[1] * VOXEL_MM[1] / 2), z=(-10.0, 10.0))
    return cam, grid


def budget_errors(res, grid: Grid) -> dict:
    """RMS errors (voxels) of the valid vectors against :data:`SHIFT_VOX`: lateral (RMS
    over x and y), depth, depth by zone (in focus |z| < 2 mm, near, far), bias."""
    ok = res.valid
    err = [getattr(res, c)[ok] - s for c, s in zip("uvw", SHIFT_VOX)]
    z_mm = np.broadcast_to(grid.z[0] + (res.z[:, None, None] + 0.5) * grid.spacing[0],
                           res.u.shape)[ok]
    out = {"lateral": float(np.sqrt(np.mean(err[0] ** 2 + err[1] ** 2) / 2)),
           "depth": float(np.sqrt(np.mean(err[2] ** 2))), "valid": float(ok.mean()),
           "bias": tuple(float(np.mean(e)) for e in err)}
    for zone, sel in (("in focus", np.abs(z_mm) < 2), ("near", z_mm < -2), ("far", z_mm > 2)):
        out[zone] = float(np.sqrt(np.mean(err[2][sel] ** 2))) if sel.any() else float("nan")
    return out


def budget_row(cam: Camera, grid: Grid, proj, ppm: float, seed: int, queue,
               rays: int = 2000) -> dict:
    """The budget of one seeding density (particles per microlens)."""
    shift_mm = SHIFT_VOX * np.array(VOXEL_MM)
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    count = max(2, int(round(ppm * cam.ml_count[0] * cam.ml_count[1])))
    pos, inten = random_particles(box, count=count, seed=seed, intensity=2e4)
    pa, pb = pos - shift_mm / 2, pos + shift_mm / 2
    kw = dict(rays_per_particle=rays, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue)
    raw_a = simulate_image(cam, pa, inten, seed=2 * seed, **kw)
    raw_b = simulate_image(cam, pb, inten, seed=2 * seed + 1, **kw)
    true_a, true_b = (render_particles(grid, p, 1.0, sigma_vox=1.0) for p in (pa, pb))
    t0 = time.perf_counter()
    windows = budget_errors(piv3d(true_a, true_b), grid)
    t_true = time.perf_counter() - t0
    pair = process_pair(raw_a, raw_b, proj)
    rep = recovery(pair.vol_a, grid, pa)
    return {"ppm": ppm, "particles": count, "windows": windows,
            "reconstruction": budget_errors(pair.piv, grid), "pair": pair,
            "final_window": pair.piv.window, "Q": quality_q(pair.vol_a, true_a),
            "recovered": rep.fraction, "ghosts": rep.ghost_fraction,
            "seconds": {**pair.seconds, "piv_true": t_true}}


def budget_table(rows: list[dict], grid: Grid) -> str:
    """The rows of :func:`budget_row` as a Markdown table."""
    dz = grid.spacing[0]
    body = []
    for r in rows:
        w, e = r["windows"], r["reconstruction"]
        body.append([f"{r['ppm']:.2f}", r["particles"], f"{w['lateral']:.3f}",
                     f"{w['depth']:.3f}", f"{e['lateral']:.3f}", f"{e['depth']:.2f}",
                     f"{e['depth'] * dz:.3f}", f"{e['in focus']:.2f}", f"{e['near']:.2f}",
                     f"{e['far']:.2f}", f"{e['valid']:.0%}", str(r["final_window"]),
                     " ".join(f"{b:+.2f}" for b in e["bias"]), f"{r['Q']:.2f}",
                     f"{r['recovered']:.0%}", f"{r['ghosts']:.0%}"])
    return md_table(["ppm", "particles", "windows only: lateral", "depth",
                     "reconstructed: lateral", "depth", "depth mm", "in focus", "near", "far",
                     "valid", "final window", "bias x y z", "Q", "recovered", "ghosts"], body)


def section_accuracy(run: BenchRun) -> str:
    """The error budget at the paper's optics for the report size's seedings."""
    lenses, seedings = run.cfg.accuracy_lenses, run.cfg.accuracy_seeding
    cam, grid = paper_optics(lenses)
    proj = Projector(cam, grid, run.queue)
    rows = []
    for k, ppm in enumerate(seedings, start=1):
        rows.append(budget_row(cam, grid, proj, ppm, seed=k, queue=run.queue))
        run.log(f"  accuracy: seeding {ppm} done")
    return ("## Accuracy: the error budget\n\nThe paper's optics and voxel (0.183 x 0.175 x "
            f"0.133 mm) on {lenses[0]} x {lenses[1]} microlenses, grid {grid.shape} (z, y, x), "
            f"a uniform displacement of {SHIFT_VOX.tolist()} voxels (x, y, z); raw images "
            "ray traced with 0.8 px blur, photon and read noise. RMS error (voxels unless "
            "stated) of the valid vectors: **windows only** correlates volumes rendered from "
            "the true particles (what the windows cannot resolve); **reconstructed** "
            "correlates `process_pair`'s volumes (what users get); depth by zone: in focus "
            "|z| < 2 mm, near, far. For a uniform displacement the window-averaged and the "
            "point-sampled truth coincide. One scene per seeding (not a median); "
            "`benchmarks/accuracy.py` runs any seeding list.\n\n"
            + budget_table(rows, grid))
