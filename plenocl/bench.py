"""The one-command benchmark report: every stage timed against a baseline from the same run.

``plenocl bench --size ci|small|paper --out DIR`` (or :func:`run_report`) runs the stage
benchmarks and writes ``DIR/report.md`` with PNG plots beside it:

- simulator: rays per second of the OpenCL kernel against the NumPy reference (same rays);
- projector: matrix-free forward + back against ``scipy.sparse`` CSR products of the same
  weights, and the memory of both;
- reconstruction: run time against error (recovery, ghosts, Q) for each method and
  setting on the paper's synthetic case, with Pareto fronts;
- skipping: speed-up and error cost of masking, active slices and early stop;
- PIV: run time against RMS error for window schedules, deformation orders and final
  iterations (and openpiv's 3-D PIV when it is importable);
- scaling: time and memory against voxels, pixels, particles and iterations, with fitted
  log-log slopes, set against the device's memory and the measured throughput.

Sizes: ``ci`` (about 1-2 minutes on 2 CPU cores), ``small`` (10-15 minutes), ``paper``
(``small`` plus the paper's full 16 MP, 300 x 200 x 150 experiment) and an internal
``test`` size (a tiny camera; seconds). Times are medians of repeated runs after a
warm-up of the kernels; the report states the repeat counts.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import flows
from .camera import Camera
from .device import DeviceLike, device_info, get_queue
from .grid import Grid
from .io import atomic_path
from .metrics import quality_q, recovery, render_particles
from .particles import random_particles
from .piv import piv3d
from .projector import Projector
from .reconstruct import reconstruct
from .reference.simulate import trace_particles
from .simulate import Simulator
from .sparse import matrix_bytes, weight_matrix
from .timing import median_time

SIZES = ("ci", "small", "paper")
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
#: (label, method, iterations, relax, options) of a reconstruction setting.
ReconSetting = tuple[str, str, int, float, dict]

# ---- configuration ----------------------------------------------------------------------
_CUBE = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
_RECON_CI: tuple[ReconSetting, ...] = (
    ("MART (paper)", "mart", 15, 0.7, {}),
    ("SMART", "smart", 30, 1.0, {}),
    ("MLEM", "mlem", 5, 1.0, {}),
    ("MLEM", "mlem", 10, 1.0, {}),
    ("MLEM", "mlem", 30, 1.0, {}),
    ("MLEM mlos start", "mlem", 10, 1.0, {"start": "mlos"}),
    ("MLEM mask 0.5", "mlem", 10, 1.0, {"mask_fraction": 0.5}),
    ("MLEM skip_empty off", "mlem", 10, 1.0, {"skip_empty": False}),
    ("MLEM tol 1e-3", "mlem", 60, 1.0, {"tol": 1e-3}),
)
_RECON_SMALL: tuple[ReconSetting, ...] = (
    *_RECON_CI[:5],
    ("MLEM", "mlem", 60, 1.0, {}),
    ("MLEM mlos start", "mlem", 30, 1.0, {"start": "mlos"}),
    ("MLEM mask 0.5", "mlem", 30, 1.0, {"mask_fraction": 0.5}),
    ("MLEM mlos + mask 0.5", "mlem", 30, 1.0, {"start": "mlos", "mask_fraction": 0.5}),
    ("SMART mlos + mask 0.5", "smart", 30, 1.0, {"start": "mlos", "mask_fraction": 0.5}),
    ("MLEM skip_empty off", "mlem", 30, 1.0, {"skip_empty": False}),
    ("MLEM tol 1e-3", "mlem", 100, 1.0, {"tol": 1e-3}),
)
_RECON_TEST: tuple[ReconSetting, ...] = (
    ("MART (paper)", "mart", 3, 0.7, {}),
    ("SMART", "smart", 3, 1.0, {}),
    ("MLEM", "mlem", 2, 1.0, {}),
    ("MLEM", "mlem", 4, 1.0, {}),
    ("MLEM mlos start", "mlem", 2, 1.0, {"start": "mlos"}),
    ("MLEM mask 0.5", "mlem", 2, 1.0, {"mask_fraction": 0.5}),
    ("MLEM skip_empty off", "mlem", 2, 1.0, {"skip_empty": False}),
    ("MLEM tol 1e-3", "mlem", 6, 1.0, {"tol": 1e-3}),
)
_PIV_SETTINGS: tuple[tuple[str, dict], ...] = (
    ("48-32-24, cubic, 3 final (default)", {}),
    ("32-24-16", {"windows": (32, 24, 16)}),
    ("32-16, 1 final", {"windows": (32, 16), "final_iterations": 1}),
    ("deform_order 1 (trilinear)", {"deform_order": 1}),
    ("deform_order 5 (quintic)", {"deform_order": 5}),
    ("final_iterations 1", {"final_iterations": 1}),
    ("final_iterations 5", {"final_iterations": 5}),
)
_PIV_TEST: tuple[tuple[str, dict], ...] = (
    ("24-16, 1 final", {"windows": (24, 16), "final_iterations": 1}),
    ("16, deform_order 1", {"windows": (16,), "final_iterations": 2, "deform_order": 1}),
)


@dataclass(frozen=True)
class BenchSize:
    """What one report size runs (scenes, settings, repeats)."""

    name: str
    repeats: int                      # cheap stages: simulator, projector, scaling
    heavy_repeats: int                # reconstruction, skipping, PIV
    camera: str                       # "synthetic" (850 x 850) or "tiny" (12 x 12 lenses)
    grid: Grid                        # the reconstruction grid
    box: Box                          # where particles are seeded (mm)
    counts: tuple[int, ...]           # particles of the reconstruction scenes
    rays: int                         # rays per particle of the reconstruction images
    recon: tuple[ReconSetting, ...]
    sim: tuple[int, int, int]         # particles, kernel rays, reference rays per particle
    csr_grid: tuple[int, int, int]    # grid of the stored-matrix comparison
    skip_iterations: int
    skip_particles: int
    piv_shape: tuple[int, int, int]
    piv: tuple[tuple[str, dict], ...]
    openpiv: tuple[tuple[int, int], ...]   # (window, overlap) voxels
    scale_voxels: tuple[tuple[int, int, int], ...]
    scale_lenses: tuple[int, ...]          # square arrays of 17 px lenses
    scale_particles: tuple[int, ...]
    scale_rays: int
    scale_iterations: tuple[int, ...]
    paper: bool = False


def _sizes() -> dict[str, BenchSize]:
    """The report sizes (``test`` is internal: a tiny camera, for the test suite)."""
    ci = BenchSize(
        name="ci", repeats=3, heavy_repeats=2, camera="synthetic", grid=_CUBE,
        box=((-2.3, 2.3),) * 3, counts=(30,), rays=20000, recon=_RECON_CI,
        sim=(200, 20000, 2000), csr_grid=(10, 20, 20), skip_iterations=20,
        skip_particles=40, piv_shape=(48, 48, 48), piv=_PIV_SETTINGS, openpiv=((24, 12),),
        scale_voxels=((8, 16, 16), (16, 32, 32), (32, 64, 64)), scale_lenses=(25, 50, 100),
        scale_particles=(100, 1000, 10000), scale_rays=500, scale_iterations=(2, 4, 8, 16))
    small = dataclasses.replace(
        ci, name="small", repeats=5, heavy_repeats=3, counts=(20, 60, 150),
        recon=_RECON_SMALL, csr_grid=(20, 40, 40), skip_iterations=30,
        piv_shape=(96, 96, 96), openpiv=((32, 16), (24, 18)),
        scale_voxels=((8, 16, 16), (16, 32, 32), (32, 64, 64), (64, 128, 128)),
        scale_lenses=(25, 50, 100, 200), scale_particles=(100, 1000, 10000, 50000),
        scale_rays=1000, scale_iterations=(4, 8, 16, 32, 64))
    test = BenchSize(
        name="test", repeats=2, heavy_repeats=1, camera="tiny",
        grid=Grid((6, 10, 10), x=(-0.6, 0.6), y=(-0.6, 0.6), z=(-0.6, 0.6)),
        box=((-0.5, 0.5),) * 3, counts=(6,), rays=2000, recon=_RECON_TEST,
        sim=(20, 1000, 200), csr_grid=(3, 6, 6), skip_iterations=4, skip_particles=8,
        piv_shape=(32, 32, 32), piv=_PIV_TEST, openpiv=((16, 8),),
        scale_voxels=((3, 6, 6), (6, 12, 12)), scale_lenses=(12, 16),
        scale_particles=(10, 40), scale_rays=200, scale_iterations=(1, 2, 4))
    paper = dataclasses.replace(small, name="paper", paper=True)
    return {"ci": ci, "small": small, "paper": paper, "test": test}


def camera_for(name: str, lenses: int | None = None) -> Camera:
    """The benchmark cameras: ``"synthetic"`` (the paper's 850 x 850 px), ``"tiny"`` (12 x 12
    lenses) or, with ``lenses``, a square array of that many 17 px lenses (M = 1, f/2)."""
    if lenses is None:
        lenses = {"synthetic": 50, "tiny": 12}[name]
    return Camera(50.0, 2.0, 1.0, 0.125, 0.5, (lenses, lenses), 0.0074, (17 * lenses,) * 2)


# ---- run state, timing, tables --------------------------------------------------------
@dataclass
class _Run:
    """The state one report run shares between its sections."""

    cfg: BenchSize
    queue: object
    out: Path
    log: Callable[..., None]
    repeats: int
    heavy: int
    notes: list[str] = field(default_factory=list)
    csr: tuple[float, float] | None = None  # CSR weights/s (forward + back), bytes per weight

    @property
    def camera(self) -> Camera:
        """The camera of the report size's scenes."""
        return camera_for(self.cfg.camera)


def timed(fn: Callable[[], object], repeats: int) -> tuple[object, float]:
    """The result of the last of ``repeats`` calls of ``fn()`` and their median wall time.

    No warm-up call: callers warm up with a cheaper call of the same setting (one
    iteration), as these runs are long.
    """
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def host_peak_bytes(fn: Callable[[], object]) -> int:
    """Peak host memory (bytes, ``tracemalloc``) newly allocated during one call of ``fn()``."""
    tracemalloc.start()
    try:
        fn()
        return int(tracemalloc.get_traced_memory()[1])
    finally:
        tracemalloc.stop()


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured Markdown table (cells as given, ``str()``-ed)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def pareto_front(cost, score, higher_is_better: bool = True) -> np.ndarray:
    """Which points no other point dominates (lower ``cost`` and better ``score``).

    A point is dominated when another costs no more and scores no worse, and is strictly
    better in one of the two. Points with a non-finite cost or score are never on the
    front.

    Parameters
    ----------
    cost
        Cost per point (e.g. run time), lower is better.
    score
        Quality per point (e.g. recovery, or an error with ``higher_is_better=False``).
    higher_is_better
        Whether a larger ``score`` is better.

    Returns
    -------
    numpy.ndarray
        Boolean mask, ``True`` on the front.
    """
    c = np.asarray(cost, float)
    s = np.asarray(score, float) * (1.0 if higher_is_better else -1.0)
    ok = np.isfinite(c) & np.isfinite(s)
    front = np.zeros(c.shape, bool)
    for i in np.flatnonzero(ok):
        better = (c < c[i]) | (s > s[i])
        front[i] = not np.any(ok & (c <= c[i]) & (s >= s[i]) & better)
    return front


def loglog_slope(n, y) -> float:
    """Least-squares slope of ``log y`` against ``log n`` (NaN with fewer than 2 points)."""
    n, y = np.asarray(n, float), np.asarray(y, float)
    ok = (n > 0) & (y > 0) & np.isfinite(y)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(n[ok]), np.log(y[ok]), 1)[0])


def _reshaped(grid: Grid, shape: tuple[int, int, int]) -> Grid:
    """The same volume as ``grid`` on ``shape`` voxels."""
    return Grid(shape, x=grid.x, y=grid.y, z=grid.z)


def _runs(n: int) -> str:
    return "1 run" if n == 1 else f"{n} runs"


def _mib(nbytes: float) -> str:
    return f"{nbytes / 2**20:.2f}"


def _scene(run: _Run, count: int, seed: int, box: Box | None = None):
    """Particles (mm, intensities) in ``box`` and their noise-free raw image."""
    pos, inten = random_particles(box or run.cfg.box, count=count, seed=seed, intensity=1e4)
    img = Simulator(run.camera, run.queue).trace(pos, inten, run.cfg.rays, seed=seed)
    return pos, inten, img


# ---- simulator ----------------------------------------------------------------------
def section_simulator(run: _Run) -> str:
    """Rays per second of the kernel against the NumPy reference tracing the same rays."""
    n, rays, ref_rays = run.cfg.sim
    cam, sim = run.camera, Simulator(run.camera, run.queue)
    pos, inten = random_particles(run.cfg.box, count=n, seed=1)
    t_dev = median_time(lambda: sim.trace(pos, inten, rays, seed=1), run.repeats)
    t_same = median_time(lambda: sim.trace(pos, inten, ref_rays, seed=1), run.repeats)
    t_ref = median_time(lambda: trace_particles(cam, pos, inten, ref_rays, 1), run.repeats)
    same = np.corrcoef(sim.trace(pos, inten, ref_rays, 1).ravel(),
                       trace_particles(cam, pos, inten, ref_rays, 1).ravel())[0, 1]
    rows = [[f"OpenCL kernel, {n} x {rays} rays", n * rays, f"{t_dev:.4f}",
             f"{n * rays / t_dev / 1e6:.2f}"],
            [f"OpenCL kernel, {n} x {ref_rays} rays", n * ref_rays, f"{t_same:.4f}",
             f"{n * ref_rays / t_same / 1e6:.2f}"],
            [f"NumPy reference, the same {n} x {ref_rays} rays", n * ref_rays,
             f"{t_ref:.4f}", f"{n * ref_rays / t_ref / 1e6:.2f}"]]
    run.notes.append(f"simulator: {n * rays / t_dev / 1e6:.1f} M rays/s, {t_ref / t_same:.1f}x "
                     "the NumPy reference at equal work")
    return (f"## Simulator\n\nCamera {cam.pixels[0]} x {cam.pixels[1]} px, {cam.ml_count[0]} x "
            f"{cam.ml_count[1]} lenses; {n} particles. Medians of {_runs(run.repeats)} after a "
            "warm-up; each run includes the image buffer fill and read-back.\n\n"
            + md_table(["path", "rays", "median s", "M rays/s"], rows)
            + f"\nSpeed-up at equal work (kernel vs reference): **{t_ref / t_same:.1f}x**; "
            f"kernel rays/s at {rays} rays per particle vs reference rays/s: "
            f"{(n * rays / t_dev) / (n * ref_rays / t_ref):.1f}x. Images of the same rays "
            f"correlate at r = {same:.7f}.\n")


# ---- projector ----------------------------------------------------------------------
def projector_bytes(proj: Projector) -> int:
    """Device bytes the projector holds itself: weight tables and scratch buffers."""
    bufs = list(getattr(proj, "_d", {}).values()) + list(getattr(proj, "_scratch", {}).values())
    return int(sum(b.nbytes for b in bufs))


def device_pair(proj: Projector, vol: np.ndarray):
    """Device-resident ``forward()`` and ``back()`` callables (as the solver runs them) and
    the bytes of the buffers they use (volume in and out, image, tables, scratch)."""
    slabs, img, out = proj.volume_to_device(vol), proj.empty_image(), proj.empty_volume()

    def forward() -> None:
        proj.forward_device(slabs, img)
        proj.queue.finish()

    def back() -> None:
        proj.back_device(img, out)
        proj.queue.finish()

    forward()
    back()
    return forward, back, 2 * vol.nbytes + img.nbytes + projector_bytes(proj)


def estimated_weights(proj: Projector, samples: int = 48, seed: int = 0) -> float:
    """Non-zeros of the weight matrix, estimated from the footprints of sampled voxels."""
    rng = np.random.default_rng(seed)
    vox = np.column_stack([rng.integers(0, n, samples) for n in proj.shape])
    return float(np.mean([len(proj.voxel_weights(*v)[0]) for v in vox]) * proj.grid.size)


def _csr_rows(run: _Run, proj: Projector, a, vol, img_h) -> tuple[list[list], float]:
    """Table rows of CSR against the matrix-free path, and the device-resident speed-up."""
    fwd, back, dev_bytes = device_pair(proj, vol)
    x, y, r = vol.ravel(), img_h.ravel(), run.repeats
    t_fc, t_bc = median_time(lambda: a @ x, r), median_time(lambda: a.T @ y, r)
    t_f, t_b = median_time(fwd, r), median_time(back, r)
    t_h = median_time(lambda: (proj.forward(vol), proj.back(img_h)), r)
    rate, speedup = a.nnz / 1e6, (t_fc + t_bc) / (t_f + t_b)
    rows = [["scipy.sparse CSR (A x, Aᵀ y)", f"{t_fc:.4f}", f"{t_bc:.4f}", f"{t_fc + t_bc:.4f}",
             f"{2 * rate / (t_fc + t_bc):.0f}", _mib(matrix_bytes(a)), "1.0x"],
            ["matrix-free, device-resident", f"{t_f:.4f}", f"{t_b:.4f}", f"{t_f + t_b:.4f}",
             f"{2 * rate / (t_f + t_b):.0f}", _mib(dev_bytes), f"**{speedup:.1f}x**"],
            ["matrix-free, host arrays in/out", "", "", f"{t_h:.4f}", f"{2 * rate / t_h:.0f}",
             "", f"{(t_fc + t_bc) / t_h:.1f}x"]]
    run.csr = (2 * a.nnz / (t_fc + t_bc), matrix_bytes(a) / a.nnz)
    run.notes.append(f"projector forward + back: {speedup:.1f}x scipy CSR on "
                     f"{proj.grid.size:,} voxels")
    return rows, speedup


_CSR_WINS = ("\nCSR wins on a grid this small: the matrix-free path has fixed per-pixel stages "
             "(light field to image and back), and its time grows slowly with voxels while "
             "CSR's grows with the weights (see Scaling for an extrapolation; `--size small` "
             "stores a 32 000-voxel matrix).\n")


def section_projector(run: _Run) -> str:
    """Matrix-free forward + back against CSR products of the same weights; memory."""
    grid = _reshaped(run.cfg.grid, run.cfg.csr_grid)
    proj = Projector(run.camera, grid, run.queue)
    t0 = time.perf_counter()
    a = weight_matrix(proj)
    build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    vol = rng.random(grid.shape, dtype=np.float32)
    img_h = rng.random(proj.image_shape, dtype=np.float32)
    ref = a @ vol.ravel()
    err = np.abs(ref - proj.forward(vol).ravel()).max() / ref.max()
    rows, speedup = _csr_rows(run, proj, a, vol, img_h)
    return (f"## Projector\n\nGrid {grid.shape} (z, y, x) over the scene's volume, "
            f"{a.nnz:,} weights ({a.nnz / grid.size:.0f} per voxel); the CSR matrix was built "
            f"from the footprint kernel in {build:.1f} s (not counted). Medians of "
            f"{_runs(run.repeats)}; weights/s counts both products. Memory: the CSR matrix "
            "against every device buffer the matrix-free path uses (volume in and out, "
            "image, tables, scratch). Kernel vs CSR forward: max relative difference "
            f"{err:.1e}.\n\n" + md_table(["path", "forward s", "back s", "forward + back s",
                                             "M weights/s", "memory MiB", "speed-up"], rows)
            + (_CSR_WINS if speedup < 1 else "")
            + (_paper_projector(run) if run.cfg.paper else ""))


def paper_grid() -> tuple[Camera, Grid]:
    """The paper's experiment: the 16 MP camera and 300 x 200 x 150 voxels."""
    return Camera.paper_16mp(), Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5),
                                     z=(-10.0, 10.0))


def _paper_projector(run: _Run) -> str:
    cam, grid = paper_grid()
    proj = Projector(cam, grid, run.queue)
    nnz = estimated_weights(proj, 300, seed=1)
    vol = np.random.default_rng(1).random(grid.shape, dtype=np.float32)
    fwd, back, dev_bytes = device_pair(proj, vol)
    t_f, t_b = median_time(fwd, run.heavy), median_time(back, run.heavy)
    return (f"\nThe paper's experiment ({cam.pixels[0]} x {cam.pixels[1]} px, grid "
            f"{grid.shape}): about {nnz:.2e} weights; CSR would need about "
            f"{nnz * 8 / 2**30:.0f} GiB (not measurable here), the matrix-free path "
            f"{dev_bytes / 2**30:.2f} GiB of device buffers. Forward {t_f:.2f} s + back "
            f"{t_b:.2f} s = **{t_f + t_b:.2f} s** ({2 * nnz / (t_f + t_b) / 1e9:.2f} G "
            f"weights/s; medians of {_runs(run.heavy)}).\n")


# ---- reconstruction -------------------------------------------------------------------
def _recon_row(run: _Run, proj: Projector, scene, setting: ReconSetting, truth) -> dict:
    """Median time and errors of one reconstruction setting on one scene."""
    label, method, iterations, relax, opts = setting
    pos, _, img = scene
    reconstruct(img, proj, method, 1, relax, **opts)  # warm-up: PoCL compiles at first launch
    (vol, info), seconds = timed(lambda: reconstruct(img, proj, method, iterations, relax,
                                                     return_info=True, **opts), run.heavy)
    rep = recovery(vol, proj.grid, pos)
    return {"label": label, "method": method, "max_it": iterations, "it": info.iterations,
            "relax": relax, "opts": opts, "seconds": seconds, "recovery": rep.fraction,
            "ghosts": rep.ghost_fraction, "q": quality_q(vol, truth),
            "slices": info.active_slices[-1] if info.active_slices else proj.shape[0]}


def _options_text(opts: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in opts.items()) or "defaults"


def _recon_table(rows: list[dict]) -> str:
    out = []
    for count in sorted({r["count"] for r in rows}):
        sub = [r for r in rows if r["count"] == count]
        f_rec = pareto_front([r["seconds"] for r in sub], [r["recovery"] for r in sub])
        f_q = pareto_front([r["seconds"] for r in sub], [r["q"] for r in sub])
        for r, a, b in zip(sub, f_rec, f_q):
            r["front_recovery"], r["front_q"] = bool(a), bool(b)
            r["number"] = len(out) + 1
            out.append([r["number"], count, r["label"], f"{r['it']}/{r['max_it']}",
                        f"{r['relax']:g}", _options_text(r["opts"]), f"{r['seconds']:.2f}",
                        f"{r['recovery']:.2f}", f"{r['ghosts']:.3f}", f"{r['q']:.3f}",
                        r["slices"], ("R" if a else "") + ("Q" if b else "")])
    return md_table(["#", "particles", "setting", "iterations run/max", "μ", "options", "time s",
                     "recovery", "ghosts", "Q", "active slices", "front"], out)


def section_reconstruction(run: _Run) -> str:
    """Run time against recovery, ghosts and Q for each method and setting; Pareto plot."""
    from .bench_plots import plot_recon_pareto

    grid, rows = run.cfg.grid, []
    proj = Projector(run.camera, grid, run.queue)
    for count in run.cfg.counts:
        scene = _scene(run, count, seed=count)
        truth = render_particles(grid, scene[0], scene[1])
        for setting in run.cfg.recon:
            rows.append({"count": count, **_recon_row(run, proj, scene, setting, truth)})
            run.log(f"  {count} particles, {setting[0]} {setting[2]} it: "
                    f"{rows[-1]['seconds']:.2f} s")
    table = _recon_table(rows)
    plot_recon_pareto(rows, run.out / "recon_pareto.png")
    cam = run.camera
    text = (f"## Reconstruction: run time against error\n\nThe paper's synthetic case: "
            f"{cam.pixels[0]} x {cam.pixels[1]} px camera, particles uniform in "
            f"{_box_text(run.cfg.box)}, noise-free images of {run.cfg.rays} rays per particle, "
            f"grid {grid.shape} (z, y, x) over x {grid.x}, y {grid.y}, z {grid.z} mm. Time: "
            f"median of {_runs(run.heavy)} of `reconstruct()` (after a 1-iteration warm-up of "
            "the same setting), image in, "
            "volume out. Recovery: a peak within 1 voxel laterally and 2 in depth of a true "
            "particle; ghosts: fraction of the intensity farther than (2, 4) voxels from every "
            "particle; Q against the particles rendered as Gaussians (σ 0.6 voxel). "
            "front: on the Pareto front of time vs recovery (R) or time vs Q (Q); the plot "
            "numbers points by the # column.\n\n"
            + table + "\n![time vs recovery and Q](recon_pareto.png)\n")
    return text + (_paper_reconstruction(run) if run.cfg.paper else "")


def _box_text(box: Box) -> str:
    return " x ".join(f"[{a:g}, {b:g}]" for a, b in box) + " mm"


def _paper_reconstruction(run: _Run) -> str:
    cam, grid = paper_grid()
    pos, inten = random_particles(((-27, 27), (-17, 17), (-9.5, 9.5)), count=5000, seed=3,
                                  intensity=1e4)
    img = Simulator(cam, run.queue).trace(pos, inten, 2000, seed=3)
    proj = Projector(cam, grid, run.queue)
    rows = []
    for label, method, mu in (("MART μ = 1 (paper)", "mart", 1.0), ("MLEM (default)", "mlem",
                                                                     1.0)):
        (vol, info), t = timed(lambda m=method, u=mu: reconstruct(img, proj, m, 5, u,
                                                                  return_info=True), run.heavy)
        rep = recovery(vol, grid, pos)
        rows.append([label, 5, f"{t:.1f}", f"{rep.fraction:.2f}", f"{rep.ghost_fraction:.3f}"])
        run.log(f"  paper experiment {label}: {t:.1f} s")
    return (f"\nThe paper's experiment (16 MP, grid (150, 200, 300), 5000 particles in "
            f"54 x 34 x 19 mm, 2000 rays each; medians of {_runs(run.heavy)}, no warm-up):\n\n"
            + md_table(["method", "iterations", "time s", "recovery", "ghosts"], rows))


# ---- skipping -------------------------------------------------------------------------
_SKIP_FEATURES: tuple[tuple[str, dict], ...] = (
    ("none (baseline)", {"skip_empty": False}),
    ("active slices", {}),
    ("masking 0.5", {"skip_empty": False, "mask_fraction": 0.5}),
    ("masking 0.5 + active slices", {"mask_fraction": 0.5}),
    ("early stop tol 1e-3", {"skip_empty": False, "tol": 1e-3}),
    ("all three", {"mask_fraction": 0.5, "tol": 1e-3}),
)


def _skip_scenes(run: _Run) -> dict[str, Box]:
    """A light sheet (the middle fifth of the seeded depth) and the full seeded cube."""
    (x, y, (z0, z1)) = run.cfg.box
    mid, half = 0.5 * (z0 + z1), 0.1 * (z1 - z0)
    return {f"light sheet {2 * half:g} mm deep": (x, y, (mid - half, mid + half)),
            f"full cube {z1 - z0:g} mm deep": run.cfg.box}


def _skip_rows(run: _Run, proj: Projector, name: str, box: Box) -> list[list]:
    pos, inten, img = _scene(run, run.cfg.skip_particles, seed=9, box=box)
    truth, rows, base = render_particles(proj.grid, pos, inten), [], None
    for label, opts in _SKIP_FEATURES:
        reconstruct(img, proj, "mlem", 1, threshold=1.0, **opts)  # warm-up
        (vol, info), t = timed(lambda o=opts: reconstruct(
            img, proj, "mlem", run.cfg.skip_iterations, threshold=1.0, return_info=True, **o),
            run.heavy)
        rep, q = recovery(vol, proj.grid, pos), quality_q(vol, truth)
        base = base or (t, rep.fraction, q)
        slices = info.active_slices[-1] if info.active_slices else proj.shape[0]
        rows.append([name, label, f"{t:.2f}", f"{base[0] / t:.2f}x", f"{rep.fraction:.2f}",
                     f"{rep.fraction - base[1]:+.2f}", f"{rep.ghost_fraction:.3f}", f"{q:.3f}",
                     f"{q - base[2]:+.3f}", info.iterations, slices])
    return rows


def section_skipping(run: _Run) -> str:
    """Speed-up and error cost of masking, active slices and early stop, per scene."""
    proj = Projector(run.camera, run.cfg.grid, run.queue)
    rows = []
    for name, box in _skip_scenes(run).items():
        rows += _skip_rows(run, proj, name, box)
        run.log(f"  skipping: {name} done")
    header = ["scene", "feature", "time s", "speed-up", "recovery", "Δ recovery", "ghosts", "Q",
              "Δ Q", "iterations", "active slices (last)"]
    return (f"## Skipping\n\nMLEM, {run.cfg.skip_iterations} iterations (early stop: until "
            "the relative residual changes by less than 1e-3), "
            f"{run.cfg.skip_particles} particles, grid {run.cfg.grid.shape}, pixels at or "
            "below 1 count dark; medians of "
            f"{_runs(run.heavy)} after a 1-iteration warm-up. Speed-up and Δ against the "
            "baseline of the same scene "
            "(no masking, every slice projected, all iterations). Active slices are exact "
            "(no error cost by construction); they pay off once masking empties depth "
            "slices.\n\n" + md_table(header, rows))


# ---- PIV ----------------------------------------------------------------------------
def piv_flows(shape: tuple[int, int, int]) -> dict[str, flows.Flow]:
    """Uniform shift, solid-body rotation and a Lamb-Oseen vortex (core radius 16 voxels,
    less in small volumes) in voxel units, about 3 voxels at most, as in
    ``benchmarks/piv.py``."""
    nz, ny, nx = shape
    centre = np.array([(nx - 1) / 2, (ny - 1) / 2, (nz - 1) / 2])
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    return {
        "uniform": flows.Uniform((2.31, -1.47, 0.68)),
        "rotation": flows.SolidBodyRotation(tuple(axis * 3.0 / (0.5 * min(shape))),
                                            tuple(centre)),
        "oseen": flows.LambOseen.from_peak_velocity(3.0, min(16.0, min(shape) / 3),
                                                    tuple(centre + [2.3, -1.7, 1.1]),
                                                    tuple(axis)),
    }


def piv_error(disp: np.ndarray, centres, flow, shape) -> float:
    """Interior RMS vector error (voxels) of ``disp`` ``(3, nz', ny', nx')`` as (u, v, w)
    at window centres ``(z, y, x)``: centres at least ``min(16, n/4)`` voxels from every
    face, against the flow's mid-time displacement."""
    zz, yy, xx = np.meshgrid(*centres, indexing="ij")
    pts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    truth = flows.centred_displacement(pts, flow, 1.0).T.reshape(disp.shape)
    margin = min(16, min(shape) // 4)
    inside = np.ones(zz.shape, bool)
    for c, n in zip((zz, yy, xx), shape):
        inside &= (c >= margin) & (c <= n - 1 - margin)
    err = (disp - truth)[:, inside]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=0)))) if err.size else float("nan")


def load_openpiv():
    """openpiv's 3-D module and version, or ``(None, reason)``."""
    os.environ.setdefault("TQDM_DISABLE", "1")  # openpiv's per-window progress bar
    try:
        import openpiv
        from openpiv import pyprocess3D
    except Exception as exc:  # noqa: BLE001 - any import failure means "not available"
        return None, f"{type(exc).__name__}: {exc}"
    return pyprocess3D, getattr(openpiv, "__version__", "?")


def _openpiv_run(p3, pair, ws: int, ov: int, repeats: int):
    """openpiv 3-D (single pass); its (u, v, w) are our (x, y, z) as (w, -u, v)."""
    def call():
        return p3.extended_search_area_piv3D(pair.vol_a, pair.vol_b, window_size=(ws,) * 3,
                                             overlap=(ov,) * 3, search_area_size=(ws,) * 3)

    (u, v, w), seconds = timed(call, repeats)
    centres = []
    for n in pair.vol_a.shape:  # openpiv's get_coordinates, per axis
        count = (n - ws) // (ws - ov) + 1
        shift = (n - 1 - ((count - 1) * (ws - ov) + ws - 1)) // 2
        centres.append(np.arange(count) * (ws - ov) + (ws - 1) / 2 + shift)
    return np.stack([w, -u, v]), tuple(centres), seconds


def _piv_flow_rows(run: _Run, p3, name: str, flow) -> list[dict]:
    shape = run.cfg.piv_shape
    pair = flows.volume_pair(shape, flow, seed=2718)
    rows = []
    for label, kwargs in run.cfg.piv:
        res, t = timed(lambda k=kwargs: piv3d(pair.vol_a, pair.vol_b, **k), run.heavy)
        disp = np.stack([res.u, res.v, res.w])
        rows.append({"flow": name, "label": f"plenocl {label}", "seconds": t,
                     "rms": piv_error(disp, (res.z, res.y, res.x), flow, shape),
                     "vectors": res.u.size, "valid": float(res.valid.mean())})
    for ws, ov in (run.cfg.openpiv if p3 is not None else ()):
        disp, centres, t = _openpiv_run(p3, pair, ws, ov, run.heavy)
        rows.append({"flow": name, "label": f"openpiv {ws}^3, overlap {ov}", "seconds": t,
                     "rms": piv_error(disp, centres, flow, shape), "vectors": disp[0].size,
                     "valid": float("nan")})
    return rows


def _piv_table(rows: list[dict]) -> list[list]:
    """Table rows per flow; marks each row's Pareto front (time vs error) and number."""
    table = []
    for name in dict.fromkeys(r["flow"] for r in rows):
        sub = [r for r in rows if r["flow"] == name]
        front = pareto_front([r["seconds"] for r in sub], [r["rms"] for r in sub], False)
        for r, f in zip(sub, front):
            r["front"], r["number"] = bool(f), len(table) + 1
            table.append([r["number"], name, r["label"], f"{r['seconds']:.2f}", f"{r['rms']:.4f}",
                          r["vectors"], f"{1e3 * r['seconds'] / r['vectors']:.2f}",
                          "—" if np.isnan(r["valid"]) else f"{r['valid']:.3f}",
                          "*" if f else ""])
    return table


def section_piv(run: _Run) -> str:
    """PIV run time against RMS error per setting and flow; openpiv in the same run."""
    from .bench_plots import plot_piv_pareto

    p3, version = load_openpiv()
    rows = []
    for name, flow in piv_flows(run.cfg.piv_shape).items():
        rows += _piv_flow_rows(run, p3, name, flow)
        run.log(f"  PIV: {name} done")
    table = _piv_table(rows)
    plot_piv_pareto(rows, run.out / "piv_pareto.png")
    about = (f"openpiv {version} (`extended_search_area_piv3D`, single pass, no validation) "
             "ran on the same volumes" if p3 is not None else
             f"openpiv is **not** importable here ({version}): no openpiv baseline in this "
             "run (`pip install openpiv` to add it)")
    return (f"## PIV: run time against error\n\nVolume pairs {run.cfg.piv_shape} (z, y, x) from "
            "`plenocl.flows.volume_pair` (Gaussian particles, σ 1 voxel, 0.004 per voxel, "
            "seed 2718); displacements up to about 3 voxels. Error: RMS of the vector error "
            "(voxels) over window centres at least min(16, n/4) voxels from the faces, "
            f"against the mid-time displacement. Medians of {_runs(run.heavy)}. {about}. "
            "front (*): on the Pareto front of time vs RMS error for that flow; the plot "
            "numbers points by the # column.\n\n"
            + md_table(["#", "flow", "setting", "time s", "RMS error (voxel)", "vectors",
                        "ms/vector", "valid", "front"], table)
            + "\n![time vs RMS error](piv_pareto.png)\n")


# ---- scaling ------------------------------------------------------------------------
def _scale_voxels(run: _Run) -> list[dict]:
    """Forward + back time and device buffers against the number of voxels."""
    points = []
    for shape in run.cfg.scale_voxels:
        proj = Projector(run.camera, _reshaped(run.cfg.grid, shape), run.queue)
        vol = np.random.default_rng(0).random(shape, dtype=np.float32)
        fwd, back, nbytes = device_pair(proj, vol)
        t = median_time(lambda f=fwd, b=back: (f(), b()), run.repeats)
        weights = estimated_weights(proj, 32)
        points.append({"n": proj.grid.size, "seconds": t, "bytes": nbytes,
                       "rate": f"{2 * weights / t / 1e6:.0f} M weights/s",
                       "weights": weights})
    return points


def _scale_pixels(run: _Run) -> list[dict]:
    """Forward + back time and device buffers against the sensor's pixels (fixed grid)."""
    h = 0.3 * min(run.cfg.scale_lenses) * 0.125
    grid = Grid((8, 16, 16), x=(-h, h), y=(-h, h), z=(-h, h))
    points = []
    for lenses in run.cfg.scale_lenses:
        cam = camera_for("", lenses)
        proj = Projector(cam, grid, run.queue)
        vol = np.random.default_rng(0).random(grid.shape, dtype=np.float32)
        fwd, back, nbytes = device_pair(proj, vol)
        t = median_time(lambda f=fwd, b=back: (f(), b()), run.repeats)
        px = cam.pixels[0] * cam.pixels[1]
        points.append({"n": px, "seconds": t, "bytes": nbytes,
                       "rate": f"{px / t / 1e6:.1f} M px/s"})
    return points


def _scale_particles(run: _Run) -> list[dict]:
    """Simulator time and host peak memory against the number of particles."""
    sim, rays, points = Simulator(run.camera, run.queue), run.cfg.scale_rays, []
    for n in run.cfg.scale_particles:
        pos, inten = random_particles(run.cfg.box, count=n, seed=4)
        t = median_time(lambda p=pos, i=inten: sim.trace(p, i, rays, seed=4), run.repeats)
        peak = host_peak_bytes(lambda p=pos, i=inten: sim.trace(p, i, rays, seed=4))
        points.append({"n": n, "seconds": t, "bytes": peak,
                       "rate": f"{n * rays / t / 1e6:.1f} M rays/s"})
    return points


def _scale_iterations(run: _Run) -> list[dict]:
    """MLEM time and host peak memory against the number of iterations."""
    proj = Projector(run.camera, run.cfg.grid, run.queue)
    _, _, img = _scene(run, run.cfg.counts[0], seed=5)
    reconstruct(img, proj, "mlem", 1)  # warm-up
    points = []
    for it in run.cfg.scale_iterations:
        call = lambda k=it: reconstruct(img, proj, "mlem", k, skip_empty=False)  # noqa: E731
        t = median_time(call, run.repeats)
        points.append({"n": it, "seconds": t, "bytes": host_peak_bytes(call),
                       "rate": f"{t / it:.3f} s/iteration"})
    return points


_SCALING = (  # axis, what is counted, memory measured, function
    ("voxels", "voxels (scene camera and volume)", "device buffers", _scale_voxels),
    ("pixels", "pixels (17 px lenses, fixed 8 x 16 x 16 grid)", "device buffers",
     _scale_pixels),
    ("particles", "particles (simulator)", "host peak (tracemalloc)", _scale_particles),
    ("iterations", "MLEM iterations (skip_empty off)", "host peak (tracemalloc)",
     _scale_iterations),
)


def _scaling_rows(data: dict) -> tuple[list, list]:
    rows, fits = [], []
    for axis, what, memory, _ in _SCALING:
        pts = data[axis]
        for p in pts:
            rows.append([what, f"{p['n']:,}", f"{p['seconds']:.4f}", _mib(p["bytes"]), memory,
                         p["rate"]])
        n = [p["n"] for p in pts]
        fits.append([axis, f"{loglog_slope(n, [p['seconds'] for p in pts]):.2f}",
                     f"{loglog_slope(n, [p['bytes'] for p in pts]):.2f}"])
    return rows, fits


def _limits(run: _Run, data: dict) -> str:
    """The measured figures set against the device's memory and throughput."""
    info = device_info(run.queue)
    big = data["voxels"][-1]
    image = 4 * run.camera.pixels[0] * run.camera.pixels[1]
    fixed = big["bytes"] - 8 * big["n"]          # image, tables, scratch (bounded)
    fits = (info.global_mem_bytes - fixed - 4 * image) / 12
    rate = 2 * big["weights"] / big["seconds"]
    it = data["iterations"]
    per_it = np.polyfit([p["n"] for p in it], [p["seconds"] for p in it], 1)
    return (f"\n**Against the machine's limits.** Device global memory "
            f"{info.global_mem_bytes / 2**30:.1f} GiB (largest buffer "
            f"{info.max_alloc_bytes / 2**30:.1f} GiB; larger volumes are split into slabs). "
            f"A forward + back at {big['n']:,} voxels used {_mib(big['bytes'])} MiB: 8 bytes "
            f"per voxel (volume in and out) and {_mib(fixed)} MiB of image, tables and "
            "scratch (bounded). The solver keeps about three volumes (estimate, sensitivity, "
            "one back projection: 12 bytes per voxel) and a few images, so about "
            f"{fits:.2e} voxels fit this device with this camera ({fits / 9e6:.1f}x the "
            f"paper's 300 x 200 x 150). Throughput: {rate / 1e6:.0f} M weights/s at "
            f"{big['n']:,} voxels (forward and back each count the estimated weights once), "
            f"about {2e10 / rate:.1f} s per forward + back of 1e10 weights (the paper's "
            f"experiment has about 1.2e10) if the rate held{_csr_at(run, big)}; MLEM costs "
            f"{per_it[0]:.3f} s per iteration plus {max(per_it[1], 0):.2f} s of set-up on the "
            f"scene's grid; the simulator traces {data['particles'][-1]['rate']} at "
            f"{data['particles'][-1]['n']:,} particles. A slope below 1 means fixed costs "
            "(per-pixel stages, launches, buffer fills, host transfers) still dominate at "
            "these sizes.\n")


def _csr_at(run: _Run, point: dict) -> str:
    """scipy CSR extrapolated to a scaling point at the rate measured in the projector
    section (empty when that section did not run)."""
    if run.csr is None:
        return ""
    rate, per_weight = run.csr
    return (f" (scipy CSR at its measured {rate / 1e6:.0f} M weights/s would take "
            f"{2 * point['weights'] / rate:.3f} s and "
            f"{point['weights'] * per_weight / 2**30:.2f} GiB here: an extrapolation, not a "
            "measurement)")


def section_scaling(run: _Run) -> str:
    """Time and memory against voxels, pixels, particles and iterations; fitted slopes."""
    from .bench_plots import plot_scaling

    data = {}
    for axis, _, _, fn in _SCALING:
        data[axis] = fn(run)
        run.log(f"  scaling: {axis} done")
    rows, fits = _scaling_rows(data)
    plot_scaling(data, {a: (w, m) for a, w, m, _ in _SCALING}, run.out / "scaling.png")
    return (f"## Scaling\n\nMedians of {_runs(run.repeats)} after a warm-up. Memory: the "
            "device buffers a forward + back uses (volume in and out, image, tables, "
            "scratch), or the host memory newly allocated during one call (tracemalloc "
            "peak).\n\n" + md_table(["size axis", "n", "time s", "memory MiB", "memory",
                                     "throughput"], rows)
            + "\nFitted log-log slopes (time ∝ n^slope):\n\n"
            + md_table(["axis", "time slope", "memory slope"], fits) + _limits(run, data)
            + "\n![log-log scaling](scaling.png)\n")


# ---- the report -----------------------------------------------------------------------
SECTIONS: tuple[tuple[str, Callable[[_Run], str]], ...] = (
    ("simulator", section_simulator),
    ("projector", section_projector),
    ("reconstruction", section_reconstruction),
    ("skipping", section_skipping),
    ("PIV", section_piv),
    ("scaling", section_scaling),
)


def _machine() -> str:
    """CPU model and core count, memory, OS."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM"
    except (ValueError, OSError, AttributeError):
        mem = ""
    return f"{os.cpu_count()} CPU cores ({model}){mem}, {platform.system()} {platform.release()}"


def _load() -> str:
    return " / ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"


def _header(run: _Run, load_start: str, end: tuple[str, float] | None) -> str:
    import pyopencl
    import scipy

    from . import __version__

    info, dev = device_info(run.queue), run.queue.device
    status = (f"load average (1 / 5 / 15 min) at end {end[0]}; total {end[1]:.0f} s"
              if end else "**incomplete: the run is still going (or stopped)**")
    return (f"# plenocl benchmark report (size `{run.cfg.name}`)\n\n"
            f"- generated {time.strftime('%Y-%m-%d %H:%M:%S')} by `plenocl bench --size "
            f"{run.cfg.name}`; plenocl {__version__}, Python {platform.python_version()}, "
            f"NumPy {np.__version__}, SciPy {scipy.__version__}, PyOpenCL "
            f"{pyopencl.VERSION_TEXT}\n"
            f"- device: **{info.name}** (platform {info.platform}, "
            f"{dev.platform.version.strip()}), {info.type}, {info.compute_units} compute "
            f"units, {info.global_mem_bytes / 2**30:.1f} GiB global memory\n"
            f"- machine: {_machine()}; load average (1 / 5 / 15 min) at start {load_start}; "
            f"{status}\n"
            f"- repeats: medians of {_runs(run.repeats)} for the simulator, projector and "
            f"scaling; {_runs(run.heavy)} for reconstruction, skipping and PIV (one warm-up first "
            "where stated)\n"
            + (f"- headline: {'; '.join(run.notes)}\n" if run.notes else "") + "\n")


def _write_report(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def run_report(size: str, out_dir: str | Path, repeats: int | None = None,
               queue: DeviceLike = None, log: Callable[..., None] = print) -> Path:
    """Run the stage benchmarks and write ``report.md`` and PNG plots into ``out_dir``.

    Parameters
    ----------
    size
        ``"ci"`` (about 1-2 minutes on 2 CPU cores), ``"small"`` (10-15 minutes),
        ``"paper"`` (``small`` plus the paper's 16 MP experiment) or ``"test"`` (a tiny
        camera, for the test suite).
    out_dir
        Folder of the report (created); files are replaced atomically. The report is
        rewritten after every section, marked incomplete until the end.
    repeats
        Runs per timing (the median is reported) for every section; by default per size
        (``ci``: 3 for cheap stages, 2 for reconstruction, skipping and PIV).
    queue
        OpenCL queue, device or name substring (:func:`plenocl.device.get_queue`).
    log
        Progress messages (``print`` by default).

    Returns
    -------
    pathlib.Path
        The report's path.
    """
    sizes = _sizes()
    if size not in sizes:
        raise ValueError(f"size must be one of {SIZES}, got {size!r}")
    if repeats is not None and repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}")
    cfg, out = sizes[size], Path(out_dir)
    run = _Run(cfg, get_queue(queue), out, log, repeats or cfg.repeats,
               repeats or cfg.heavy_repeats)
    load_start, t0, parts = _load(), time.perf_counter(), []
    path = out / "report.md"
    for title, section in SECTIONS:
        log(f"bench: {title} ...")
        t1 = time.perf_counter()
        parts.append(section(run))
        log(f"bench: {title} done in {time.perf_counter() - t1:.1f} s")
        _write_report(path, _header(run, load_start, None) + "\n".join(parts))
    end = (_load(), time.perf_counter() - t0)
    _write_report(path, _header(run, load_start, end) + "\n".join(parts))
    return path


# ---- command line -------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    """``plenocl bench``: run the benchmark report and say where it is."""
    path = run_report(args.size, args.out, args.repeats, queue=getattr(args, "device", None))
    print(f"benchmark report: {path} (plots beside it)")
    return 0


def add_bench_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``bench`` on the CLI's subparsers (the device comes from ``--device``)."""
    p = subparsers.add_parser("bench", help="benchmark every stage against a baseline; "
                                            "write a Markdown report with plots")
    p.add_argument("--size", choices=SIZES, default="ci",
                   help="ci: 1-2 min on 2 cores; small: 10-15 min; paper: adds the 16 MP "
                        "experiment (default: ci)")
    p.add_argument("--out", default="plenocl_bench", help="output folder (default: "
                                                          "plenocl_bench)")
    p.add_argument("--repeats", type=_positive_int, default=None,
                   help="runs per timing, the median is reported (default: per size)")
    p.set_defaults(func=cmd_bench)
    return p


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value
