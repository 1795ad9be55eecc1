"""Reconstruction: run time against error for each method and setting, the matrix-free
solver against a scipy.sparse implementation of the same method (same run), and the
time of the paper's full experiment.

    python benchmarks/reconstruct.py [--quick] [--skip-paper] [--repeats 3] [--relax-only]

Scene: the paper's synthetic case, the 850 x 850 px camera (50 x 50 microlenses, M = 1,
f/2) and particles in a 5 mm cube, reconstructed on 20 x 40 x 40 voxels (one microlens
laterally, half the camera's 0.5 mm depth resolution in depth: Grid.for_camera's
default) and, for comparison, on cubic 40^3 voxels (0.125 mm deep, a quarter of the
depth resolution, where in-focus particles smear over +-4 voxels in depth).
Recovery: a peak within 1 voxel laterally and 2 in depth of a true particle. Ghosts:
the fraction of reconstructed intensity farther than (2, 4) voxels from every particle.
"""

from __future__ import annotations

import functools
import statistics
import time

import numpy as np

from plenocl import Camera, Grid, get_queue, random_particles
from plenocl.bench.core import particle_scene
from plenocl.bench.scripts import script_parser
from plenocl.bench.sparse import matrix_bytes, weight_matrix
from plenocl.bench.timing import run_times
from plenocl.metrics import quality_q, recovery, render_particles
from plenocl.opencl.device import device_info
from plenocl.projection import Projector
from plenocl.reconstruction import METHODS, reconstruct
from plenocl.reference import reconstruct as ref
from plenocl.simulate import simulate_image

CUBE = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
CUBIC = Grid((40, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
SETTINGS = [  # label, method, iterations, relax, options
    ("MART (paper)", "mart", 15, 0.7, dict(smooth_px=0)),
    ("SMART", "smart", 30, 1.0, {}),
    ("SMART mlos+mask", "smart", 30, 1.0, dict(start="mlos", mask_fraction=0.5)),
    ("MLEM", "mlem", 10, 1.0, {}),
    ("MLEM", "mlem", 30, 1.0, {}),
    ("MLEM", "mlem", 60, 1.0, {}),
    ("MLEM mlos", "mlem", 30, 1.0, dict(start="mlos")),
    ("MLEM mask 0.5", "mlem", 30, 1.0, dict(mask_fraction=0.5)),
    ("MLEM mlos+mask 0.5", "mlem", 30, 1.0, dict(start="mlos", mask_fraction=0.5)),
    ("MLEM early stop 1e-3", "mlem", 100, 1.0, dict(tol=1e-3)),
]


def table(queue, grid: Grid, counts, settings, repeats: int) -> None:
    """Recovery, ghosts, Q and median time per setting and particle count."""
    cam = Camera.synthetic_850()
    proj = Projector(cam, grid, queue)
    print(f"grid {grid.shape} (voxel {grid.spacing[0]:.3f} mm deep)")
    print(f"{'particles':>9s} {'setting':24s} {'it':>4s} {'time s':>7s} {'recov':>6s} "
          f"{'ghosts':>6s} {'Q':>5s} {'active':>6s}")
    for n in counts:
        pos, inten, img = particle_scene(cam, n, seed=n)
        truth = render_particles(grid, pos, inten)
        for label, method, it, mu, opts in settings:
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                vol, info = reconstruct(img, proj, method, it, mu, return_info=True,
                                        supersample=1, **opts)
                times.append(time.perf_counter() - t0)
            rep = recovery(vol, grid, pos)
            print(f"{n:9d} {label:24s} {info.iterations:4d} {statistics.median(times):7.2f} "
                  f"{rep.fraction:6.2f} {rep.ghost_fraction:6.2f} "
                  f"{quality_q(vol, truth):5.2f} {info.active_fraction:6.2f}", flush=True)


def _skip_settings(method: str) -> tuple[tuple[str, dict], ...]:
    """Every feature for MLEM; for SMART and MART (whose log-ratio back projection reads
    every lens) the baseline and dark-microlens skipping only."""
    off = dict(skip_empty=False, crop=False, skip_dark=False)
    dark = (("none", off), ("dark microlenses", {**off, "skip_dark": True}))
    if method != "mlem":
        return dark
    return (*dark, ("active slices", {**off, "skip_empty": True}),
            ("crop to the lit region", {**off, "crop": True}),
            ("mask 0.5", {**off, "mask_fraction": 0.5}),
            ("mask 0.5 + slices", {**off, "skip_empty": True, "mask_fraction": 0.5}),
            ("defaults", {}), ("defaults + tol 1e-3", dict(tol=1e-3)))


def skipping(queue, repeats: int) -> None:
    """Speed-up of each skipping feature (active slices, cropping to the lit region, dark
    microlenses, masking, early stop) and its effect on error, on a light sheet (particles
    within 1 mm of depth), a lateral quarter of the field and the full cube; for SMART and
    MART, dark-microlens skipping against their own baseline."""
    cam = Camera.synthetic_850()
    proj = Projector(cam, CUBE, queue)
    print(f"\nskipping (default iterations per method, {CUBE.shape} voxels; medians of "
          f"{repeats}; speed-up against 'none' of the same scene and method):")
    print(f"{'scene':18s} {'method':6s} {'setting':24s} {'time s':>7s} {'speed-up':>8s} "
          f"{'recov':>6s} {'ghosts':>6s} {'slices':>6s} {'lit':>5s}")
    for scene_name, box in (("sheet 1 mm deep", ((-2.3, 2.3), (-2.3, 2.3), (-0.5, 0.5))),
                            ("lateral quarter", ((-2.3, 0.0), (0.0, 2.3), (-2.3, 2.3))),
                            ("full 5 mm cube", ((-2.3, 2.3),) * 3)):
        pos, inten, img = particle_scene(cam, 40, seed=9, box=box)
        for method in METHODS:
            base = None
            for label, opts in _skip_settings(method):
                run = functools.partial(reconstruct, img, proj, method, threshold=1.0,
                                        return_info=True, **opts)
                t = statistics.median(run_times(run, repeats))
                vol, info = run()
                base = base or t
                rep = recovery(vol, CUBE, pos)
                slices = info.active_slices[-1] if info.active_slices else CUBE.shape[0]
                print(f"{scene_name:18s} {method:6s} {label:24s} {t:7.2f} {base / t:7.2f}x "
                      f"{rep.fraction:6.2f} {rep.ghost_fraction:6.3f} {slices:6d} "
                      f"{info.lit_lens_fraction:5.2f}", flush=True)


def seed_study(queue, seeds: int = 20, counts=(20, 60)) -> None:
    """Recovery of the default (MLEM, 30 iterations) over many scenes: mean and worst, on
    the depth-matched grid and on cubic voxels, against the paper's MART on the same
    scenes (issue 5's targets: >= 90 % of 20 and >= 80 % of 60 particles)."""
    cam = Camera.synthetic_850()
    projs = {"20x40x40": Projector(cam, CUBE, queue), "cubic 40^3": Projector(cam, CUBIC, queue)}
    print(f"\nrecovery over {seeds} scenes (mean / worst):")
    print(f"{'particles':>9s} {'grid':12s} {'MLEM 30':>14s} {'MART (paper)':>14s}")
    for n in counts:
        scenes = [particle_scene(cam, n, seed=5000 + k) for k in range(seeds)]
        for name, proj in projs.items():
            rec = {m: [recovery(reconstruct(img, proj, m, it, mu, supersample=1, smooth_px=0),
                                proj.grid, pos).fraction for pos, _, img in scenes]
                   for m, it, mu in (("mlem", 30, 1.0), ("mart", 15, 0.7))}
            cells = [f"{np.mean(v):.2f} / {min(v):.2f}" for v in rec.values()]
            print(f"{n:9d} {name:12s} {cells[0]:>14s} {cells[1]:>14s}", flush=True)


def coarse_to_fine(queue, counts=(20, 60, 150), seeds=3) -> None:
    """Does coarse-to-fine pay? MLEM on 2x coarser voxels, upsampled as the start of a few
    fine iterations, against plain MLEM on the fine grid (means over ``seeds`` scenes)."""
    cam = Camera.synthetic_850()
    coarse = Grid(tuple(n // 2 for n in CUBE.shape), CUBE.x, CUBE.y, CUBE.z)
    fine_p, coarse_p = Projector(cam, CUBE, queue), Projector(cam, coarse, queue)
    print(f"\ncoarse-to-fine ({coarse.shape} then {CUBE.shape}), means over {seeds} scenes:")
    print(f"{'particles':>9s} {'schedule':28s} {'time s':>7s} {'recov':>6s}")
    for n in counts:
        rows: dict[str, list] = {}
        for seed in range(seeds):
            pos, _, img = particle_scene(cam, n, seed=300 + seed)
            for label, kc, kf in (("fine MLEM 30", 0, 30), ("fine MLEM 10", 0, 10),
                                  ("coarse 20 + fine 10", 20, 10),
                                  ("coarse 10 + fine 5", 10, 5)):
                t0 = time.perf_counter()
                start = "uniform"
                if kc:
                    vc = reconstruct(img, coarse_p, iterations=kc, supersample=1)
                    start = vc.repeat(2, 0).repeat(2, 1).repeat(2, 2) / 8
                vol = reconstruct(img, fine_p, iterations=kf, start=start, supersample=1)
                rows.setdefault(label, []).append((time.perf_counter() - t0,
                                                   recovery(vol, CUBE, pos).fraction))
        for label, vals in rows.items():
            t, r = np.mean(vals, axis=0)
            print(f"{n:9d} {label:28s} {t:7.2f} {r:6.2f}", flush=True)


def sparse_comparison(queue, repeats: int) -> None:
    """The same MLEM (30 iterations) matrix-free on the device and with scipy.sparse CSR, on
    the grid of the study above (its CSR matrix still fits in memory)."""
    cam = Camera.synthetic_850()
    grid = CUBE
    proj = Projector(cam, grid, queue)
    _, _, img = particle_scene(cam, 20, seed=5)
    t0 = time.perf_counter()
    W = weight_matrix(proj)
    t_build = time.perf_counter() - t0
    norm = img / img.max()

    def device():
        return reconstruct(img, proj, "mlem", 30, supersample=1)

    def stored():
        return ref.mlem(W, norm, 30) * img.max()

    t_dev = statistics.median(run_times(device, repeats))
    t_csr = statistics.median(run_times(stored, repeats))
    agree = np.corrcoef(device().ravel(), stored().ravel())[0, 1]
    print(f"\nMLEM, 30 iterations, {grid.shape} voxels, {W.nnz / 1e6:.1f} M non-zeros "
          f"(CSR {matrix_bytes(W) / 2**20:.0f} MiB, built in {t_build:.1f} s):")
    print(f"  matrix-free (device) {t_dev:7.2f} s   scipy.sparse CSR {t_csr:7.2f} s   "
          f"speed-up {t_csr / t_dev:.1f}x   volumes agree: r = {agree:.5f}")


def paper_experiment(queue) -> None:
    """The paper's full experiment: 16 MP camera, 300 x 200 x 150 voxels, 5 iterations."""
    cam = Camera.paper_16mp()
    grid = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0))
    pos, inten = random_particles(((-27, 27), (-17, 17), (-9.5, 9.5)), count=5000, seed=3,
                                  intensity=1e4)
    img = simulate_image(cam, pos, inten, 2000, seed=3)
    t0 = time.perf_counter()
    proj = Projector(cam, grid, queue)
    t_setup = time.perf_counter() - t0
    print(f"\npaper's experiment: 16 MP, {grid.shape[::-1]} voxels, 5000 particles; "
          f"projector set-up {t_setup:.1f} s")
    for label, method, mu in (("MART, mu = 1 (paper)", "mart", 1.0), ("MLEM (default)", "mlem",
                                                                       1.0)):
        t0 = time.perf_counter()
        _, info = reconstruct(img, proj, method, 5, mu, return_info=True, supersample=1,
                              smooth_px=0)
        print(f"  {label:22s} 5 iterations: {time.perf_counter() - t0:7.1f} s "
              f"(residual {info.residuals[-1]:.3f})", flush=True)


def relax_cost(queue, repeats: int, n: int = 81_000_000) -> None:
    """One MLEM update (``kernels/solver.cl`` update_mlem) of a paper-size sub-voxel grid
    (81 M sub-voxels, 7 % non-zero as a coarse-to-fine support) at μ = 1, at the pair's
    μ = 1.5 (a square root) and at μ = 1.3 (``pow``), taking turns; medians."""
    import pyopencl.array as cla

    from plenocl.opencl.program import KernelSet

    kernels = KernelSet(queue, "solver.cl", ("update_mlem",))
    rng = np.random.default_rng(0)
    start = np.where(rng.random(n, np.float32) < 0.07, np.float32(1), np.float32(0))
    vol = cla.to_device(queue, start)
    ratio = cla.to_device(queue, rng.random(n, np.float32) + np.float32(0.5))
    sens = cla.to_device(queue, np.full(n, 0.9, np.float32))
    times: dict[float, list] = {mu: [] for mu in (1.0, 1.5, 1.3)}
    for _ in range(repeats):
        for mu in times:
            vol.set(start)
            queue.finish()
            t0 = time.perf_counter()
            kernels.launch("update_mlem", (n,), vol, ratio, sens, np.float32(mu),
                           np.float32(0.5), np.int32(n))
            queue.finish()
            times[mu].append(time.perf_counter() - t0)
    print(f"\nMLEM update of {n / 1e6:.0f} M sub-voxels (medians of {repeats}): "
          + ", ".join(f"μ = {mu:g} {statistics.median(t):.3f} s" for mu, t in times.items()))


def main() -> None:
    parser = script_parser(__doc__, {"paper": None})
    parser.add_argument("--quick", action="store_true", help="20 and 60 particles, fewer rows")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--relax-only", action="store_true",
                        help="only the cost of the MLEM update's relaxation")
    args = parser.parse_args()
    queue = get_queue()
    info = device_info(queue)
    print(f"device: {info.name} ({info.platform})\n")
    relax_cost(queue, max(args.repeats, 5))
    if args.relax_only:
        return
    counts = (20, 60) if args.quick else (20, 60, 150)
    settings = SETTINGS[:5] if args.quick else SETTINGS
    table(queue, CUBE, counts, settings, args.repeats)
    print()
    table(queue, CUBIC, counts, [SETTINGS[0], SETTINGS[4]], args.repeats)
    seed_study(queue, 5 if args.quick else 20)
    skipping(queue, max(args.repeats, 3))
    coarse_to_fine(queue, counts)
    sparse_comparison(queue, max(args.repeats, 3))
    if not args.skip_paper:
        paper_experiment(queue)


if __name__ == "__main__":
    main()
