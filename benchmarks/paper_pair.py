"""One image pair at the paper's full size: the stage split and the velocity error of
each reconstruction setting, every setting on the same scene in the same run.

    python benchmarks/paper_pair.py [--settings previous fullaperture default] [--lenses 289 193]
                                    [--seeding 0.05] [--motion uniform] [--bit-depth 16]
                                    [--profile] [--host-profile N] [--bytes-by-site N]
                                    [--scratch-mb M]

Camera: the paper's optics on the whole 16 MP sensor (289 x 193 microlenses,
4914 x 3282 px); grid: the paper's 300 x 200 x 150 voxels (``paper_optics``, as in
``benchmarks/accuracy.py``). Scene: ray-traced particles at ``--seeding`` per microlens
with 0.8 px blur, photon and read noise (``budget_scene``; ``--bit-depth 16``: as a
camera's 16-bit integers, whose median takes a histogram), moved by the motion. Each
setting runs ``plenocl.process_pair`` on the same two raw images; the table gives the
seconds of each stage (both reconstructions, PIV, the particle refinement with its fit
to the raw images), the lateral and depth RMS error (voxels) of the valid vectors, and
the particles the first volume recovered; then how many windows each PIV pass
correlated by FFT (``PIVResult.passes``' ``fft_windows``: the first pass all of them, a
deformed pass those its direct lags could not fit). The refined projector (the fine iterations),
the coarse-sampled ones (the coarse and the early fine iterations) and their
sensitivities are built before the rows (a batch builds them once per worker) and their
time printed, so no row pays for them and the order of the rows does not matter.

``--profile``: everything runs on a queue with profiling enabled, and after the rows the
first setting's pair runs more times under
:class:`plenocl.bench.clprofile.OpenCLProfile`: first with every PIV FFT on the device
and the queue's memory pool off (every device array made and released by the driver, as
before 2026-12-03: :mod:`plenocl.opencl.pool`), then, the pool on again, returning its
volumes (``volumes=True``, the chain before 2026-12-02), with every PIV FFT on the
device (``PIVSettings(fft="device")``, the route a GPU measures: no volume comes back)
and asked for its vectors alone (``volumes=False``, as a batch that keeps no volumes,
the FFT route as measured on this device); with ``--bit-depth``, also with the camera's
counts given as float32 (every PIV FFT on the device), which the host prepares as it
prepared every image before 2026-12-02 evening, where the counts themselves are prepared
on the device (:mod:`plenocl.reconstruction.deviceimage`). The last one's table gives
per stage the wall seconds, the seconds inside OpenCL calls, the host's own work outside
them, the kernels' device seconds (profiling events), the launches, the calls in which
the host waited for the queue (waits and blocking copies) and the megabytes moved each
way; then, for every one, the host's work in the stages (beside their wall and kernel
seconds) and the bytes moved each way
(every copy, the volumes' after the stages too) against the two raw images; then the 15
kernels of most device time (launches, seconds, share).
``--host-profile N``: the first setting's pair once more under cProfile, its ``N``
functions of most own time (on a GPU, where the host's work goes; docs/design.md §7.5).
``--bytes-by-site N``: the first setting's pair once more, its vectors alone with every
PIV FFT on the device (a GPU's route), each copy to or from the host told by the plenocl
function that made it (``OpenCLProfile(sites=True)``): each way's ``N`` largest sites,
what moves beyond the raw images and the vectors (issue 46).
``--scratch-mb M``: the projector's scratch bound (``Projector(scratch_bytes=)``); the
sub-voxel projector's plan (chunks, depths a launch) is printed either way. On this
CPU one chunk of every depth halved the launches (1,077 → 541 a 116 x 78 pair) and the
host's work with them (0.775 → 0.700 s) but slowed the kernels by a fifth (9.4 → 11.5
s): to be measured on a GPU, whose launches cost more and whose kernels gain from
larger ones (docs/design.md §7.5).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import (  # noqa: E402
    PREVIOUS_SETTINGS,
    ROTATION,
    UNIFORM,
    budget_scene,
    pair_row,
    paper_setup,
)
from plenocl.bench.clprofile import (  # noqa: E402
    OpenCLProfile,
    kernel_lines,
    site_lines,
    split_lines,
    total_profile,
)
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.opencl.pool import use_pool  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402
from plenocl.piv import PIVSettings  # noqa: E402
from plenocl.reconstruction import SUPERSAMPLE, ReconstructionSettings  # noqa: E402
from plenocl.reconstruction.settings import (  # noqa: E402
    COARSE_OVERSAMPLE,
    EARLY_OVERSAMPLE,
)

MOTIONS = {"uniform": UNIFORM, "rotation": ROTATION}
#: The reconstruction settings compared (each with process_pair's other defaults).
SETTINGS = {  # before: 30 MLEM iterations on the sub-voxels from a uniform volume
    "before": PREVIOUS_SETTINGS,
    # the default until 2026-11-26: coarse 10 + fine 10 MLEM iterations at μ = 1
    "previous": ReconstructionSettings(supersample=3, coarse_iterations=10, iterations=10,
                                       relax=1.0, support=0.01, coarse_oversample=None,
                                       early_oversample=None),
    # the default with every iteration on the projector's own aperture sampling (the
    # default until 2026-11-26 afternoon, before coarse_oversample and early_oversample)
    "fullaperture": ReconstructionSettings(supersample=3, coarse_iterations=5, iterations=7,
                                           relax=1.5, support=0.01, coarse_oversample=None,
                                           early_oversample=None),
    "default": None,
    # the default with the paper's bilinear lens weights (the default until 2026-11-29)
    "paperweights": ReconstructionSettings(lens_weights="paper"),
    "voxels": ReconstructionSettings(supersample=1),
    # the paper's method with its defaults (smoothed by 1 px, after MLEM's coarse run)
    "mart": ReconstructionSettings("mart"),
}


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=SETTINGS)
    parser.add_argument("--lenses", type=int, nargs=2, default=[289, 193])
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--motion", default="uniform", choices=MOTIONS)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--bit-depth", type=int, default=None,
                        help="raw images as a camera's integers (e.g. 16) instead of float "
                             "counts")
    parser.add_argument("--profile", action="store_true",
                        help="then the first setting's pair once more, profiled")
    parser.add_argument("--host-profile", type=int, default=0, metavar="N",
                        help="then the first setting's pair once more under cProfile: its "
                             "N functions of most own time (where the host's work goes)")
    parser.add_argument("--bytes-by-site", type=int, default=0, metavar="N",
                        help="then the first setting's pair once more, its copies by the "
                             "plenocl function that made them: each way's N largest")
    parser.add_argument("--scratch-mb", type=float, default=None,
                        help="the projector's scratch bound (MiB; default: the device's "
                             "rule): a larger one takes more depths per launch")
    args = parser.parse_args()
    queue = get_queue(profiling=args.profile)
    options = ({} if args.scratch_mb is None
               else {"scratch_bytes": int(args.scratch_mb * 2**20)})
    cam, grid, proj = paper_setup(tuple(args.lenses), queue, **options)
    motion = MOTIONS[args.motion]
    scene = budget_scene(cam, grid, args.seeding, args.seed, queue, motion=motion,
                         bit_depth=args.bit_depth)
    t0 = time.perf_counter()
    proj.refined(SUPERSAMPLE).sensitivity()
    proj.sampled(COARSE_OVERSAMPLE).sensitivity()
    proj.refined(SUPERSAMPLE).sampled(EARLY_OVERSAMPLE).sensitivity()
    queue.finish()
    print(f"the refined projector, the coarse and early sampled ones and their "
          f"sensitivities, built "
          f"once per projector (a batch "
          f"worker's first pair): {time.perf_counter() - t0:.1f} s; every row below runs "
          "with them built")
    fine = proj.refined(SUPERSAMPLE).plan
    print(f"the sub-voxel projector's plan: {len(fine.columns)} aperture-column chunk(s), "
          f"{fine.zchunk} depths a launch, {fine.scratch_bytes / 2**20:.0f} MiB of scratch")
    print(f"{scene.count} particles ({args.seeding} per microlens), {motion.name}")
    print(f"{'setting':10s} {'total s':>8s} {'rec a':>6s} {'rec b':>6s} {'piv':>5s} "
          f"{'part.':>6s} | {'lateral':>7s} {'depth':>6s} {'valid':>6s} {'recov':>6s}")
    by_fft = []
    for name in args.settings:
        rec = SETTINGS[name]
        pair = process_pair(scene.raw_a, scene.raw_b, proj,
                            **({} if rec is None else {"reconstruction": rec}))
        row, s = pair_row(pair, scene, grid, motion), pair.seconds
        e = row["errors"]
        print(f"{name:10s} {sum(s.values()):8.1f} {s['reconstruct_a']:6.1f} "
              f"{s['reconstruct_b']:6.1f} {s['piv']:5.1f} {s.get('particles', 0):6.1f} | "
              f"{e['lateral']:7.3f} {e['depth']:6.3f} {e['valid']:6.0%} "
              f"{row['recovered']:6.0%}", flush=True)
        by_fft.append(f"{name} {[p['fft_windows'] for p in pair.piv.passes]}")
    print(f"PIV windows correlated by FFT per pass (of {pair.piv.passes[-1]['vectors']} in "
          f"the last): {'; '.join(by_fft)}")
    if args.profile:
        profile_pair(scene, proj, SETTINGS[args.settings[0]])
    if args.host_profile:
        host_profile(scene, proj, SETTINGS[args.settings[0]], args.host_profile)
    if args.bytes_by_site:
        bytes_by_site(scene, proj, SETTINGS[args.settings[0]], args.bytes_by_site)


#: The profiled ways of the pair: the label, ``volumes=``, PIV's FFT route, whether a
#: camera's integer counts are given as float32 (prepared on the host, as every image
#: was before 2026-12-02 evening; rows only with ``--bit-depth``) and whether the queue's
#: memory pool is on (off: every array made and released by the driver, as before
#: 2026-12-03; :mod:`plenocl.opencl.pool`).
PROFILED = (("no memory pool", False, "device", False, False),
            ("with the volumes", True, None, False, True),
            ("counts as floats", False, "device", True, True),
            ("the device's FFT", False, "device", False, True),
            ("the vectors alone", False, None, False, True))


def profile_pair(scene, proj, rec) -> None:
    """One pair of ``scene`` with reconstruction settings ``rec``, profiled: its split
    and the bytes it moved against the raw images'; beside it, in the same run, the same
    pair returning its volumes (the chain before 2026-12-02, whose volumes came back) and
    with every PIV FFT on the device (a GPU's route: no volume comes back)."""
    moved = {}
    counts = scene.raw_a.dtype.kind in "ui"
    profiled = [row for row in PROFILED if counts or not row[3]]
    for label, volumes, fft, as_floats, pooled in profiled:
        raws = ((scene.raw_a, scene.raw_b) if not as_floats else
                (scene.raw_a.astype(np.float32), scene.raw_b.astype(np.float32)))
        use_pool(proj.queue, pooled)
        with OpenCLProfile() as prof:
            pair = process_pair(*raws, proj, volumes=volumes,
                                **({} if fft is None else {"piv": PIVSettings(fft=fft)}),
                                **({} if rec is None else {"reconstruction": rec}))
            proj.queue.finish()
        split = prof.split(pair.spans)
        total = total_profile(split)
        back = sum(call.nbytes for call in prof.calls if call.kind == "d2h")
        moved[label] = (total.host, total.h2d_bytes, back, total.wall, total.kernel)
    print("\n".join(split_lines(split)))
    raws = scene.raw_a.nbytes + scene.raw_b.nbytes
    for label, *_ in profiled[::-1]:
        host, moved_in, moved_out, wall, kernel = moved[label]
        print(f"{label:17s}: host work {host:.3f} s in the stages ({wall:.2f} s wall, "
              f"{kernel or 0.0:.2f} s of kernels); {moved_in / 1e6:.1f} MB "
              f"to the device ({moved_in / raws:.1f}x the two raw images' {raws / 1e6:.1f} "
              f"MB), {moved_out / 1e6:.1f} MB back (every copy)")
    print("\n".join(kernel_lines(prof.kernel_seconds())))


def vectors_alone(scene, proj, rec, fft: str | None = None):
    """One pair of ``scene`` asked for its vectors alone, with reconstruction settings
    ``rec`` (``None``: the default) and PIV's FFT route ``fft`` (``None``: the default's
    measured one), the queue finished; its :class:`PairResult`."""
    pair = process_pair(scene.raw_a, scene.raw_b, proj, volumes=False,
                        **({} if fft is None else {"piv": PIVSettings(fft=fft)}),
                        **({} if rec is None else {"reconstruction": rec}))
    proj.queue.finish()
    return pair


def host_profile(scene, proj, rec, count: int) -> None:
    """One pair of ``scene`` under cProfile: the ``count`` functions of most own time."""
    import cProfile
    import io
    import pstats

    profiler = cProfile.Profile()
    profiler.enable()
    vectors_alone(scene, proj, rec)
    profiler.disable()
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(count)
    print(text.getvalue())


def bytes_by_site(scene, proj, rec, count: int) -> None:
    """One pair of ``scene``, its vectors alone, with every PIV FFT on the device (a
    GPU's route: the host's FFT brings its windows back, which would hide the rest),
    each copy told by the plenocl function that made it: each way's ``count`` largest,
    against the raw images and the vectors."""
    with OpenCLProfile(sites=True) as prof:
        pair = vectors_alone(scene, proj, rec, fft="device")
    raw = (scene.raw_a.nbytes + scene.raw_b.nbytes) / 1e6
    vectors = sum(a.nbytes for a in vars(pair.piv).values() if isinstance(a, np.ndarray))
    print(f"copies by the plenocl function that made them, every PIV FFT on the device "
          f"(the two raw images: {raw:.2f} MB; the vectors: {vectors / 1e6:.2f} MB)")
    print("\n".join(site_lines(prof.bytes_by_site(), count)))


if __name__ == "__main__":
    main()
