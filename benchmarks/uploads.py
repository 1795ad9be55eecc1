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

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import UNIFORM, budget_scene, paper_setup  # noqa: E402
from plenocl.bench.clprofile import OpenCLProfile, total_profile  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.opencl import arrays  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402


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


def profiled_pair(scene, proj) -> tuple[dict, object]:
    """One pair under the profile: waits, host work and wall seconds, and its field."""
    with OpenCLProfile() as prof:
        pair = process_pair(scene.raw_a, scene.raw_b, proj)
        proj.queue.finish()
    total = total_profile(prof.split(pair.spans))
    return {"waits": total.waits, "host": total.host, "wall": total.wall}, pair.piv


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[116, 78])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    queue = get_queue(profiling=True)
    cam, grid, proj = paper_setup(tuple(args.lenses), queue)
    scene = budget_scene(cam, grid, 0.05, 3, queue, motion=UNIFORM)
    ways = {"blocking to_device (before)": blocking_upload, "arrays.upload": arrays.upload}
    for upload in ways.values():
        uploads_by(upload)
        process_pair(scene.raw_a, scene.raw_b, proj)  # kernels, plans and routes made
    rows = {label: [] for label in ways}
    fields = {}
    print(f"{'round':>5s} {'uploads':28s} {'waits':>6s} {'host s':>7s} {'wall s':>7s}")
    for k in range(args.rounds):
        for label, upload in ways.items():
            uploads_by(upload)
            row, fields[label] = profiled_pair(scene, proj)
            rows[label].append(row)
            print(f"{k + 1:5d} {label:28s} {row['waits']:6d} {row['host']:7.3f} "
                  f"{row['wall']:7.2f}", flush=True)
    uploads_by(arrays.upload)
    print("medians")
    for label, got in rows.items():
        med = {key: float(np.median([r[key] for r in got])) for key in got[0]}
        print(f"{'':5s} {label:28s} {med['waits']:6.0f} {med['host']:7.3f} {med['wall']:7.2f}")
    a, b = fields.values()
    same = all(np.array_equal(getattr(a, c), getattr(b, c), equal_nan=True)
               for c in ("u", "v", "w", "valid"))
    print(f"the vectors the same to the bit: {same}")


if __name__ == "__main__":
    main()
