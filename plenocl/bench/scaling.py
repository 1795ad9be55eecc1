"""Benchmark report section: scaling of time and memory, against the machine."""

from __future__ import annotations

import numpy as np

from ..grid import Grid
from ..opencl.device import device_info
from ..particles import random_particles
from ..projection.projector import Projector
from ..reconstruction import reconstruct
from ..simulate import Simulator
from .core import (
    VOXELS,
    BenchRun,
    bench_scene,
    camera_for,
    host_peak_bytes,
    loglog_slope,
    md_table,
    mib,
    repeats_text,
    reshaped,
)
from .stages import device_pair, estimated_weights
from .timing import median_time


# ---- scaling ------------------------------------------------------------------------
def _scale_voxels(run: BenchRun) -> list[dict]:
    """Forward + back time and device buffers against the number of voxels."""
    points = []
    for shape in run.cfg.scale_voxels:
        proj = Projector(run.camera, reshaped(run.cfg.grid, shape), run.queue)
        vol = np.random.default_rng(0).random(shape, dtype=np.float32)
        fwd, back, nbytes = device_pair(proj, vol)
        t = median_time(lambda f=fwd, b=back: (f(), b()), run.repeats)
        weights = estimated_weights(proj, 32)
        points.append({"n": proj.grid.size, "seconds": t, "bytes": nbytes,
                       "rate": f"{2 * weights / t / 1e6:.0f} M weights/s",
                       "weights": weights})
    return points


def _scale_pixels(run: BenchRun) -> list[dict]:
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


def _scale_particles(run: BenchRun) -> list[dict]:
    """Simulator time and host peak memory against the number of particles."""
    sim, rays, points = Simulator(run.camera, run.queue), run.cfg.scale_rays, []
    for n in run.cfg.scale_particles:
        pos, inten = random_particles(run.cfg.box, count=n, seed=4)
        t = median_time(lambda p=pos, i=inten: sim.trace(p, i, rays, seed=4), run.repeats)
        peak = host_peak_bytes(lambda p=pos, i=inten: sim.trace(p, i, rays, seed=4))
        points.append({"n": n, "seconds": t, "bytes": peak,
                       "rate": f"{n * rays / t / 1e6:.1f} M rays/s"})
    return points


def _scale_iterations(run: BenchRun) -> list[dict]:
    """MLEM time and host peak memory against the number of iterations."""
    proj = Projector(run.camera, run.cfg.grid, run.queue)
    _, _, img = bench_scene(run, run.cfg.counts[0], seed=5)
    reconstruct(img, proj, "mlem", 1, **VOXELS)  # warm-up
    points = []
    for it in run.cfg.scale_iterations:
        call = lambda k=it: reconstruct(img, proj, "mlem", k, skip_empty=False,  # noqa: E731
                                        **VOXELS)
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
            rows.append([what, f"{p['n']:,}", f"{p['seconds']:.4f}", mib(p["bytes"]), memory,
                         p["rate"]])
        n = [p["n"] for p in pts]
        fits.append([axis, f"{loglog_slope(n, [p['seconds'] for p in pts]):.2f}",
                     f"{loglog_slope(n, [p['bytes'] for p in pts]):.2f}"])
    return rows, fits


def _limits(run: BenchRun, data: dict) -> str:
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
            f"A forward + back at {big['n']:,} voxels used {mib(big['bytes'])} MiB: 8 bytes "
            f"per voxel (volume in and out) and {mib(fixed)} MiB of image, tables and "
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


def _csr_at(run: BenchRun, point: dict) -> str:
    """scipy CSR extrapolated to a scaling point at the rate measured in the projector
    section (empty when that section did not run)."""
    if run.csr is None:
        return ""
    rate, per_weight = run.csr
    return (f" (scipy CSR at its measured {rate / 1e6:.0f} M weights/s would take "
            f"{2 * point['weights'] / rate:.3f} s and "
            f"{point['weights'] * per_weight / 2**30:.2f} GiB here: an extrapolation, not a "
            "measurement)")


def section_scaling(run: BenchRun) -> str:
    """Time and memory against voxels, pixels, particles and iterations; fitted slopes."""
    from .plots import plot_scaling

    data = {}
    for axis, _, _, fn in _SCALING:
        data[axis] = fn(run)
        run.log(f"  scaling: {axis} done")
    rows, fits = _scaling_rows(data)
    plot_scaling(data, {a: (w, m) for a, w, m, _ in _SCALING}, run.out / "scaling.png")
    return (f"## Scaling\n\nMedians of {repeats_text(run.repeats)} after a warm-up. Memory: the "
            "device buffers a forward + back uses (volume in and out, image, tables, "
            "scratch), or the host memory newly allocated during one call (tracemalloc "
            "peak).\n\n" + md_table(["size axis", "n", "time s", "memory MiB", "memory",
                                     "throughput"], rows)
            + "\nFitted log-log slopes (time ∝ n^slope):\n\n"
            + md_table(["axis", "time slope", "memory slope"], fits) + _limits(run, data)
            + "\n![log-log scaling](scaling.png)\n")
