"""Benchmark of plenocl's 3-D PIV: accuracy, speed, peak locking, deformation order.

Run from the repository root::

    python benchmarks/piv.py              # full run, 3 repeats (several minutes on 2 cores)
    python benchmarks/piv.py --quick      # fewer cases, 1 repeat
    python benchmarks/piv.py --device-only  # piv3d alone vs inside process_pair
    python benchmarks/piv.py --sums-only  # the direct correlation's sums, host vs device

Every case renders a synthetic volume pair (Gaussian particles, sigma 1 voxel, 0.004
particles/voxel, erf-integrated) with known displacement and runs plenocl's ``piv3d``
(defaults) and openpiv-python's single-pass ``extended_search_area_piv3D`` on the *same*
volumes in the same process; times are medians over the repeats. Errors are RMS of the
vector error (voxels) over interior vectors (window centres at least 16 voxels from
every face) against the mid-time displacement of the flow. openpiv has no validation, so
its "valid" column applies plenocl's normalised median test to its field.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("TQDM_DISABLE", "1")   # openpiv's per-window progress bar

import numpy as np
import scipy

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenocl import flows  # noqa: E402
from plenocl.bench import piv_flows  # noqa: E402
from plenocl.bench.piv_section import displacement_truth, interior, load_openpiv  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.piv import piv3d  # noqa: E402
from plenocl.piv.validation import normalized_median_test  # noqa: E402

MARGIN = 16


def openpiv_or_none():
    """openpiv's 3-D module and version, or ``(None, None)`` with the reason printed."""
    p3, version = load_openpiv()
    if p3 is None:
        print(f"openpiv is not available ({version}); pip install openpiv to compare. "
              f"Running plenocl only.\n")
        return None, None
    return p3, version


def run_plenocl(pair, repeats: int, **kwargs) -> dict:
    res, seconds = timed(lambda: piv3d(pair.vol_a, pair.vol_b, **kwargs), repeats)
    return {"disp": np.stack([res.u, res.v, res.w]), "centres": (res.z, res.y, res.x),
            "valid": res.valid, "seconds": seconds}


def openpiv_centres(n: int, ws: int, ov: int) -> np.ndarray:
    """Window centres (voxel index) along one axis, as openpiv's get_coordinates places them."""
    count = (n - ws) // (ws - ov) + 1
    shift = (n - 1 - ((count - 1) * (ws - ov) + ws - 1)) // 2
    return np.arange(count) * (ws - ov) + (ws - 1) / 2 + shift


def run_openpiv(p3, pair, ws: int, ov: int, repeats: int) -> dict:
    """openpiv 3-D PIV; its (u, v, w) map to our (x, y, z) as (w, -u, v) (checked below)."""
    def call():
        return p3.extended_search_area_piv3D(pair.vol_a, pair.vol_b, window_size=(ws,) * 3,
                                             overlap=(ov,) * 3, search_area_size=(ws,) * 3)
    (u_op, v_op, w_op), seconds = timed(call, repeats)
    disp = np.stack([w_op, -u_op, v_op])
    centres = tuple(openpiv_centres(n, ws, ov) for n in pair.vol_a.shape)
    flags = normalized_median_test(disp[::-1])
    return {"disp": disp, "centres": centres, "valid": ~flags, "seconds": seconds}


def score(run: dict, flow, shape) -> dict:
    err = run["disp"] - displacement_truth(flow, run["centres"])
    inner = interior(shape, run["centres"], MARGIN)
    e = err[:, inner]
    n = err[0].size
    return {"rms": float(np.sqrt(np.mean(np.sum(e**2, axis=0)))),
            "bias": float(np.abs(e.mean(axis=1)).max()),
            "valid": float(run["valid"][inner].mean()), "seconds": run["seconds"],
            "vectors": n, "us_per_vector": 1e6 * run["seconds"] / n}


def print_table(title: str, header: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print(title)
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
    print()


def check_openpiv_axes(p3) -> None:
    """Fail loudly if openpiv's axis/sign convention is not the one assumed."""
    d = (1.3, -0.6, 2.2)
    pair = flows.volume_pair((64, 64, 64), flows.Uniform(d), seed=1)
    run = run_openpiv(p3, pair, 32, 16, 1)
    got = np.median(run["disp"].reshape(3, -1), axis=1)
    assert np.allclose(got, d, atol=0.25), f"openpiv axis mapping changed: {got} vs {d}"


def comparison(p3, shapes, repeats: int, seed: int) -> None:
    header = ["volume (z,y,x)", "flow", "method", "RMS err", "|bias|", "valid", "time s",
              "vectors", "us/vector"]
    rows = []
    for shape in shapes:
        for name, flow in piv_flows(shape).items():
            pair = flows.volume_pair(shape, flow, seed=seed)
            runs = {"plenocl piv3d": run_plenocl(pair, repeats)}
            if p3 is not None:
                runs["openpiv 32^3 50%"] = run_openpiv(p3, pair, 32, 16, repeats)
                runs["openpiv 24^3 75%"] = run_openpiv(p3, pair, 24, 18, repeats)
            for method, run in runs.items():
                s = score(run, flow, shape)
                rows.append(["x".join(map(str, shape)), name, method, f"{s['rms']:.4f}",
                             f"{s['bias']:.4f}", f"{s['valid']:.3f}", f"{s['seconds']:.2f}",
                             str(s["vectors"]), f"{s['us_per_vector']:.0f}"])
            print(f"  done {shape} {name}", file=sys.stderr, flush=True)
    print_table(f"PIV accuracy and speed (median of {repeats} runs; interior RMS in voxels)",
                header, rows)


def peak_locking(p3, seed: int) -> None:
    """Histogram of the sub-voxel parts of the measured displacement in an ABC flow."""
    shape = (96, 96, 96)
    flow = _ABCFlow(amplitude=2.0, wavelength=96.0)
    pair = flows.volume_pair(shape, flow, seed=seed)
    runs = {"plenocl": run_plenocl(pair, 1)}
    if p3 is not None:
        runs["openpiv 24^3 75%"] = run_openpiv(p3, pair, 24, 18, 1)
    series = {"truth (same vector grid)": displacement_truth(flow, runs["plenocl"]["centres"])}
    series.update({name: run["disp"] for name, run in runs.items()})
    bins = np.linspace(0.0, 1.0, 11)
    rows = []
    for name, disp in series.items():
        frac = np.mod(disp.ravel(), 1.0)
        hist = np.histogram(frac, bins)[0] / frac.size
        rows.append([name, *(f"{h:.3f}" for h in hist),
                     f"{(hist[[0, -1]].sum() - hist[[4, 5]].sum()) / 0.2:+.2f}"])
    header = ["series", *(f"{a:.1f}-{b:.1f}" for a, b in zip(bins[:-1], bins[1:])),
              "locking"]
    print_table("Peak locking: fraction of sub-voxel parts (all components) per bin, ABC flow "
                "96^3, +-4 voxels; locking = (near-integer - near-half) / 0.2, 0 = none",
                header, rows)


class _ABCFlow:
    """Arnold-Beltrami-Childress flow (divergence-free), equal coefficients, in voxels."""

    def __init__(self, amplitude: float, wavelength: float):
        self.a = amplitude
        self.k = 2 * np.pi / wavelength

    def __call__(self, p: np.ndarray) -> np.ndarray:
        x, y, z = (self.k * np.asarray(p, float)).T
        a = self.a
        return np.column_stack([a * np.sin(z) + a * np.cos(y), a * np.sin(x) + a * np.cos(z),
                                a * np.sin(y) + a * np.cos(x)])


def deformation_study(repeats: int, seed: int) -> None:
    """Trilinear vs cubic vs quintic deformation, and the other design choices."""
    shape = (96, 96, 96)
    cases = piv_flows(shape)
    cases["uniform"] = flows.Uniform((1.5, -0.5, 2.5))   # half-voxel parts: worst bias
    pairs = {k: flows.volume_pair(shape, f, seed=seed + 1) for k, f in cases.items()}
    variants = {"cubic B-spline (default)": {}, "trilinear": {"deform_order": 1},
                "quintic B-spline": {"deform_order": 5},
                "top-hat windows": {"weighting": None}, "linear predictor": {"predictor": "linear"}}
    rows = []
    for label, kwargs in variants.items():
        row, total = [label], 0.0
        for name, flow in cases.items():
            s = score(run_plenocl(pairs[name], repeats, **kwargs), flow, shape)
            row += [f"{s['rms']:.4f}", f"{s['bias']:.4f}"]
            total += s["seconds"]
        rows.append([*row, f"{total / len(cases):.2f}"])
        print(f"  done {label}", file=sys.stderr, flush=True)
    header = ["variant", "uniform RMS", "|bias|", "rotation RMS", "|bias|", "oseen RMS",
              "|bias|", "time s"]
    print_table("Deformation interpolation and design choices (96^3; uniform shift "
                "(1.5, -0.5, 2.5) voxels)", header, rows)


def resolution_study(seed: int) -> None:
    """Lamb-Oseen error against core radius and peak swirl (spatial resolution)."""
    shape = (96, 96, 96)
    centre = (47.5 + 2.3, 47.5 - 1.7, 47.5 + 1.1)
    axis = (1.0, 2.0, 3.0)
    rows = []
    for rc, umax in ((12, 3.0), (16, 2.0), (16, 3.0), (16, 4.0), (24, 3.0), (24, 4.0)):
        flow = flows.LambOseen.from_peak_velocity(umax, rc, centre, axis)
        pair = flows.volume_pair(shape, flow, seed=seed + 2)
        row = [str(rc), f"{umax:.0f}", f"{umax / (flow.U_PEAK * rc):.2f}"]
        for iters in (3, 5):
            s = score(run_plenocl(pair, 1, final_iterations=iters), flow, shape)
            row += [f"{s['rms']:.4f}", f"{s['rms'] / umax:.3f}"]
        rows.append(row)
    header = ["core r_c", "u_max", "core rad/dt", "RMS (3 it.)", "RMS/u_max", "RMS (5 it.)",
              "RMS/u_max"]
    print_table("Lamb-Oseen vortex vs core size (final window 24^3, 96^3 volume)", header, rows)


def boundary_layer(seed: int) -> None:
    """The paper's flow: a turbulent boundary layer, mean profile from spatial averages."""
    shape = (80, 96, 128)
    tbl = flows.TurbulentBoundaryLayer(u_inf=6.0, delta=80.0, re_tau=1000.0, wall_y=-8.0,
                                       x_range=(0, 128), z_range=(0, 80), seed=seed)
    t0 = time.perf_counter()
    pair = flows.volume_pair(shape, tbl, seed=seed)
    t_gen = time.perf_counter() - t0
    run = run_plenocl(pair, 1)
    s = score(run, tbl, shape)
    zc, yc, xc = run["centres"]
    profile = run["disp"][0].mean(axis=(0, 2))
    expect = tbl.mean_velocity(yc)
    true_profile = displacement_truth(tbl, (zc, yc, xc))[0].mean(axis=(0, 2))
    print(f"Turbulent boundary layer 128x96x80 (U_inf 6 voxels, delta 80, Re_tau 1000, "
          f"u'/U_inf 0.07): interior RMS {s['rms']:.4f} voxel, valid {s['valid']:.3f}, "
          f"PIV {s['seconds']:.1f} s, rendering {t_gen:.1f} s")
    print("  y (vox)  measured <u>  true <u> (same points)  model mean U(y)")
    for y, m, t, e in list(zip(yc, profile, true_profile, expect))[::2]:
        print(f"  {y:7.1f}  {m:12.3f}  {t:22.3f}  {e:15.3f}")
    print()


def device_choice(repeats: int, seed: int) -> None:
    """``piv3d`` on its own (default device, as every stage) against the host deformation
    it used before without ``queue=`` and the queue ``process_pair`` passes, one pair."""
    from plenocl.opencl.device import get_queue

    shape = (100, 150, 200)
    pair = flows.volume_pair(shape, flows.Uniform((2.3, -1.4, 0.7)), density=0.001,
                             sigma=1.5, seed=seed, noise=0.02)
    variants = {"piv3d(a, b): default device (now)": {},
                "piv3d(a, b, queue=False): host SciPy (before: the default)": {"queue": False},
                "piv3d(a, b, queue=projector.queue), as process_pair": {"queue": get_queue()}}
    piv3d(pair.vol_a, pair.vol_b)  # kernels built, FFT plans made
    times = {label: [] for label in variants}
    results = {}
    for _ in range(max(1, repeats)):  # interleaved: drifts of a shared machine hit all alike
        for label, kwargs in variants.items():
            results[label], seconds = timed(lambda k=kwargs: piv3d(pair.vol_a, pair.vol_b, **k), 1)
            times[label].append(seconds)
    rows = []
    for label, res in results.items():
        err = [float(np.sqrt(np.mean((c - t) ** 2)))
               for c, t in zip((res.u, res.v, res.w), (2.3, -1.4, 0.7))]
        rows.append([label, f"{np.median(times[label]):.2f}",
                     " / ".join(f"{e:.4f}" for e in err)])
    print_table(f"piv3d's device, {shape[::-1]} voxels (x, y, z), medians of {repeats}, "
                f"interleaved", ["call", "seconds", "RMS error u / v / w (voxel)"], rows)


def window_sums(repeats: int, seed: int) -> None:
    """The direct correlation's window sums on the host (``HostSums``, BLAS: the path
    before) and on ``piv3d``'s device (``DeviceSums``, ``kernels/windowsums.cl``), alone
    on the final pass's grid and inside ``piv3d`` (same device deformation), at the
    paper's volume size, interleaved in one process."""
    from plenocl.opencl.device import get_queue
    from plenocl.piv import multipass
    from plenocl.piv.correlation import window_grid
    from plenocl.piv.devicesums import DeviceSums
    from plenocl.piv.direct import HostSums

    shape, queue = (150, 200, 286), get_queue()
    pair = flows.volume_pair(shape, flows.Uniform((1.7, -1.4, 2.3)), density=3.3e-4,
                             sigma=1.5, seed=seed, noise=0.02)
    grid = window_grid(shape, (24, 24, 24), 0.75)
    engines = {"host (BLAS)": HostSums(), "device": DeviceSums(queue)}
    calls = {f"{what}, {label}": (lambda e=engine, w=what: getattr(e, w)(
                 pair.vol_a, pair.vol_b, grid, 0.35))
             for what in ("correlation_sums", "spread_sums") for label, engine in engines.items()}
    chosen = {"piv3d, host sums": lambda deformer: None, "piv3d, device sums": multipass.sums_for}
    original = multipass.sums_for
    for label, choose in chosen.items():   # piv3d's engine, chosen as sums_for would
        calls[label] = (lambda c=choose: _piv3d_with(multipass, c, pair, queue))
    _interleaved(calls, repeats, f"window sums, {shape[::-1]} voxels (x, y, z), grid "
                 f"{grid.count[::-1]} of 24^3 windows at 75 % (x, y, z), {queue.device.name}")
    multipass.sums_for = original


def _piv3d_with(multipass, choose, pair, queue):
    """``piv3d`` with the window sums' engine ``choose(deformer)``."""
    original, multipass.sums_for = multipass.sums_for, choose
    try:
        return piv3d(pair.vol_a, pair.vol_b, queue=queue)
    finally:
        multipass.sums_for = original


def _interleaved(calls: dict, repeats: int, title: str) -> None:
    """Each call once (warm-up), then ``repeats`` rounds interleaved; medians; the two
    piv3d results' largest difference."""
    results = {label: call() for label, call in calls.items()}
    times = {label: [] for label in calls}
    for _ in range(max(1, repeats)):
        for label, call in calls.items():
            results[label], seconds = timed(call, 1)
            times[label].append(seconds)
    rows = [[label, f"{np.median(t):.3f}"] for label, t in times.items()]
    print_table(f"{title}, medians of {repeats}, interleaved", ["call", "seconds"], rows)
    host, device = results["piv3d, host sums"], results["piv3d, device sums"]
    diff = max(float(np.nanmax(np.abs(getattr(host, c) - getattr(device, c)))) for c in "uvw")
    print(f"piv3d fields, device sums against host sums: max |difference| {diff:.2e} voxel\n")


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--device-only", action="store_true",
                        help="only piv3d's device choice (default, host, process_pair's)")
    parser.add_argument("--sums-only", action="store_true",
                        help="only the direct correlation's window sums, host against device")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="96^3 only, 1 repeat")
    parser.add_argument("--seed", type=int, default=2718)
    args = parser.parse_args()
    repeats = 1 if args.quick else args.repeats
    if args.device_only:
        device_choice(repeats, args.seed)
        return
    if args.sums_only:
        window_sums(repeats, args.seed)
        return
    p3, version = openpiv_or_none()
    print(f"numpy {np.__version__}, scipy {scipy.__version__}, openpiv {version}, "
          f"{os.cpu_count()} CPUs\n")
    if p3 is not None:
        check_openpiv_axes(p3)
    shapes = [(96, 96, 96)] if args.quick else [(96, 96, 96), (80, 96, 128)]
    comparison(p3, shapes, repeats, args.seed)
    device_choice(repeats, args.seed)
    window_sums(repeats, args.seed)
    peak_locking(p3, args.seed)
    deformation_study(1 if args.quick else repeats, args.seed)
    if not args.quick:
        resolution_study(args.seed)
        boundary_layer(args.seed)


if __name__ == "__main__":
    main()
