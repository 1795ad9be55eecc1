"""Pairs per hour of ``plenocl run`` on one device: one process against several Dask
worker processes sharing it, the same experiment in the same run (issue 46, item 3).

    python benchmarks/throughput.py [--lenses 289 193] [--pairs 8 24] [--workers 0 2 4]

The experiment is the paper pair's (``benchmarks/paper_pair.py``): the paper's optics on
``--lenses`` microlenses (the whole 16 MP sensor by default), the paper's voxel, 0.05
particles per microlens ray-traced with blur and noise, the default chain
(``process_pair``'s defaults: no reconstruction, PIV or particle section in the file).
One pair of raw images is simulated and written as each ``--pairs`` count of pairs of
frames (hard links: the throughput does not depend on the particles' positions), with
the camera and grid files and one experiment file per count. Each worker count (``0``:
serially in this process, ``plenocl run`` without ``--workers``) then runs each
experiment from an empty output folder; a row gives the wall time of the run
(``RunSummary.wall_seconds``: the cluster's start and every worker's first pair, which
builds its projectors, included), seconds per pair, pairs per hour, and the vectors'
lateral and depth RMS error of the last pair against the simulated motion (every row
should agree). With two or more counts, a last row per worker count gives the
**marginal** rate between the smallest and the largest count (their difference in pairs
over their difference in wall time): a long batch's pairs per hour, without the start.

On a GPU the chain is host-bound (``paper_pair.py --profile``: 1.6 s of kernels in an
8.8 s pair on an H200), so worker processes that share the device overlap one pair's
host work with another's kernels; on a CPU device they share the same cores and gain
little.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import get_queue  # noqa: E402
from plenocl.batch import run  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    UNIFORM,
    budget_errors,
    budget_scene,
    paper_optics,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.grid import Grid  # noqa: E402
from plenocl.io.files import write_tiff  # noqa: E402
from plenocl.io.tomlfile import write_toml  # noqa: E402
from plenocl.vectorfield import read_npz  # noqa: E402

#: The time between a pair's exposures written into the experiment (s).
DT_S = 175e-6


def write_images(folder: Path, lenses: tuple[int, int], seed: int, queue) -> tuple[Path, ...]:
    """The paper pair's camera and grid files and its two simulated raw images in
    ``folder``; the images' paths."""
    cam, grid = paper_optics(lenses)
    scene = budget_scene(cam, grid, 0.05, seed, queue, motion=UNIFORM)
    cam.to_toml(folder / "camera.toml")
    grid.to_toml(folder / "grid.toml")
    images = tuple(folder / f"image_{j}.tif" for j in (0, 1))
    for path, image in zip(images, (scene.raw_a, scene.raw_b)):
        write_tiff(path, image.astype(np.float32))
    print(f"{scene.count} particles; pairs of {cam.pixels[0]} x {cam.pixels[1]} px")
    return images


def write_experiment(folder: Path, images: tuple[Path, ...], pairs: int) -> Path:
    """``pairs`` pairs of frames (hard links to ``images``) and their experiment file in
    ``folder``; the file's path."""
    raw = folder / f"raw_{pairs}"
    raw.mkdir()
    for k in range(pairs):
        for j, image in enumerate(images):
            os.link(image, raw / f"frame_{2 * k + j:03d}.tif")
    path = folder / f"experiment_{pairs}.toml"
    write_toml(path, {"camera": {"file": "camera.toml"}, "grid": {"file": "grid.toml"},
                      "images": {"folder": raw.name, "pattern": "frame_*.tif",
                                 "pairing": "sequence", "dt_s": DT_S},
                      "output": {"folder": f"results_{pairs}"}})
    return path


def throughput_run(experiment: Path, out: Path, workers: int, queue) -> tuple[float, str]:
    """One run of ``experiment`` into ``out`` on ``workers`` processes (0: this one): its
    wall seconds and its row."""
    summary = run(experiment, out, queue=None if workers else queue, log=lambda m: None,
                  workers=workers or None, progress=False)
    if summary.failed:
        raise RuntimeError(f"{len(summary.failed)} pairs failed: {summary.failed}")
    grid = Grid.from_toml(experiment.parent / "grid.toml")
    pairs = sorted((out / "pairs").glob("pair_*.npz"))
    errors = budget_errors(read_npz(pairs[-1])[0], grid, UNIFORM)
    per_pair = summary.seconds_per_pair
    return summary.wall_seconds, (
        f"| {_label(workers)} | {len(pairs)} | {summary.wall_seconds:.1f} | {per_pair:.2f} | "
        f"{3600 / per_pair:.0f} | {errors['lateral']:.3f} / {errors['depth']:.3f} |")


def _label(workers: int) -> str:
    return "one process (serial)" if not workers else f"--workers {workers}"


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[289, 193])
    parser.add_argument("--pairs", type=int, nargs="+", default=[8, 24],
                        help="pairs per run (two or more counts: the marginal rate too)")
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2, 4],
                        help="worker processes per row (0: serially in this process)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}; {os.cpu_count()} cores")
    work = Path(tempfile.mkdtemp(prefix="plenocl_throughput_"))
    counts = sorted(set(args.pairs))
    try:
        images = write_images(work, tuple(args.lenses), args.seed, queue)
        files = {n: write_experiment(work, images, n) for n in counts}
        print("| run | pairs | wall s | s per pair | pairs per hour | last pair lateral / "
              "depth |")
        print("|---|---|---|---|---|---|")
        for workers in args.workers:
            walls = {}
            for n in counts:
                walls[n], row = throughput_run(files[n], work / f"out_{workers}_{n}",
                                               workers, queue)
                print(row, flush=True)
            if len(counts) > 1:
                lo, hi = counts[0], counts[-1]
                each = (walls[hi] - walls[lo]) / (hi - lo)
                print(f"| {_label(workers)}, marginal {lo} to {hi} | {hi - lo} | "
                      f"{walls[hi] - walls[lo]:.1f} | {each:.2f} | {3600 / each:.0f} | |",
                      flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
