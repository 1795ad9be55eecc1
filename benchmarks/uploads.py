"""Uploads that do not wait for the queue (issue 46, docs/design.md §7.5): the chain's
pair with ``opencl.arrays.upload`` (the buffer made from the host array, no command on
the queue) against the same chain with pyopencl's blocking ``to_device`` put back in
every module that uploads (the code before), alternately in one process.

    python benchmarks/uploads.py [--lenses 116 78] [--rounds 3]

Scene: ``benchmarks/paper_pair.py``'s (the paper's optics, 0.05 particles per microlens,
ray traced with blur and noise), default chain, kernels built and one pair run before
the rounds. Each round profiles one pair each way (:class:`plenocl.bench.clprofile.
OpenCLProfile`): the calls in which the host waited for the queue, its work outside
OpenCL calls and the pair's wall time; then the medians, and whether the two ways gave
the same vectors to the bit.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import pyopencl.array as cl_array  # noqa: E402

from plenocl.bench.alternate import alternation_script  # noqa: E402
from plenocl.opencl import arrays  # noqa: E402


def blocking_upload(queue, host):
    """The upload before: pyopencl's blocking write, which waits for the queue."""
    return cl_array.to_device(queue, np.ascontiguousarray(host))


def uploads_by(upload) -> None:
    """Every plenocl module that uploads through ``arrays.upload`` made to use
    ``upload`` (the modules import the function by name)."""
    for name, module in list(sys.modules.items()):
        uses = getattr(module, "upload", None) in (arrays.upload, blocking_upload)
        if name.startswith("plenocl") and module is not arrays and uses:
            module.upload = upload


def main() -> None:
    alternation_script(__doc__, lambda queue: {
        "blocking to_device (before)": lambda: uploads_by(blocking_upload),
        "arrays.upload": lambda: uploads_by(arrays.upload)}, rounds=3)


if __name__ == "__main__":
    main()
