"""Projector throughput: matrix-free kernels against stored scipy.sparse CSR products of
the same weights (same run, medians of repeats), memory of both, the atomic-scatter
alternatives, and one forward + back projection of the paper's full experiment.

    python benchmarks/projector.py [--repeats 5] [--skip-paper] [--skip-direct]
                                   [--skip-stored] [--skip-small] [--skip-rotated]
                                   [--skip-reconstruction] [--skip-scratch]
                                   [--skip-widths]

Weights per second count the non-zeros of the weight matrix processed per second (the
CSR matrix's ``nnz`` for the stored case; an estimate from sampled voxels for the paper
grid, whose matrix cannot be stored). The roofline puts the paper grid's rate beside the
most a stored matrix could reach at this device's copy bandwidth (8 bytes per weight); the
small problems show the fixed cost per call.
"""

from __future__ import annotations

import os
import time

import numpy as np

from plenocl import Camera, Grid, get_queue
from plenocl.bench.accuracy_section import paper_optics
from plenocl.bench.scripts import script_parser
from plenocl.bench.sparse import matrix_bytes
from plenocl.bench.stages import csr_case, device_pair, projector_bytes
from plenocl.bench.timing import median_time
from plenocl.opencl.device import device_info, is_cpu
from plenocl.projection import Projector
from plenocl.projection.projector import cpu_vector_width
from plenocl.reconstruction import ReconstructionSettings
from plenocl.reconstruction.reconstruct import run_reconstruction


def row(label: str, nnz: float, seconds: float, note: str = "") -> None:
    print(f"  {label:44s} {seconds:9.4f} s {nnz / seconds / 1e6:10.1f} M weights/s  {note}")


def stored_comparison(queue, repeats: int, direct: bool) -> None:
    cam = Camera.synthetic_850()
    grid = Grid((40, 50, 50), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
    proj = Projector(cam, grid, queue)
    a, build, vol, img_h = csr_case(proj)
    fwd, back, _ = device_pair(proj, vol)
    img, out = proj.forward_device(proj.volume_to_device(vol)), proj.empty_volume()
    err_f = np.abs(a @ vol.ravel() - proj.forward(vol).ravel()).max() / (a @ vol.ravel()).max()
    ref_b = a.T @ img_h.ravel()
    err_b = np.abs(ref_b - proj.back(img_h).ravel()).max() / ref_b.max()
    print(f"850 x 850 camera (50 x 50 lenses, M = 1, f/2), grid {grid.shape} over 5 mm cubed: "
          f"{a.nnz:,} non-zeros ({a.nnz / grid.size:.0f} per voxel); CSR built from the "
          f"footprint kernel in {build:.1f} s")
    print(f"  kernels vs CSR products: max relative difference forward {err_f:.1e}, "
          f"back {err_b:.1e}")
    print(f"  memory: CSR matrix {matrix_bytes(a) / 2**20:.1f} MiB; projector tables + scratch "
          f"{projector_bytes(proj) / 2**20:.2f} MiB "
          f"({100 * projector_bytes(proj) / matrix_bytes(a):.2f}% of CSR); volume "
          f"{grid.nbytes / 2**20:.2f} MiB and image {img.nbytes / 2**20:.2f} MiB either way")
    x, y = vol.ravel(), img_h.ravel()
    t_fc, t_bc = median_time(lambda: a @ x, repeats), median_time(lambda: a.T @ y, repeats)
    t_f, t_b = median_time(fwd, repeats), median_time(back, repeats)
    t_fh = median_time(lambda: proj.forward(vol), repeats)
    t_bh = median_time(lambda: proj.back(img_h), repeats)
    print(f"  medians of {repeats} (forward = A x, back = A^T y):")
    row("scipy CSR forward (1 thread)", a.nnz, t_fc)
    row("scipy CSR back (CSR transpose)", a.nnz, t_bc)
    row("matrix-free forward, device-resident", a.nnz, t_f)
    row("matrix-free back, device-resident", a.nnz, t_b)
    row("matrix-free forward, host arrays in/out", a.nnz, t_fh)
    row("matrix-free back, host arrays in/out", a.nnz, t_bh)
    print(f"  forward + back: CSR {t_fc + t_bc:.4f} s, matrix-free {t_f + t_b:.4f} s "
          f"({(t_fc + t_bc) / (t_f + t_b):.1f}x faster)")
    atomic = Projector(cam, grid, queue, back="atomic")
    t_bs = median_time(lambda: (atomic.back_device(img, out), queue.finish()), repeats)
    ref_s = proj.volume_to_host(proj.back_device(img))
    err_s = np.abs(atomic.volume_to_host(out) - ref_s).max() / ref_s.max()
    row('back="atomic": atomic-scatter back_y', a.nnz, t_bs,
        f"(vs gather: max relative difference {err_s:.1e})")
    if direct:
        dproj = Projector(cam, grid, queue, method="direct")
        dfwd, dback, _ = device_pair(dproj, vol)
        row("direct forward: 16 atomic adds/sample/voxel", a.nnz, median_time(dfwd, repeats))
        row("direct back: 16-product gather per voxel", a.nnz, median_time(dback, repeats))


def paper_experiment(queue, repeats: int) -> dict[str, float]:
    cam = Camera.paper_16mp()
    grid = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0))
    proj = Projector(cam, grid, queue)
    rng = np.random.default_rng(1)
    sample = np.column_stack([rng.integers(0, n, 300) for n in grid.shape])
    nnz = np.mean([len(proj.voxel_weights(*v)[0]) for v in sample]) * grid.size
    fwd, back, _ = device_pair(proj, rng.random(grid.shape, dtype=np.float32))
    t_f, t_b = median_time(fwd, repeats), median_time(back, repeats)
    print(f"paper experiment: {cam.pixels[0]} x {cam.pixels[1]} px, {cam.ml_count[0]} x "
          f"{cam.ml_count[1]} lenses, grid {grid.shape} over 55 x 35 x 20 mm "
          f"({proj.path} path, {proj.n_samples} aperture samples)")
    print(f"  estimated non-zeros {nnz:.2e} (CSR would need {nnz * 8 / 2**30:.0f} GiB); "
          f"projector tables + scratch {projector_bytes(proj) / 2**20:.1f} MiB")
    print(f"  medians of {repeats}:")
    row("forward, device-resident", nnz, t_f)
    row("back, device-resident", nnz, t_b)
    print(f"  one forward + back: {t_f + t_b:.2f} s")
    return {"paper grid, forward": nnz / t_f, "paper grid, back": nnz / t_b}


def memory_bandwidth(queue, repeats: int, nbytes: int = 512 * 2**20) -> float:
    """Device-to-device copy bandwidth (bytes read + written per second) of ``queue``'s
    device: the roof a memory-bound product cannot pass."""
    import pyopencl as cl

    src = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, nbytes)
    dst = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, nbytes)
    cl.enqueue_fill_buffer(queue, src, np.float32(1.0), 0, nbytes)
    seconds = median_time(lambda: (cl.enqueue_copy(queue, dst, src), queue.finish()), repeats)
    return 2 * nbytes / seconds


def roofline(queue, repeats: int, rates: dict[str, float]) -> None:
    """Weight updates per second against the memory roof: a stored matrix (CSR, float32
    value + int32 column index) streams at least 8 bytes per weight, so this device's
    copy bandwidth caps any stored product at bandwidth / 8 weights per second."""
    bandwidth = memory_bandwidth(queue, repeats)
    roof = bandwidth / 8
    print(f"roofline: copy bandwidth {bandwidth / 1e9:.1f} GB/s (median of {repeats}, "
          f"512 MiB device-to-device): a stored matrix can do at most {roof / 1e6:.0f} M "
          f"weights/s here")
    for label, rate in rates.items():
        print(f"  {label:44s} {rate / 1e6:10.1f} M weights/s = {rate / roof:5.2f}x that roof")


def small_calls(queue, repeats: int) -> None:
    """Fixed cost per call: forward + back of small cubic grids on the 850 x 850 camera,
    device-resident, against the stored CSR products of the same weights."""
    cam = Camera.synthetic_850()
    print(f"small problems (850 x 850 camera), medians of {repeats}:")
    for n in (8, 16, 24):
        grid = Grid((n, n, n), x=(-1.0, 1.0), y=(-1.0, 1.0), z=(-1.0, 1.0))
        proj = Projector(cam, grid, queue)
        a, _, vol, img_h = csr_case(proj)
        fwd, back, _ = device_pair(proj, vol)
        x, y = vol.ravel(), img_h.ravel()
        t_csr = median_time(lambda a=a, x=x, y=y: (a @ x, a.T @ y), repeats)
        t_mf = median_time(lambda f=fwd, b=back: (f(), b()), repeats)
        print(f"  {n:2d}^3 voxels, {a.nnz:>10,} weights: matrix-free forward + back "
              f"{t_mf * 1e3:7.2f} ms, CSR {t_csr * 1e3:7.2f} ms ({t_csr / t_mf:.2f}x)")


def rotated_array(queue, repeats: int, rotation: float = 0.15) -> None:
    """The paper experiment with its array rotated by ``rotation`` degrees: on a grid in
    the sensor's axes (by default projected through the lens-row frame and resampled; and
    on the general kernels, ``general="exact"``) and on the grid of Grid.for_camera, whose
    axes follow the lens rows (separable path); calibrated-like centres (each lens 0.1 px
    off the lattice) too; against the axis-aligned array on the same grid, in the same
    run."""
    grid = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0))
    vol = np.random.default_rng(2).random(grid.shape, np.float32)
    ideal = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280),
                   ml_rotation_deg=rotation)
    jitter = np.random.default_rng(3).normal(0, 0.1 / np.sqrt(2), ideal.microlens_centers.shape)
    calibrated = ideal.with_centers(ideal.microlens_centers + jitter)
    aligned = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280))
    cases = [("aligned array", aligned, 0.0, "resample"),
             (f"{rotation:g} deg array, sensor-axis grid", ideal, 0.0, "resample"),
             (f"{rotation:g} deg array, sensor-axis grid, general kernels", ideal, 0.0, "exact"),
             (f"{rotation:g} deg array, lens-row grid", ideal, None, "resample"),
             (f"{rotation:g} deg, centres 0.1 px off lattice, lens-row grid", calibrated, None,
              "resample"),
             (f"{rotation:g} deg, centres 0.1 px off lattice, sensor-axis grid", calibrated,
              0.0, "resample")]
    base = None
    for label, cam, frame, general in cases:
        rot = (Grid.for_camera(cam, z=(-10, 10)).rotation_deg if frame is None else frame)
        g = Grid(grid.shape, grid.x, grid.y, grid.z, rotation_deg=rot)
        proj = Projector(cam, g, queue, general=general)
        fwd, back, _ = device_pair(proj, vol)
        t_f, t_b = median_time(fwd, repeats), median_time(back, repeats)
        base = base or t_f + t_b
        print(f"{label} (frame {rot:.4f} deg, {proj.path} path), paper grid, medians of "
              f"{repeats}: forward {t_f:.2f} s, back {t_b:.2f} s, forward + back "
              f"{t_f + t_b:.2f} s = {(t_f + t_b) / base:.2f}x the aligned array")


def rotated_reconstruction(queue, rotation: float = 0.15) -> None:
    """One coarse-to-fine reconstruction at the pair's defaults on the paper's grid and
    sensor: the aligned array, and the array rotated by ``rotation`` degrees on the
    lens-row grid and on a sensor-axis grid (reconstructed in the lens-row frame and
    resampled once, docs/design.md §5.1), in the same run. The image is the lens-row
    projection of particles at 0.05 per microlens (3 x 3 voxels each) plus noise."""
    grid = Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0))
    turned = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280),
                    ml_rotation_deg=rotation)
    aligned = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280))
    rng = np.random.default_rng(5)
    vol = np.zeros(grid.shape, np.float32)
    for z, y, x in zip(*(rng.integers(2, n - 2, 2790) for n in grid.shape)):
        vol[z, y - 1:y + 2, x - 1:x + 2] += 1000.0
    images = {}  # one per camera: both grids of the rotated array see the same image
    for cam, frame in ((aligned, 0.0), (turned, rotation)):
        truth = Projector(cam, Grid(grid.shape, grid.x, grid.y, grid.z, rotation_deg=frame),
                          queue)
        noisy = truth.forward(vol) + rng.normal(20, 3, truth.image_shape).astype(np.float32)
        images[id(cam)] = np.clip(noisy, 0, None)
    base = None
    for label, cam, frame in (("aligned array", aligned, 0.0),
                              (f"{rotation:g} deg array, lens-row grid", turned, rotation),
                              (f"{rotation:g} deg array, sensor-axis grid", turned, 0.0)):
        proj = Projector(cam, Grid(grid.shape, grid.x, grid.y, grid.z, rotation_deg=frame),
                         queue)
        t0 = time.perf_counter()
        run_reconstruction(images[id(cam)], proj, ReconstructionSettings())
        seconds = time.perf_counter() - t0
        base = base or seconds
        print(f"{label} ({proj.path} path): pair-default reconstruction {seconds:.1f} s = "
              f"{seconds / base:.2f}x the aligned array")


def _sparse_support(grid: Grid, factor: int = 3) -> np.ndarray:
    """A sparse support on ``grid``'s ``factor x factor`` sub-voxels (6.5 % of them, as a
    pair's fine iterations see it): dilated random voxels, random values."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    coarse = ndimage.binary_dilation(rng.random(grid.shape) < 0.0015, np.ones((3, 3, 5), bool))
    fine = np.repeat(np.repeat(coarse, factor, 1), factor, 2)
    return (fine * rng.random(fine.shape)).astype(np.float32)


def _taking_turns(queue, projs: dict, sup: np.ndarray, repeats: int) -> tuple[dict, dict]:
    """Forward + back (on the support ``sup``) of each projector of ``projs``, taking
    turns ``repeats`` times: the median seconds and the last outputs per key."""
    times: dict = {key: [] for key in projs}
    outs: dict = {}
    for _ in range(repeats):
        for key, p in projs.items():
            vol, img, out = p.volume_to_device(sup), p.empty_image(), p.empty_volume()
            img.fill(1.0)
            t0 = time.perf_counter()
            image = p.forward_device(vol)
            p.back_device(img, out=out, support=vol)
            queue.finish()
            times[key].append(time.perf_counter() - t0)
            outs[key] = (image, out)
    return {key: float(np.median(t)) for key, t in times.items()}, outs


def scratch_sizes(queue, repeats: int, sizes_mib=(32, 256)) -> None:
    """Forward + back on the paper's 3 x 3 sub-voxels (a sparse support, 6.5 % of the
    grid, as a pair's fine iterations see it) for scratch buffers of each size, the
    projectors taking turns; medians of ``repeats``."""
    cam, grid = paper_optics((289, 193))
    projs = {mib: Projector(cam, grid, queue, scratch_bytes=mib * 2**20).refined(3)
             for mib in sizes_mib}
    sup = _sparse_support(grid)
    medians, _ = _taking_turns(queue, projs, sup, repeats)
    fine = next(iter(projs.values())).grid
    print(f"\nscratch size, paper grid on 3 x 3 sub-voxels {fine.shape}, support "
          f"{(sup > 0).mean():.1%}: forward + back, medians of {repeats}")
    base = medians[sizes_mib[0]]
    for mib, p in projs.items():
        t = medians[mib]
        print(f"  {mib:5d} MiB: {len(p.plan.columns)} column chunk(s), {p.plan.zchunk:3d} "
              f"depths per chunk: {t:.3f} s ({t / base:.2f}x the {sizes_mib[0]} MiB)")


def vector_widths(queue, repeats: int) -> None:
    """Forward + back on the paper's 3 x 3 sub-voxels (the support of
    :func:`scratch_sizes`) with the row kernels at vector widths 8 and 16 (the default on
    a CPU whose native float vectors hold 16, ``cpu_vector_width``), taking turns;
    medians of ``repeats``, and whether both give the same bits."""
    if not is_cpu(queue.device):
        print("\nvector widths: the row kernels' widths are a CPU's (this device runs 1)")
        return
    cam, grid = paper_optics((289, 193))
    projs = {vw: Projector(cam, grid, queue, vector_width=vw).refined(3) for vw in (8, 16)}
    sup = _sparse_support(grid)
    medians, outs = _taking_turns(queue, projs, sup, repeats)
    host = {vw: (image.get(), projs[vw].volume_to_host(back))
            for vw, (image, back) in outs.items()}
    same = all(np.array_equal(a, b) for a, b in zip(host[8], host[16], strict=True))
    print(f"\nvector width of the row kernels (this device's default: "
          f"{cpu_vector_width(queue.device)}), paper grid on 3 x 3 sub-voxels, support "
          f"{(sup > 0).mean():.1%}: forward + back, medians of {repeats}")
    for vw, t in medians.items():
        print(f"  width {vw:2d}: {t:.3f} s ({t / medians[8]:.2f}x width 8)")
    print(f"  the same image and back projection at both widths, bit for bit: {same}")


def main() -> None:
    parser = script_parser(__doc__, {"paper": None, "direct": None,
                                     "rotated": "skip the rotated-array (general path) figure",
                                     "reconstruction": "skip the rotated array's "
                                                       "reconstruction times",
                                     "stored": "skip the stored-matrix (CSR) comparison",
                                     "scratch": "skip the scratch-size comparison",
                                     "widths": "skip the row kernels' vector widths",
                                     "small": "skip the per-call cost of small problems"})
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--paper-repeats", type=int, default=3)
    args = parser.parse_args()
    queue = get_queue()
    info = device_info(queue)
    print(f"device: {info.name} ({info.platform}), {info.compute_units} compute units; "
          f"load average at start {os.getloadavg()[0]:.2f} (other processes share the CPU)")
    if not args.skip_stored:
        stored_comparison(queue, args.repeats, not args.skip_direct)
    if not args.skip_small:
        small_calls(queue, args.repeats)
    if not args.skip_paper:
        roofline(queue, args.repeats, paper_experiment(queue, args.paper_repeats))
    if not args.skip_rotated:
        rotated_array(queue, args.paper_repeats)
    if not args.skip_reconstruction:
        rotated_reconstruction(queue)
    if not args.skip_scratch:
        scratch_sizes(queue, args.paper_repeats)
    if not args.skip_widths:
        vector_widths(queue, args.paper_repeats)
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
