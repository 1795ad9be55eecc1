"""Particles tracked through time-resolved recordings at the paper's optics (issue 30),
beside the pair chain on the same frames, in one run.

    python benchmarks/tracking.py [--seeding 0.05] [--frames 8] [--lenses 96 64]
                                  [--motion uniform rotation] [--pairs 2]

Camera and grid: ``benchmarks/accuracy.py``'s (the paper's optics and voxel on
``--lenses`` microlenses). Each series: ``--frames`` images of particles at ``--seeding``
per microlens moved by the motion at every frame (uniform: (2.3, -1.4, 1.7) voxels per
frame; rotation: 2 degrees per frame about the lateral x axis, which moves particles in
depth), exact ray tracing, 0.8 px blur, photon and read noise.

``plenocl.track`` on the whole series: per-step displacement errors (voxels) of the
tracks seen in at least 4 frames, matched to the true particles, lateral (RMS over x
and y) and depth, the focal zone (|z| < 2 mm) apart, both for the smoothed tracks and
for the positions as each frame's fit measured them (what linking alone gives), and
the same measured positions smoothed without the neighbours' depth prior ("own") and
by the local lines that smoothed tracks before the state-space smoother ("poly"); the
share of the true particles tracked, the share of ghost tracks, seconds per frame.
Beside it: ``plenocl.process_pair`` on the first ``--pairs`` consecutive pairs (its
vectors' errors against the same motion, seconds per frame = per pair / 2), and the
tracks binned into the pair chain's windows (``plenocl.bin_tracks``, every frame's
samples: both motions are steady), with the share of windows holding a vector.
``--figure tracks.png`` draws the first series' tracks coloured by speed.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import bin_tracks, get_queue, process_pair, track  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    ROTATION,
    UNIFORM,
    Motion,
    budget_errors,
    paper_setup,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.tracking_section import simulate_series, track_errors  # noqa: E402
from plenocl.pipeline import TrackSettings, smooth_tracks  # noqa: E402
from plenocl.plot.tracks import tracks_figure  # noqa: E402
from plenocl.ptv import Tracks  # noqa: E402

MOTIONS = {"uniform": UNIFORM, "rotation": ROTATION}


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--seeding", type=float, nargs="+", default=[0.05])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--lenses", type=int, nargs=2, default=[96, 64])
    parser.add_argument("--motion", nargs="+", default=list(MOTIONS), choices=MOTIONS)
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--figure", default=None,
                        help="write the first series' tracks, coloured by speed, here (.png)")
    args = parser.parse_args()
    queue = get_queue()
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    print(f"{'motion':9s} {'ppm':>5s} {'chain':9s} {'lateral':>7s} {'depth':>6s} "
          f"{'focal':>6s} {'tracked':>7s} {'ghosts':>6s} {'s/frame':>7s}")
    print("(track rows: per-step errors of tracked particles; pairs and binned: of vectors)")
    for name in args.motion:
        for ppm in args.seeding:
            _rows(MOTIONS[name], ppm, args, cam, grid, proj, queue)


def _rows(motion: Motion, ppm: float, args, cam, grid, proj, queue) -> None:
    series = simulate_series(cam, grid, ppm, args.frames, args.seed, queue, motion)
    t0 = time.perf_counter()
    tracks = track(series.frames, proj, dt=1.0)
    row = track_errors(tracks, series.truth, grid, time.perf_counter() - t0)
    if args.figure:
        tracks_figure(Path(args.figure), tracks.positions, tracks.velocities, "mm per frame")
        args.figure = None
    for chain in ("smoothed", "measured"):
        e = row[chain]
        _print(motion, ppm, "track " + chain[:3], e["lateral"], e["depth"], e["focal_depth"],
               f"{row['tracked']:7.0%} {row['ghosts']:6.0%}", row["seconds_per_frame"])
    for label, other in _smoothers(tracks, proj).items():
        e = track_errors(other, series.truth, grid, 0.0)["smoothed"]
        _print(motion, ppm, label, e["lateral"], e["depth"], e["focal_depth"], "",
               float("nan"))
    pairs = [process_pair(series.frames[k], series.frames[k + 1], proj)
             for k in range(min(args.pairs, args.frames - 1))]
    if not pairs:
        return
    errors = [budget_errors(pair.piv, grid, motion) for pair in pairs]
    seconds = np.median([sum(pair.seconds.values()) / 2 for pair in pairs])
    _print(motion, ppm, "pairs", *_pooled(errors), "", seconds)
    ref = pairs[0].piv
    field = bin_tracks(tracks, grid, window=ref.window, step=ref.step)
    binned = budget_errors(field, grid, motion)
    _print(motion, ppm, "binned", *_pooled([binned]), f"{binned['valid']:7.0%}", float("nan"))


def _smoothers(tracks, proj) -> dict:
    """The same measured positions smoothed otherwise: the state-space smoother without
    the neighbours' prior ("own"), and the local lines over 7 frames that smoothed the
    tracks before it ("poly")."""
    args = (tracks.measured, tracks.measured_sigma, tracks.intensities, tracks.dt)
    return {"track own": smooth_tracks(*args, proj, TrackSettings(neighbours=0)),
            "track poly": Tracks.from_measured(*args, window=7, degree=1)}


def _pooled(errors: list[dict]) -> tuple[float, float, float]:
    """RMS over several fields' lateral, depth and in-focus depth errors."""
    return tuple(float(np.sqrt(np.nanmean([e[k] ** 2 for e in errors])))
                 for k in ("lateral", "depth", "in focus"))


def _print(motion: Motion, ppm: float, chain: str, lateral: float, depth: float,
           focal: float, shares: str, seconds: float) -> None:
    print(f"{motion.name[:9]:9s} {ppm:5.3f} {chain:9s} {lateral:7.3f} {depth:6.3f} "
          f"{focal:6.3f} {shares:14s} {seconds:7.1f}", flush=True)


if __name__ == "__main__":
    main()
