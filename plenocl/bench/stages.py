"""Benchmark report sections: simulator, projector, reconstruction, skipping."""

from __future__ import annotations

import time

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..metrics import quality_q, recovery, render_particles
from ..particles import random_particles
from ..projection.projector import Projector
from ..reconstruction import reconstruct
from ..reference.simulate import trace_particles
from ..simulate import Simulator
from .core import (
    PAPER_METHOD,
    VOXELS,
    BenchRun,
    Box,
    ReconSetting,
    bench_scene,
    md_table,
    mib,
    pareto_front,
    repeats_text,
    reshaped,
)
from .sparse import matrix_bytes, weight_matrix
from .timing import median_time, timed


# ---- simulator ----------------------------------------------------------------------
def section_simulator(run: BenchRun) -> str:
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
            f"{cam.ml_count[1]} lenses; {n} particles. Medians of {repeats_text(run.repeats)} "
            "after a warm-up; each run includes the image buffer fill and read-back.\n\n"
            + md_table(["path", "rays", "median s", "M rays/s"], rows)
            + f"\nSpeed-up at equal work (kernel vs reference): **{t_ref / t_same:.1f}x**; "
            f"kernel rays/s at {rays} rays per particle vs reference rays/s: "
            f"{(n * rays / t_dev) / (n * ref_rays / t_ref):.1f}x. Images of the same rays "
            f"correlate at r = {same:.7f}.\n")


# ---- projector ----------------------------------------------------------------------
def projector_bytes(proj: Projector) -> int:
    """Device bytes the projector holds itself: weight tables and scratch buffers."""
    return proj.device_bytes()


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


def _csr_rows(run: BenchRun, proj: Projector, a, vol, img_h) -> tuple[list[list], float]:
    """Table rows of CSR against the matrix-free path, and the device-resident speed-up."""
    fwd, back, dev_bytes = device_pair(proj, vol)
    x, y, r = vol.ravel(), img_h.ravel(), run.repeats
    t_fc, t_bc = median_time(lambda: a @ x, r), median_time(lambda: a.T @ y, r)
    t_f, t_b = median_time(fwd, r), median_time(back, r)
    t_h = median_time(lambda: (proj.forward(vol), proj.back(img_h)), r)
    rate, speedup = a.nnz / 1e6, (t_fc + t_bc) / (t_f + t_b)
    rows = [["scipy.sparse CSR (A x, Aᵀ y)", f"{t_fc:.4f}", f"{t_bc:.4f}", f"{t_fc + t_bc:.4f}",
             f"{2 * rate / (t_fc + t_bc):.0f}", mib(matrix_bytes(a)), "1.0x"],
            ["matrix-free, device-resident", f"{t_f:.4f}", f"{t_b:.4f}", f"{t_f + t_b:.4f}",
             f"{2 * rate / (t_f + t_b):.0f}", mib(dev_bytes), f"**{speedup:.1f}x**"],
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


def csr_case(proj: Projector):
    """The stored-matrix baseline of a projector: its CSR weight matrix, the seconds it
    took to build, and a random volume and image (seed 0) to project."""
    t0 = time.perf_counter()
    a = weight_matrix(proj)
    build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    vol = rng.random(proj.grid.shape, dtype=np.float32)
    return a, build, vol, rng.random(proj.image_shape, dtype=np.float32)


def section_projector(run: BenchRun) -> str:
    """Matrix-free forward + back against CSR products of the same weights; memory."""
    grid = reshaped(run.cfg.grid, run.cfg.csr_grid)
    proj = Projector(run.camera, grid, run.queue)
    a, build, vol, img_h = csr_case(proj)
    ref = a @ vol.ravel()
    err = np.abs(ref - proj.forward(vol).ravel()).max() / ref.max()
    rows, speedup = _csr_rows(run, proj, a, vol, img_h)
    return (f"## Projector\n\nGrid {grid.shape} (z, y, x) over the scene's volume, "
            f"{a.nnz:,} weights ({a.nnz / grid.size:.0f} per voxel); the CSR matrix was built "
            f"from the footprint kernel in {build:.1f} s (not counted). Medians of "
            f"{repeats_text(run.repeats)}; weights/s counts both products. Memory: the CSR matrix "
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


def _paper_projector(run: BenchRun) -> str:
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
            f"weights/s; medians of {repeats_text(run.heavy)}).\n")


# ---- reconstruction -------------------------------------------------------------------
def _recon_row(run: BenchRun, proj: Projector, scene, setting: ReconSetting, truth) -> dict:
    """Median time and errors of one reconstruction setting on one scene."""
    label, method, iterations, relax, opts = setting
    pos, _, img = scene
    given = {**VOXELS, **opts}
    reconstruct(img, proj, method, 1, relax, **given)  # warm-up: PoCL compiles at first launch
    (vol, info), seconds = timed(lambda: reconstruct(img, proj, method, iterations, relax,
                                                     return_info=True, **given), run.heavy)
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


def section_reconstruction(run: BenchRun) -> str:
    """Run time against recovery, ghosts and Q for each method and setting; Pareto plot."""
    from .plots import plot_recon_pareto

    grid, rows = run.cfg.grid, []
    proj = Projector(run.camera, grid, run.queue)
    for count in run.cfg.counts:
        scene = bench_scene(run, count, seed=count)
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
            f"median of {repeats_text(run.heavy)} of `reconstruct()` on the voxels "
            "themselves (`supersample=1`; after a 1-iteration warm-up of the same setting), "
            "image in, "
            "volume out. Recovery: a peak within 1 voxel laterally and 2 in depth of a true "
            "particle; ghosts: fraction of the intensity farther than (2, 4) voxels from every "
            "particle; Q against the particles rendered as Gaussians (σ 0.6 voxel). "
            "front: on the Pareto front of time vs recovery (R) or time vs Q (Q); the plot "
            "numbers points by the # column.\n\n"
            + table + "\n![time vs recovery and Q](recon_pareto.png)\n")
    return text + (_paper_reconstruction(run) if run.cfg.paper else "")


def _box_text(box: Box) -> str:
    return " x ".join(f"[{a:g}, {b:g}]" for a, b in box) + " mm"


def _paper_reconstruction(run: BenchRun) -> str:
    cam, grid = paper_grid()
    pos, inten = random_particles(((-27, 27), (-17, 17), (-9.5, 9.5)), count=5000, seed=3,
                                  intensity=1e4)
    img = Simulator(cam, run.queue).trace(pos, inten, 2000, seed=3)
    proj = Projector(cam, grid, run.queue)
    rows = []
    for label, method, mu, opts in (("MART μ = 1 (paper)", "mart", 1.0, PAPER_METHOD),
                                    ("MLEM (voxels' default)", "mlem", 1.0, {}),
                                    ("MLEM, no skipping", "mlem", 1.0, _OFF)):
        (vol, info), t = timed(lambda m=method, u=mu, o=opts: reconstruct(
            img, proj, m, 5, u, return_info=True, **VOXELS, **o), run.heavy)
        rep = recovery(vol, grid, pos)
        rows.append([label, 5, f"{t:.1f}", f"{rep.fraction:.2f}", f"{rep.ghost_fraction:.3f}",
                     f"{info.lit_lens_fraction:.2f}"])
        run.log(f"  paper experiment {label}: {t:.1f} s")
    return (f"\nThe paper's experiment (16 MP, grid (150, 200, 300), 5000 particles in "
            f"54 x 34 x 19 mm, 2000 rays each; on the voxels themselves; medians of "
            f"{repeats_text(run.heavy)}, no warm-up; "
            "'no skipping': every slice and microlens projected, no cropping):\n\n"
            + md_table(["method", "iterations", "time s", "recovery", "ghosts", "lit lenses"],
                       rows))


# ---- skipping -------------------------------------------------------------------------
_OFF = {"skip_empty": False, "crop": False, "skip_dark": False}
_SKIP_FEATURES: tuple[tuple[str, dict], ...] = (
    ("none (baseline)", _OFF),
    ("active slices", {**_OFF, "skip_empty": True}),
    ("crop to the lit region", {**_OFF, "crop": True}),
    ("dark microlenses", {**_OFF, "skip_dark": True}),
    ("masking 0.5", {**_OFF, "mask_fraction": 0.5}),
    ("masking 0.5 + active slices", {**_OFF, "skip_empty": True, "mask_fraction": 0.5}),
    ("early stop tol 1e-3", {**_OFF, "tol": 1e-3}),
    ("defaults (slices + crop + dark lenses)", {}),
    ("defaults + tol 1e-3", {"tol": 1e-3}),
)


def _skip_scenes(run: BenchRun) -> dict[str, Box]:
    """A light sheet (the middle fifth of the seeded depth), a lateral quarter (particles
    in one corner of the field of view) and the full seeded cube."""
    (x, y, (z0, z1)) = run.cfg.box
    mid, half = 0.5 * (z0 + z1), 0.1 * (z1 - z0)
    corner = ((x[0], 0.5 * (x[0] + x[1])), (0.5 * (y[0] + y[1]), y[1]), (z0, z1))
    return {f"light sheet {2 * half:g} mm deep": (x, y, (mid - half, mid + half)),
            "lateral quarter": corner,
            f"full cube {z1 - z0:g} mm deep": run.cfg.box}


def _skip_rows(run: BenchRun, proj: Projector, name: str, box: Box) -> list[list]:
    pos, inten, img = bench_scene(run, run.cfg.skip_particles, seed=9, box=box)
    truth, rows, base = render_particles(proj.grid, pos, inten), [], None
    for label, opts in _SKIP_FEATURES:
        reconstruct(img, proj, "mlem", 1, threshold=1.0, **VOXELS, **opts)  # warm-up
        (vol, info), t = timed(lambda o=opts: reconstruct(
            img, proj, "mlem", run.cfg.skip_iterations, threshold=1.0, return_info=True,
            **VOXELS, **o), run.heavy)
        rep, q = recovery(vol, proj.grid, pos), quality_q(vol, truth)
        base = base or (t, rep.fraction, q)
        slices = info.active_slices[-1] if info.active_slices else proj.shape[0]
        rows.append([name, label, f"{t:.2f}", f"{base[0] / t:.2f}x", f"{rep.fraction:.2f}",
                     f"{rep.fraction - base[1]:+.2f}", f"{rep.ghost_fraction:.3f}", f"{q:.3f}",
                     f"{q - base[2]:+.3f}", info.iterations, slices,
                     f"{info.lit_lens_fraction:.2f}"])
    return rows


def section_skipping(run: BenchRun) -> str:
    """Speed-up and error cost of masking, active slices and early stop, per scene."""
    proj = Projector(run.camera, run.cfg.grid, run.queue)
    rows = []
    for name, box in _skip_scenes(run).items():
        rows += _skip_rows(run, proj, name, box)
        run.log(f"  skipping: {name} done")
    header = ["scene", "feature", "time s", "speed-up", "recovery", "Δ recovery", "ghosts", "Q",
              "Δ Q", "iterations", "active slices (last)", "lit lenses"]
    return (f"## Skipping\n\nMLEM, {run.cfg.skip_iterations} iterations (early stop: until "
            "the relative residual changes by less than 1e-3), "
            f"{run.cfg.skip_particles} particles, grid {run.cfg.grid.shape}, pixels at or "
            "below 1 count dark; medians of "
            f"{repeats_text(run.heavy)} after a 1-iteration warm-up. Speed-up and Δ against the "
            "baseline of the same scene "
            "(no masking, every slice and microlens projected, all iterations). Active "
            "slices and dark-microlens skipping are exact (the volumes are bit-identical, "
            "tested); cropping is exact up to float32 rounding (the sub-grid's weight tables "
            "are recomputed; tested within 1e-4). Active slices pay off once "
            "masking empties depth slices. Lit lenses: the fraction of microlenses that see "
            "a pixel above the threshold.\n\n" + md_table(header, rows))
