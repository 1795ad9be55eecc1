"""The image fit on a hexagonal microlens array against a rectangular one (issue 29):
``process_pair`` with and without the fit to the raw images, per-particle and vector
errors and the particle stage's seconds, in the same run.

    python benchmarks/hex_image_fit.py [--lenses 48 56] [--scenes 2] [--particles 60]

The cameras, grid and optics of ``benchmarks/hexagonal.py`` (the rectangular array has
as many lenses per row and as many rows, so it is taller); each scene: ``--particles``
particles in the grid's middle 2.8 x 2.8 x 3.6 mm ray traced through each camera's exact
cells (1 px blur, photon noise), the second exposure displaced uniformly by (2.3, -1.4,
1.7) voxels; PIV windows of 16 voxels (3 x 2 x 2 vectors). Per particle: the first
exposure's volume peaks matched to the true particles (within 1.5 voxel laterally, 4 in
depth) and the same peaks fitted to the raw image (``ImageFit.refine``), RMS lateral /
depth error (voxels). Per vector: RMS error of
``process_pair``'s valid vectors against the displacement, lateral / depth, with
``image_fit=None`` and with the default fit; seconds (medians): the particle stage
(``PairResult.seconds["particles"]``, the fit included) and the whole pair, without and
with the fit.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from hexagonal import GRID, camera  # noqa: E402

from plenocl import Projector, get_queue, simulate_image  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.metrics import match_particles  # noqa: E402
from plenocl.peaks import find_particles  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402
from plenocl.piv import PIVSettings  # noqa: E402
from plenocl.piv.imagefit import ImageFit  # noqa: E402

SHIFT_VOXELS = np.array([2.3, -1.4, 1.7])


def scene(cam, seed: int, count: int, queue) -> tuple[np.ndarray, list[np.ndarray]]:
    """True positions of the first exposure and both exposures' raw images."""
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-1.4, 1.4, (count, 2)), rng.uniform(-1.8, 1.8, count)])
    shift = SHIFT_VOXELS * np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])
    return pos, [simulate_image(cam, p, np.full(count, 2e4), 20000, seed=seed + k,
                                blur_px=1.0, photon_noise=True, queue=queue)
                 for k, p in enumerate((pos, pos + shift))]


def particle_errors(pos, raws, result, proj, queue) -> tuple[np.ndarray, np.ndarray]:
    """Per matched particle (x, y, z) errors (voxels) of the first volume's peaks and of
    the same peaks fitted to the raw image."""
    found, _ = find_particles(result.vol_a, 0.1)
    true_idx = GRID.to_index(pos)
    pairs = np.array(match_particles(found, true_idx, 1.5, 4.0)).reshape(-1, 2)
    peaks, truth = found[pairs[:, 1]], true_idx[pairs[:, 0]]
    fitted = ImageFit(proj.camera, GRID, raws[:1], queue=queue).refine(0, peaks)
    return peaks - truth, fitted - truth


def vector_errors(result) -> np.ndarray:
    """``(valid, 3)`` errors (voxels) of the valid vectors against the displacement."""
    piv = result.piv
    d = np.stack([piv.u, piv.v, piv.w], -1)[piv.valid]
    return d - SHIFT_VOXELS


def rms(d: np.ndarray) -> str:
    """Lateral / depth RMS of ``(n, 3)`` errors."""
    return f"{np.sqrt(np.mean(d[:, :2] ** 2)):.3f} / {np.sqrt(np.mean(d[:, 2] ** 2)):.3f}"


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[48, 56])
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--particles", type=int, default=60)
    args = parser.parse_args()
    queue = get_queue()
    print(f"device: {queue.device.name.strip()}; {args.lenses[0]} x {args.lenses[1]} lenses; "
          f"grid {GRID.shape}; {args.scenes} scenes of {args.particles} particles")
    print(f"{'array':12s} {'peaks':>13s} {'fitted':>13s} {'vectors':>13s} "
          f"{'vectors, fit':>13s} {'particles s':>12s} {'pair s':>11s}")
    for layout in ("rectangular", "hexagonal"):
        cam = camera(layout, *args.lenses)
        proj = Projector(cam, GRID, queue)
        rows = {k: [] for k in ("peaks", "fitted", "vectors", "fit", "s", "s_fit", "pair",
                                "pair_fit")}
        for s in range(args.scenes):
            pos, raws = scene(cam, 200 + 2 * s, args.particles, queue)
            for fit, key in ((None, "vectors"), (True, "fit")):
                t0 = time.perf_counter()
                result = process_pair(*raws, proj, image_fit=fit,
                                      piv=PIVSettings(windows=(16,)))
                rows["pair" if fit is None else "pair_fit"].append(time.perf_counter() - t0)
                rows[key].append(vector_errors(result))
                rows["s" if fit is None else "s_fit"].append(result.seconds["particles"])
            peaks, fitted = particle_errors(pos, raws, result, proj, queue)
            rows["peaks"].append(peaks)
            rows["fitted"].append(fitted)
        cols = [rms(np.vstack(rows[k])) for k in ("peaks", "fitted", "vectors", "fit")]
        seconds = [f"{np.median(rows[a]):.2f} / {np.median(rows[b]):.2f}"
                   for a, b in (("s", "s_fit"), ("pair", "pair_fit"))]
        print(f"{layout:12s} " + " ".join(f"{c:>13s}" for c in cols)
              + f" {seconds[0]:>12s} {seconds[1]:>11s}", flush=True)


if __name__ == "__main__":
    main()
