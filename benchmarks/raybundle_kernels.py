"""The image fit's render kernels alone: the device seconds of ``ray_spots`` and
``render_rows`` per render (profiling-queue events), against a git revision's kernels in
the same run.

    python benchmarks/raybundle_kernels.py [--lenses 289 193] [--particles 2800]
                                           [--rays 200] [--chunk 128] [--repeat 3]
                                           [--rows-per-item 0 1] [--baseline REV]
                                           [--fresh-output]

The paper's optics on ``--lenses`` microlenses (289 x 193: the whole 16 MP sensor),
``--particles`` at uniform random positions in the grid (strong defocus included), each
rendered with and without derivatives in chunks of ``--chunk`` particles, as
``DeviceFitSums`` renders them, into one output buffer kept for all runs (with
``--fresh-output`` a new one per render, as ``DeviceFitSums`` did before it kept its
buffers: on a CPU device the first touch of its pages is then part of the kernels'
time). One renderer per ``--rows-per-item`` (``DeviceRayBundle.rows_per_item``: 0 a
whole patch per work-item, the CPU's choice; 1 a row, the GPU's) and, with
``--baseline REV``, one with ``kernels/raybundle.cl`` and ``plenocl/piv/devicebundle.py``
of git revision ``REV``. The renderers take turns ``--repeat`` times; printed per
renderer: the median seconds of each kernel per render and of the render's wall time,
and the largest difference of each row from the first renderer's, over that row's peak.

Measured (2 shared CPU cores, PoCL 3.0, load 7; the defaults, medians of 3, baseline
28c6a20: the kernels before issue 28, both with the kept output): with derivatives
``ray_spots`` 1.32 -> 0.22 s, ``render_rows`` 0.55 -> 0.19 s (a row per item, the GPU
form, 0.73 s on this CPU); values only 1.27 -> 0.21 s and 0.41 -> 0.04 s; the rows
within 4.9e-7 of their peaks. docs/design.md §7.2 has the rest.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import paper_optics  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.opencl.program import KernelSet  # noqa: E402
from plenocl.optics.raybundle import Patches, RayBundle  # noqa: E402
from plenocl.piv.devicebundle import DeviceRayBundle  # noqa: E402

KERNELS = ("ray_spots", "render_rows")


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--lenses", type=int, nargs=2, default=[289, 193])
    parser.add_argument("--particles", type=int, default=2800)
    parser.add_argument("--rays", type=int, default=200)
    parser.add_argument("--chunk", type=int, default=128)
    parser.add_argument("--repeat", type=int, default=3, help="timed renders (median)")
    parser.add_argument("--rows-per-item", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--baseline", help="git revision whose kernels to time as well")
    parser.add_argument("--fresh-output", action="store_true",
                        help="a new output buffer per render (page faults included)")
    args = parser.parse_args()
    queue = get_queue(profiling=True)
    cam, grid = paper_optics(tuple(args.lenses))
    bundle = RayBundle.of(cam, rays=args.rays)
    rng = np.random.default_rng(3)
    low = [grid.x[0], grid.y[0], grid.z[0]]
    high = [grid.x[1], grid.y[1], grid.z[1]]
    points = cam.image_points(rng.uniform(low, high, (args.particles, 3)))
    intensity = rng.uniform(100.0, 1000.0, args.particles)
    patches = bundle.patches(points)
    print(f"device: {queue.device.name.strip()}; {args.particles} particles, {args.rays} "
          f"rays, {int(patches.offset[-1])} patch elements")
    renderers = {}
    if args.baseline:
        renderers[f"baseline {args.baseline}"] = baseline_renderer(args.baseline, bundle, queue)
    for rows in args.rows_per_item:
        renderers[f"rows/item {rows}"] = DeviceRayBundle(bundle, queue)
        renderers[f"rows/item {rows}"].rows_per_item = rows
    scene = (points, intensity, patches, args.chunk, not args.fresh_output)
    for derivatives in (True, False):
        timed = {name: [] for name in renderers}
        rows = {}
        for repeat in range(args.repeat + 1):  # the first: builds and warms up
            for name, renderer in renderers.items():
                rows[name], seconds = render(renderer, derivatives, scene)
                if repeat:
                    timed[name].append(seconds)
        report(derivatives, timed, rows)


def render(renderer, derivatives: bool, scene: tuple) -> tuple[np.ndarray, list[float]]:
    """One chunked render into the output buffer; the rows and the seconds of each kernel
    and of the wall."""
    points, intensity, patches, chunk, keep = scene
    total = int(patches.offset[-1])
    out = output(renderer.queue, (5 if derivatives else 1) * total, keep)
    events = []
    start = time.perf_counter()
    for first in range(0, len(points), chunk):
        part = slice(first, first + chunk)
        sub = Patches(patches.offset[first:part.stop + 1], patches.col0[part],
                      patches.row0[part], patches.width[part], patches.height[part])
        events += renderer.render_into(points[part], intensity[part], sub, derivatives,
                                       out, total)
    renderer.queue.finish()
    wall = time.perf_counter() - start
    seconds = [sum((e.profile.end - e.profile.start) * 1e-9 for e in events[k::2])
               for k in range(2)]
    return out.get().reshape(-1, total), [*seconds, wall]


_KEPT: dict[int, cl_array.Array] = {}


def output(queue, size: int, keep: bool) -> cl_array.Array:
    """The output buffer of ``size`` floats: kept from one render to the next, or new."""
    if not keep:
        return cl_array.empty(queue, size, np.float32)
    if size not in _KEPT:
        _KEPT[size] = cl_array.empty(queue, size, np.float32)
    return _KEPT[size]


def report(derivatives: bool, timed: dict, rows: dict) -> None:
    """Per renderer: median seconds per render and the rows' largest differences."""
    print(f"\nwith derivatives: {derivatives}   (medians of {len(next(iter(timed.values())))}"
          " renders; max |rows - first renderer's| / row peak)")
    first = rows[next(iter(rows))]
    for name, runs in timed.items():
        ray, ren, wall = np.median(np.array(runs), axis=0)
        diff = [np.abs(r - f).max() / max(np.abs(f).max(), 1e-30)
                for r, f in zip(rows[name], first, strict=True)]
        print(f"{name:22s} ray_spots {ray:7.3f} s  render_rows {ren:7.3f} s  wall "
              f"{wall:7.3f} s  diff {max(diff):.1e}")


class _SourceKernels(KernelSet):
    """The two kernels of a revision's ``raybundle.cl`` (built from its text against
    today's headers), each launch's event recorded."""

    def __init__(self, queue, source: str, derivatives: bool) -> None:
        super().__init__(queue, "raybundle.cl", KERNELS, [f"-DPL_DERIVATIVES={int(derivatives)}"],
                         looping=["render_rows"], source=source)
        self.events: list[cl.Event] = []

    def launch(self, name, global_size, *args, local_size=None):
        event = super().launch(name, global_size, *args, local_size=local_size)
        self.events.append(event)
        return event


class _Baseline:
    """A revision's renderer whose ``render_into`` returns its kernels' events."""

    def __init__(self, renderer, programs: dict) -> None:
        self.renderer, self.programs, self.queue = renderer, programs, renderer.queue

    def render_into(self, *args):
        for program in self.programs.values():
            program.events.clear()
        self.renderer.render_into(*args)
        return [e for program in self.programs.values() for e in program.events]


def baseline_renderer(revision: str, bundle: RayBundle, queue) -> _Baseline:
    """``DeviceRayBundle`` and ``raybundle.cl`` of git ``revision``."""
    def show(path: str) -> str:
        return subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:{path}"],
                              check=True, capture_output=True, text=True).stdout

    spec = importlib.util.spec_from_loader("plenocl.piv.baseline_bundle", loader=None)
    module = importlib.util.module_from_spec(spec)
    code = show("plenocl/piv/devicebundle.py")
    # revisions before the OpenCL layer's folder (issue 48) import it from the package root
    code = re.sub(r"from \.\.(device|program|build|icd|threads) import",
                  r"from ..opencl.\1 import", code)
    exec(compile(code, f"{revision}:devicebundle.py", "exec"), module.__dict__)
    source = show("kernels/raybundle.cl")
    programs = {d: _SourceKernels(queue, source, d) for d in (True, False)}

    class Renderer(module.DeviceRayBundle):
        def _kernels(self, derivatives: bool):
            return programs[derivatives]

    return _Baseline(Renderer(bundle, queue), programs)


if __name__ == "__main__":
    main()
