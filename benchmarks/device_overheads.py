"""What a GPU's pair loses outside its kernels (issue 46, docs/design.md §7.5): the
chain's pair with each of three changes undone, and with all three, against the chain as
it is, alternately in one process.

    python benchmarks/device_overheads.py [--lenses 289 193] [--rounds 3]

- *kept buffers*: each iteration's projection, ratio and back projection written over
  the previous iteration's (``Solver.kept``); undone: new device buffers each iteration
  (a GPU driver allocates and frees them; a CPU device faults their pages in).
- *one launch*: the image fit renders every particle at once on a GPU
  (``fitsums.fit_chunk``); undone: 128 at a time (22 launches a step on the paper pair,
  each with its uploads and index tables).
- *ahead*: the second exposure's host preparation on a helper thread while the first
  reconstructs, off a CPU device (``pipeline.pair``); undone: in turn. On a CPU device
  the chain already runs it in turn, so there the two rows are the same code.

Scene: ``benchmarks/paper_pair.py``'s (the paper's optics, 0.05 particles per microlens,
ray traced with blur and noise; the paper's 289 x 193 lenses by default), default chain,
kernels built and one pair run each way before the rounds. Each round profiles one pair
each way (:class:`plenocl.bench.clprofile.OpenCLProfile`): the calls in which the host
waited for the queue, its work outside OpenCL calls and the pair's wall time; then the
medians, and whether every way gave the same vectors to the bit.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


from plenocl.bench.alternate import alternation_script  # noqa: E402
from plenocl.opencl.device import is_cpu  # noqa: E402
from plenocl.pipeline import pair as pair_module  # noqa: E402
from plenocl.piv import fitsums  # noqa: E402
from plenocl.reconstruction.solver import Solver  # noqa: E402

KEPT, CHUNK = Solver.kept, fitsums.fit_chunk


def fresh_buffers(self, name, make):
    """``Solver.kept`` undone: a new buffer at every call."""
    return make()


def chunk_of_128(renderer, chunk=None):
    """``fit_chunk`` undone: 128 particles a launch unless a chunk is given."""
    return fitsums.HOST_CHUNK if chunk is None else int(chunk)


def undo(*changes: str) -> None:
    """The chain with ``changes`` undone and the others as they are."""
    Solver.kept = fresh_buffers if "kept buffers" in changes else KEPT
    fitsums.fit_chunk = chunk_of_128 if "one launch" in changes else CHUNK
    pair_module.is_cpu = (lambda device: True) if "ahead" in changes else is_cpu


WAYS = {"all three undone": ("kept buffers", "one launch", "ahead"),
        "kept buffers undone": ("kept buffers",), "one launch undone": ("one launch",),
        "ahead undone": ("ahead",), "as it is": ()}


def main() -> None:
    alternation_script(__doc__, lambda queue: {
        label: functools.partial(undo, *changes) for label, changes in WAYS.items()},
        lenses=(289, 193), rounds=3)


if __name__ == "__main__":
    main()
