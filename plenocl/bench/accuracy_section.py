"""Benchmark report section: where the velocity error comes from (the error budget).

At the paper's optics and voxel, for a uniform displacement (or a solid-body rotation
about a lateral axis, :data:`ROTATION`), per seeding density: PIV on volumes rendered
from the true particles (what the windows cannot resolve), on volumes reconstructed from
ray-traced raw images with ``process_pair`` defaults (what users get), the same
sub-voxel volumes refined with the volumes' particles not fitted to the raw images,
correlated without the particle refinement, and the chain before
(single-frame reconstruction on the voxels themselves, correlation only: the baseline,
same scene), and the reconstructions' quality (Q, particles recovered, ghost
intensity). Lateral and depth separately, depth also by zone (in focus, near, far).
``benchmarks/accuracy.py`` runs the same rows for any seeding and motion from the
command line.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..metrics import quality_q, recovery, render_particles
from ..particles import random_particles
from ..pipeline import process_pair
from ..piv.multipass import piv3d
from ..piv.refinement import FocalZone, SightLines, refine_with_particles
from ..projection import Projector
from ..reconstruction import ReconstructionSettings
from ..simulate import simulate_image
from .core import BenchRun, md_table

SHIFT_VOX = np.array([2.3, -1.4, 1.7])  # (x, y, z) voxels
VOXEL_MM = (0.1833, 0.175, 0.1333)      # (x, y, z): the paper's 300 x 200 x 150 grid
#: The single-frame reconstruction on the voxels themselves: the default before sub-voxels
#: (and before the particle refinement).
BASELINE_SETTINGS = ReconstructionSettings(supersample=1)
#: The default chain's reconstruction before coarse-to-fine (docs/design.md §6.5): 30
#: MLEM iterations on the sub-voxels from a uniform volume.
PREVIOUS_SETTINGS = ReconstructionSettings(supersample=3, iterations=30, coarse_iterations=0)
#: The rows of a budget: the default chain, the same chain with the reconstruction before
#: coarse-to-fine (where asked for), its particles as the volumes place them (not fitted
#: to the raw images), its volumes correlated without the particle refinement, and the
#: chain before all of them.
ROWS = {"default": "default", "previous": "30 sub-voxel iterations",
        "volume_particles": "particles not fitted to the image",
        "correlation": "sub-voxels, correlation only",
        "baseline": "before (voxels, correlation)"}


def paper_setup(lenses: tuple[int, int], queue, layout: str = "rectangular",
                **options) -> tuple[Camera, Grid, Projector]:
    """:func:`paper_optics` on ``lenses`` microlenses (``layout``) with its projector on
    ``queue`` (``options``: :class:`plenocl.Projector`'s, e.g. ``scratch_bytes``);
    prints the device, the load, the camera and the grid (a benchmark script's first
    lines)."""
    cam, grid = paper_optics(lenses, layout)
    proj = Projector(cam, grid, queue, **options)
    print(f"device: {queue.device.name.strip()}; load average {os.getloadavg()[0]:.2f}")
    print(f"camera: {cam.describe()}; {cam.pixels[0]} x {cam.pixels[1]} px")
    print(f"grid {grid.shape} (z, y, x), voxel {grid.spacing[2]:.4f} x {grid.spacing[1]:.4f}"
          f" x {grid.spacing[0]:.4f} mm")
    return cam, grid, proj


def paper_optics(lenses: tuple[int, int], layout: str = "rectangular"
                 ) -> tuple[Camera, Grid]:
    """The paper's optics (f = 50 mm, f/2.42, ``|M| = 0.66``, 125 µm lenses of f = 500 µm,
    7.4 µm pixels) on ``lenses`` microlenses, and the paper's voxel over 20 mm of depth
    just inside their field of view. ``layout="hexagonal"``: a hexagonal array of the
    same pitch on the same sensor (as many lenses per row, the rows ``pitch·√3/2`` apart:
    ``lenses[1]·2/√3`` of them), the same grid."""
    pitch_px = 0.125 * (1 + 0.5 / (50.0 * 1.66)) / 0.0074
    pixels = tuple(int(np.ceil(n * pitch_px)) + 2 for n in lenses)
    cam = Camera(50.0, 2.42, 0.66, 0.125, 0.5, tuple(lenses), 0.0074, pixels
                 ).with_layout(layout)
    half = [n * 0.125 / 0.66 / 2 * 0.96 for n in lenses]
    shape = (150, int(2 * half[1] / VOXEL_MM[1]), int(2 * half[0] / VOXEL_MM[0]))
    grid = Grid(shape, x=(-shape[2] * VOXEL_MM[0] / 2, shape[2] * VOXEL_MM[0] / 2),
                y=(-shape[1] * VOXEL_MM[1] / 2, shape[1] * VOXEL_MM[1] / 2), z=(-10.0, 10.0))
    return cam, grid


@dataclass(frozen=True)
class Motion:
    """A known particle motion between the exposures: a uniform displacement
    :data:`SHIFT_VOX` (``angle_rad`` 0) or a solid-body rotation by ``angle_rad`` about
    the grid's lateral x axis through its centre, which moves particles in depth."""

    name: str
    angle_rad: float = 0.0

    def positions(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The two exposures' particles (mm) for mid-time positions ``pos``."""
        return self.moved(pos, -0.5), self.moved(pos, 0.5)

    def moved(self, pos: np.ndarray, steps: float) -> np.ndarray:
        """Where particles at ``pos`` (mm) are after ``steps`` exposure intervals (a
        time series: the shift, or the angle, once per interval)."""
        if not self.angle_rad:
            return pos + steps * SHIFT_VOX * np.array(VOXEL_MM)
        return _rotate_x(pos, self.angle_rad * steps)

    def displacement(self, res, grid: Grid) -> tuple[np.ndarray, ...]:
        """The true displacement ``(u, v, w)`` (voxels) at ``res``'s window centres. The
        motion is linear in space, so the window average and the point value agree."""
        if not self.angle_rad:
            return tuple(np.full(res.u.shape, s) for s in SHIFT_VOX)
        x, y, z = window_centres_mm(res, grid)
        zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
        pa, pb = self.positions(np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]))
        d = (pb - pa) / np.array(grid.spacing[::-1])
        return tuple(d[:, k].reshape(res.u.shape) for k in range(3))


def window_centres_mm(res, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The window centres ``(x, y, z)`` of ``res`` in the grid's millimetres."""
    dz, dy, dx = grid.spacing
    return res.positions_mm(grid.spacing, (grid.z[0] + dz / 2, grid.y[0] + dy / 2,
                                           grid.x[0] + dx / 2))


def _rotate_x(pos: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.array(pos, np.float64, copy=True)
    out[:, 1], out[:, 2] = c * pos[:, 1] - s * pos[:, 2], s * pos[:, 1] + c * pos[:, 2]
    return out


UNIFORM = Motion("uniform")
#: 2 degrees: up to about 2 voxels in y at the volume's depth ends and 1.5-3 voxels in
#: depth at its lateral edges (paper optics, 64-289 lenses high).
ROTATION = Motion("rotation about x", np.radians(2.0))


def vector_errors(res, grid: Grid, motion: Motion = UNIFORM
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The valid vectors of ``res``: their window centres ``(n, 3)`` (x, y, z) mm and
    their errors ``(n, 3)`` (x, y, z) voxels against the motion's displacement there."""
    ok = res.valid
    truth = motion.displacement(res, grid)
    err = np.stack([getattr(res, c)[ok] - t[ok] for c, t in zip("uvw", truth)], axis=1)
    x, y, z = window_centres_mm(res, grid)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return np.stack([xx[ok], yy[ok], zz[ok]], axis=1), err


def budget_errors(res, grid: Grid, motion: Motion = UNIFORM) -> dict:
    """RMS errors (voxels) of the valid vectors against the motion's displacement: lateral
    (RMS over x and y), depth, depth by zone (in focus ``|z| < 2`` mm, near, far), bias."""
    where, err = vector_errors(res, grid, motion)
    z_mm = where[:, 2]
    out = {"lateral": float(np.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2) / 2)),
           "depth": float(np.sqrt(np.mean(err[:, 2] ** 2))), "valid": float(res.valid.mean()),
           "bias": tuple(float(np.mean(e)) for e in err.T)}
    for zone, sel in (("in focus", np.abs(z_mm) < 2), ("near", z_mm < -2), ("far", z_mm > 2)):
        out[zone] = float(np.sqrt(np.mean(err[sel, 2] ** 2))) if sel.any() else float("nan")
    return out


@dataclass
class BudgetScene:
    """One scene of the budget: particles ``pa``/``pb`` (mm) of the two exposures, their
    ray-traced raw images, and both exposures' true-rendered volumes."""

    count: int
    pa: np.ndarray
    pb: np.ndarray
    raw_a: np.ndarray
    raw_b: np.ndarray
    true_a: np.ndarray
    true_b: np.ndarray


def budget_scene(cam: Camera, grid: Grid, ppm: float, seed: int, queue, rays: int = 2000,
                 motion: Motion = UNIFORM, bit_depth: int | None = None) -> BudgetScene:
    """Particles at ``ppm`` per microlens moved by ``motion``, ray traced with 0.8 px
    blur, photon and read noise on a dark level of 20 counts; float counts, or a
    camera's integers of ``bit_depth`` bits."""
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    count = max(2, int(round(ppm * cam.ml_count[0] * cam.ml_count[1])))
    pos, inten = random_particles(box, count=count, seed=seed, intensity=2e4)
    pa, pb = motion.positions(pos)
    kw = dict(rays_per_particle=rays, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue, bit_depth=bit_depth)
    raw_a = simulate_image(cam, pa, inten, seed=2 * seed, **kw)
    raw_b = simulate_image(cam, pb, inten, seed=2 * seed + 1, **kw)
    return BudgetScene(count, pa, pb, raw_a, raw_b,
                       *(render_particles(grid, p, 1.0, sigma_vox=1.0) for p in (pa, pb)))


def pair_row(pair, scene: BudgetScene, grid: Grid, motion: Motion = UNIFORM) -> dict:
    """The errors and reconstruction quality of one ``process_pair`` result."""
    rep = recovery(pair.vol_a, grid, scene.pa)
    return {"errors": budget_errors(pair.piv, grid, motion), "window": pair.piv.window,
            "Q": quality_q(pair.vol_a, scene.true_a), "recovered": rep.fraction,
            "ghosts": rep.ghost_fraction, "seconds": sum(pair.seconds.values())}


def budget_row(cam: Camera, grid: Grid, proj, ppm: float, seed: int, queue,
               rays: int = 2000, motion: Motion = UNIFORM, baseline: bool = True,
               previous: bool = False) -> dict:
    """The budget of one seeding density (particles per microlens): windows only,
    ``process_pair`` defaults, its volumes by correlation alone, (``previous``) the
    default chain with :data:`PREVIOUS_SETTINGS`' reconstruction, and (``baseline``) the
    chain before (single-frame reconstruction on the voxels themselves, ``supersample=1``,
    correlation only)."""
    scene = budget_scene(cam, grid, ppm, seed, queue, rays, motion)
    windows = budget_errors(piv3d(scene.true_a, scene.true_b, queue=queue), grid, motion)
    pair = process_pair(scene.raw_a, scene.raw_b, proj)
    row = {"ppm": ppm, "particles": scene.count, "windows": windows, "pair": pair,
           "scene": scene, "default": pair_row(pair, scene, grid, motion)}
    t0 = time.perf_counter()
    correlation = piv3d(pair.vol_a, pair.vol_b, queue=proj.queue)
    seconds = pair.seconds["reconstruct_a"] + pair.seconds["reconstruct_b"]
    row["correlation"] = pair_row(dataclasses.replace(pair, piv=correlation, seconds={
        "reconstruct": seconds, "piv": time.perf_counter() - t0}), scene, grid, motion)
    t0 = time.perf_counter()
    unfitted = refine_with_particles(correlation, pair.vol_a, pair.vol_b,
                                     focus=FocalZone.of(cam, grid),
                                     sight=SightLines.of(cam, grid))
    row["volume_particles"] = pair_row(dataclasses.replace(pair, piv=unfitted, seconds={
        "reconstruct": seconds, "piv": pair.seconds["piv"],
        "particles": time.perf_counter() - t0}), scene, grid, motion)
    if previous:
        row["previous"] = pair_row(process_pair(scene.raw_a, scene.raw_b, proj,
                                                reconstruction=PREVIOUS_SETTINGS),
                                   scene, grid, motion)
    if baseline:
        before = process_pair(scene.raw_a, scene.raw_b, proj, reconstruction=BASELINE_SETTINGS,
                              particles=False)
        row["baseline"] = pair_row(before, scene, grid, motion)
    return row


def budget_entries(rows: list[dict]):
    """Each measured chain of each row of :func:`budget_row`, in :data:`ROWS` order:
    ``(row, windows-only errors, chain name, chain result, chain errors)``."""
    for r in rows:
        for label, name in ROWS.items():
            if label in r:
                yield r, r["windows"], name, r[label], r[label]["errors"]


def budget_table(rows: list[dict], grid: Grid) -> str:
    """The rows of :func:`budget_row` as a Markdown table: each reconstruction (default,
    and the baseline where measured) on a line of its own."""
    dz = grid.spacing[0]
    body = []
    for r, w, name, x, e in budget_entries(rows):
        body.append([f"{r['ppm']:.2f}", r["particles"], f"{w['lateral']:.3f}",
                     f"{w['depth']:.3f}", name, f"{e['lateral']:.3f}", f"{e['depth']:.2f}",
                     f"{e['depth'] * dz:.3f}", f"{e['in focus']:.2f}", f"{e['near']:.2f}",
                     f"{e['far']:.2f}", f"{e['valid']:.0%}", str(x["window"]),
                     " ".join(f"{b:+.2f}" for b in e["bias"]), f"{x['Q']:.2f}",
                     f"{x['recovered']:.0%}", f"{x['ghosts']:.0%}", f"{x['seconds']:.1f}"])
    return md_table(["ppm", "particles", "windows only: lateral", "depth", "reconstruction",
                     "lateral", "depth", "depth mm", "in focus", "near", "far", "valid",
                     "final window", "bias x y z", "Q", "recovered", "ghosts", "s/pair"], body)


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
            "the true particles (what the windows cannot resolve); the reconstructions "
            "correlate `process_pair`'s volumes (what users get): by default on 3 x 3 "
            "lateral sub-voxels per voxel with the particle refinement (particles fitted to "
            "the raw images; and as the volumes place them), correlation only, and the "
            "single frame on the voxels themselves "
            "(the default before, same scene); depth by zone: in focus "
            "|z| < 2 mm, near, far. For a uniform displacement the window-averaged and the "
            "point-sampled truth coincide. One scene per seeding (not a median); "
            "`benchmarks/accuracy.py` runs any seeding list.\n\n"
            + budget_table(rows, grid))
