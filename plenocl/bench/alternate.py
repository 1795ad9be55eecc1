"""Two or more ways of the chain timed alternately in one process (the benchmarks that
put code before a change back beside it: ``benchmarks/uploads.py``,
``benchmarks/device_overheads.py``, ``benchmarks/memory_pool.py``).

Scene: ``benchmarks/paper_pair.py``'s (the paper's optics, 0.05 particles per
microlens, ray traced with blur and noise), default chain. Kernels are built and one
pair run each way before the rounds; each round profiles one pair each way
(:func:`plenocl.bench.clprofile.profiled_pair`): the calls in which the host waited for
the queue, its work outside OpenCL calls, the pair's wall time and the megabytes it sent
to the device. Then the medians, and
whether every way gave the first way's vectors to the bit.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..opencl.device import get_queue
from .accuracy_section import UNIFORM, budget_scene, paper_setup
from .clprofile import profiled_pair
from .scripts import script_parser

__all__ = ["alternate_ways", "alternation_script"]

#: The field's columns compared across ways.
COMPARED = ("u", "v", "w", "valid", "sigma_u")


def alternate_ways(ways: dict[str, Callable[[], None]], lenses: tuple[int, int],
                   rounds: int, *, queue=None, warm: bool = False,
                   bit_depth: int | None = None) -> dict[str, dict[str, float]]:
    """Each way (a label and the call that sets the chain up that way) profiled once a
    round, ``rounds`` rounds, on the scene at ``lenses``; prints each row, the medians
    and whether the vectors agree; returns the medians by label. The last way's setting
    is left in place. ``queue``: the profiling queue the chain runs on (``None``: a new
    one), for ways that set it up; ``warm``: each round, one pair unprofiled after a
    way is set up and before its profiled one (a way whose state a pair builds, as a
    batch's later pairs find it); ``bit_depth``: the raw images as a camera's integers of
    that depth (e.g. 16) instead of float counts."""
    queue = queue or get_queue(profiling=True)
    cam, grid, proj = paper_setup(tuple(lenses), queue)
    scene = budget_scene(cam, grid, 0.05, 3, queue, motion=UNIFORM, bit_depth=bit_depth)
    for way in ways.values():
        way()
        profiled_pair(scene.raw_a, scene.raw_b, proj)  # kernels, plans and routes made
    width = max(len(label) for label in ways) + 2
    rows, fields = {label: [] for label in ways}, {}
    print(f"{'round':>5s} {'way':{width}s} {'waits':>6s} {'host s':>7s} {'wall s':>7s} "
          f"{'MB in':>6s}")
    for k in range(rounds):
        for label, way in ways.items():
            way()
            if warm:
                profiled_pair(scene.raw_a, scene.raw_b, proj)
            row, fields[label] = profiled_pair(scene.raw_a, scene.raw_b, proj)
            rows[label].append(row)
            print(f"{k + 1:5d} {label:{width}s} {row['waits']:6d} {row['host']:7.3f} "
                  f"{row['wall']:7.2f} {row['mb_in']:6.1f}", flush=True)
    print("medians")
    medians = {label: {key: float(np.median([r[key] for r in got])) for key in got[0]}
               for label, got in rows.items()}
    for label, med in medians.items():
        print(f"{'':5s} {label:{width}s} {med['waits']:6.0f} {med['host']:7.3f} "
              f"{med['wall']:7.2f} {med['mb_in']:6.1f}")
    first = next(iter(fields.values()))
    same = all(np.array_equal(getattr(f, c), getattr(first, c), equal_nan=True)
               for f in fields.values() for c in COMPARED)
    print(f"the vectors the same to the bit every way: {same}")
    return medians


def alternation_script(doc: str, ways: Callable[[object], dict[str, Callable[[], None]]],
                       lenses: tuple[int, int] = (116, 78), rounds: int = 4,
                       **options) -> dict[str, dict[str, float]]:
    """A benchmark script's ``main``: its ``--lenses`` and ``--rounds`` (defaults
    ``lenses``, ``rounds``) read, a profiling queue made (``PYOPENCL_CTX``'s device or the
    default) and named, and :func:`alternate_ways` run on it with ``ways(queue)`` and
    ``options`` (``warm``, ``bit_depth``)."""
    parser = script_parser(doc)
    parser.add_argument("--lenses", type=int, nargs=2, default=list(lenses))
    parser.add_argument("--rounds", type=int, default=rounds)
    args = parser.parse_args()
    queue = get_queue(profiling=True)
    print(f"device: {queue.device.name.strip()} ({queue.device.platform.name.strip()})")
    return alternate_ways(ways(queue), args.lenses, args.rounds, queue=queue, **options)
