"""The particle stage's host work at the paper's size: the stage alone, repeated on one
pair's inputs.

    python benchmarks/particle_stage.py [--tree PATH] [--lenses 289 193] [--repeats 7]

The pair is ``paper_pair.py``'s (``--bit-depth 16``, the default chain, every PIV FFT on
the device: the route a GPU takes, where no volume comes back). It runs once whole; the
particle stage (``plenocl.pipeline.velocity.refine_particles``: the volumes' particles,
their fit to the raw images, the pairing and the window means) then runs ``--repeats``
more times on that pair's inputs, each under :class:`plenocl.bench.clprofile.OpenCLProfile`.
The script prints each repeat's host work outside OpenCL calls, their median and the
stage's median wall and kernel seconds.

``--tree``: the plenocl checkout to import (default: this one). Code that was replaced
cannot run beside its replacement in one process, so a change to the stage is measured by
running this script on the checkout before it and on the one after it, alternately (the
machine's load moves host seconds by about a fifth).

Measured (Intel's runtime on a 2-core AMD EPYC, 2026-12-04, this script's first form,
which was then a scratch script): ``07cc959`` (before the stage's cut) against
``b607fd6``, seven repeats each, in turn and then in the reverse order: **0.329 → 0.261
s** and 0.397 → 0.306 s of host work (medians); the stage's wall 2.84 / 3.40 s before,
3.01 / 3.16 s after; the vectors within 3.6e-14 voxel. At 116 x 78 (``--lenses 116 78``,
this script, the two checkouts alternating twice, 7 repeats each): 0.116 / 0.084 s before
against 0.077 / 0.072 s after; the kernels' medians moved with the machine (0.40-0.64 s
before, 0.39-0.41 s after). The pieces, each against the code it replaced in the same
run, are rows of ``host_work.py``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--tree", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--lenses", type=int, nargs=2, default=[289, 193])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    sys.path.insert(0, str(args.tree.resolve()))
    import plenocl.pipeline.velocity as velocity
    from plenocl import get_queue
    from plenocl.bench.accuracy_section import UNIFORM, budget_scene, paper_setup
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.pipeline import process_pair
    from plenocl.piv import PIVSettings

    print(f"plenocl from {Path(velocity.__file__).parents[2]}")
    queue = get_queue(profiling=True)
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    scene = budget_scene(cam, grid, 0.05, 3, queue, motion=UNIFORM, bit_depth=16)
    stage, seen = velocity.refine_particles, []
    velocity.refine_particles = lambda *a, **k: seen.append((a, k)) or stage(*a, **k)
    process_pair(scene.raw_a, scene.raw_b, proj, volumes=False,
                 piv=PIVSettings(fft="device"))
    velocity.refine_particles = stage
    given, options = seen[-1]
    host, wall, kernel = [], [], []
    for _ in range(args.repeats):
        with OpenCLProfile() as prof:
            start = time.perf_counter()
            stage(*given, **{**options, "clock": velocity.StageClock()})
            queue.finish()
            span = (start, time.perf_counter())
        split = prof.split({"particles": span})["particles"]
        host.append(split.host)
        wall.append(span[1] - span[0])
        kernel.append(split.kernel or 0.0)
    print(f"particle stage, {args.repeats} repeats: host work "
          f"{' '.join(f'{h:.3f}' for h in host)} s, median {statistics.median(host):.3f} s; "
          f"wall median {statistics.median(wall):.2f} s, kernels "
          f"{statistics.median(kernel):.2f} s")


if __name__ == "__main__":
    main()
