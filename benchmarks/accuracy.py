"""Where the velocity error comes from, at the paper's optics and voxel size: the error
budget of issue 15, lateral and depth separately, as a function of seeding and depth.

    python benchmarks/accuracy.py [--seeding 0.01 0.02 0.05 0.1 0.2] [--lenses 96 64]

Camera: the paper's optics (f = 50 mm, f/2.42, |M| = 0.66, 125 µm microlenses of
f = 500 µm, 7.4 µm pixels, about 17 px per lens) on a window of ``--lenses`` microlenses
(the full sensor has 289 x 193: the depth physics is the same, the run 9x shorter). Grid:
the paper's voxel, 0.183 x 0.175 x 0.133 mm, over 20 mm of depth (150 voxels). Flow: a
uniform displacement of (2.3, -1.4, 1.7) voxels. Images: exact ray tracing, 0.8 px
particle blur, photon noise, a dark level with read noise.

For each seeding (particles per microlens), in the same run:

- **windows**: PIV on volumes rendered from the true particles (Gaussian blobs of
  1 voxel): what the interrogation windows themselves cannot resolve;
- **reconstruction**: PIV on volumes reconstructed from the raw images with
  ``plenocl.process_pair`` defaults (MLEM 30 iterations, median background, windows
  fitted to the volume and its particle count): what the user gets;
- **48-32-24**: the same reconstructed volumes with the fixed schedule the default
  replaced (the baseline of the window choice);
- reconstruction quality: Q against the true-rendered volume, particles recovered, ghost
  intensity fraction.

Errors are RMS over the valid vectors against the imposed displacement (uniform: the
window-averaged and the point-sampled truth coincide), in voxels and mm; lateral is the
RMS over x and y. By depth: in focus (|z| < 2 mm, within about 2 depth resolutions of
the focal plane), near (z < -2 mm) and far (z > 2 mm).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from plenocl import Camera, Grid, Projector, get_queue, process_pair, random_particles
from plenocl.metrics import quality_q, recovery, render_particles
from plenocl.piv import piv3d
from plenocl.simulate import simulate_image

SHIFT_VOX = np.array([2.3, -1.4, 1.7])  # (x, y, z) voxels
VOXEL_MM = (0.1833, 0.175, 0.1333)      # (x, y, z): the paper's 300 x 200 x 150 grid


def setup(lenses: tuple[int, int]) -> tuple[Camera, Grid]:
    """The paper's optics on ``lenses`` microlenses, and the paper's voxel over them."""
    pitch_px = 0.125 * (1 + 0.5 / (50.0 * 1.66)) / 0.0074
    pixels = tuple(int(np.ceil(n * pitch_px)) + 2 for n in lenses)
    cam = Camera(50.0, 2.42, 0.66, 0.125, 0.5, lenses, 0.0074, pixels)
    half = [n * 0.125 / 0.66 / 2 * 0.96 for n in lenses]  # just inside the field of view
    shape = (150, int(2 * half[1] / VOXEL_MM[1]), int(2 * half[0] / VOXEL_MM[0]))
    grid = Grid(shape, x=(-shape[2] * VOXEL_MM[0] / 2, shape[2] * VOXEL_MM[0] / 2),
                y=(-shape[1] * VOXEL_MM[1] / 2, shape[1] * VOXEL_MM[1] / 2), z=(-10.0, 10.0))
    return cam, grid


def errors(res, grid: Grid) -> dict:
    """RMS errors (voxels) of the valid vectors: lateral, depth, and depth by zone."""
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


def one_seeding(cam: Camera, grid: Grid, proj: Projector, ppm: float, seed: int, queue):
    """The budget rows of one seeding density."""
    shift_mm = SHIFT_VOX * np.array(VOXEL_MM)
    box = [(lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z)]
    count = int(round(ppm * cam.ml_count[0] * cam.ml_count[1]))
    pos, inten = random_particles(tuple(box), count=count, seed=seed, intensity=2e4)
    pa, pb = pos - shift_mm / 2, pos + shift_mm / 2
    kw = dict(rays_per_particle=2000, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue)
    raw_a = simulate_image(cam, pa, inten, seed=2 * seed, **kw)
    raw_b = simulate_image(cam, pb, inten, seed=2 * seed + 1, **kw)
    true_a, true_b = (render_particles(grid, p, 1.0, sigma_vox=1.0) for p in (pa, pb))
    t0 = time.perf_counter()
    windows = errors(piv3d(true_a, true_b), grid)
    t_true = time.perf_counter() - t0
    pair = process_pair(raw_a, raw_b, proj)
    rec = errors(pair.piv, grid)
    fixed = errors(piv3d(pair.vol_a, pair.vol_b, windows=(48, 32, 24)), grid)
    rep = recovery(pair.vol_a, grid, pa)
    return {"ppm": ppm, "particles": count, "windows": windows, "reconstruction": rec,
            "fixed": fixed, "final_window": pair.piv.window,
            "Q": quality_q(pair.vol_a, true_a), "recovered": rep.fraction,
            "ghosts": rep.ghost_fraction, "seconds": {**pair.seconds, "piv_true": t_true}}


def print_rows(rows: list[dict], grid: Grid) -> None:
    dz = grid.spacing[0]
    print(f"{'ppm':>5s} {'n':>5s} | {'windows only: lat':>17s} {'depth':>6s} | "
          f"{'reconstructed: lat':>18s} {'depth':>6s} {'(mm)':>6s} {'focus':>6s} "
          f"{'near':>6s} {'far':>6s} {'valid':>6s} {'final window':>13s} | "
          f"{'48-32-24: lat':>13s} {'depth':>6s} | {'Q':>5s} {'recov':>6s} {'ghosts':>6s}")
    for r in rows:
        w, e, f = r["windows"], r["reconstruction"], r["fixed"]
        print(f"{r['ppm']:5.2f} {r['particles']:5d} | {w['lateral']:17.3f} {w['depth']:6.3f} | "
              f"{e['lateral']:18.3f} {e['depth']:6.2f} {e['depth'] * dz:6.3f} "
              f"{e['in focus']:6.2f} {e['near']:6.2f} {e['far']:6.2f} {e['valid']:6.0%} "
              f"{str(r['final_window']):>13s} | {f['lateral']:13.3f} {f['depth']:6.2f} | "
              f"{r['Q']:5.2f} {r['recovered']:6.0%} {r['ghosts']:6.0%}")
    print("bias of the reconstructed field (voxels, x y z):",
          "; ".join(f"{r['ppm']:.2f}: " + " ".join(f"{b:+.2f}" for b in r["reconstruction"]
                                                 ["bias"]) for r in rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeding", type=float, nargs="+",
                        default=[0.01, 0.02, 0.05, 0.1, 0.2])
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    args = parser.parse_args()
    queue = get_queue()
    cam, grid = setup(tuple(args.lenses))
    proj = Projector(cam, grid, queue)
    print(f"device: {queue.device.name.strip()}; load average {os.getloadavg()[0]:.2f}")
    print(f"camera: {cam.describe()}; {cam.pixels[0]} x {cam.pixels[1]} px")
    print(f"grid {grid.shape} (z, y, x), voxel {grid.spacing[2]:.4f} x {grid.spacing[1]:.4f}"
          f" x {grid.spacing[0]:.4f} mm; displacement {SHIFT_VOX.tolist()} voxels (x, y, z)")
    print("RMS displacement error (voxels unless stated) over the valid vectors:")
    rows = []
    for k, ppm in enumerate(args.seeding):
        rows.append(one_seeding(cam, grid, proj, ppm, seed=k + 1, queue=queue))
        s = rows[-1]["seconds"]
        print(f"  seeding {ppm}: " + ", ".join(f"{k} {v:.1f} s" for k, v in s.items()),
              flush=True)
    print_rows(rows, grid)


if __name__ == "__main__":
    main()
