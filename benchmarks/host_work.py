"""The host work issue 46 moved to the device or made cheaper, each against the code it
replaced on the same data in the same process: medians of repeated runs and the largest
difference of the results.

    python benchmarks/host_work.py [--repeats 5] [--particles 2800] [--pairs 4]

Data of the paper's size: a 150 x 200 x 286 voxel volume of 6,000 Gaussian particles
(sigma 1.5 voxels) on a weak noise floor, and a 4914 x 3282 px float
image (a dark level of 20 counts with 3 counts of noise, 3 % of the pixels lit).

* the deformation's cubic B-spline prefilter: ``DeviceDeformer.prepare`` (padded on the
  host, uploaded, filtered on the device, where the deformer keeps it) against SciPy's
  ``spline_filter`` of the padded volume (``plenocl.piv.interpolate.prepare``, the path
  before, whose result was then uploaded too);
* the particles' tube sums along their lines of sight at the paper's optics:
  ``DeviceTubeSums`` against ``host_tube_sums`` (SciPy's ``map_coordinates``);
* the image's median and noise (``median_and_noise``: the bracketed selection) against
  NumPy's two medians;
* the coarse support's dilation by the 3 x 3 x 3 box: ``schedule.box_dilated`` (in-place
  ORs of shifted views, 2026-11-30) against the separable maxima it replaced and SciPy's
  ``binary_dilation``;
* a background removal in float32 (``subtract_background``: the float32 result of
  the float64 difference written in place, 2026-11-30; the image fit's until
  2026-12-01, which now reads ``scaled_background_free``'s image, the reconstruction's)
  against the clip and cast it replaced;
* the uncertainty's correlated-sum factors of the volume against itself moved a voxel
  (32-voxel windows, ``DeviceSums.correlated_factors``, ``kernels/correlated.cl``,
  2026-11-30) against the host's ``direct.correlated_factors``;
* the lit microlenses of a 16 MP image (``projection.lenses.lit_lenses``: lit pixels
  counted along rows, each lens's rows looked up) against the summed-area table it
  replaced, and on the device (``kernels/lenses.cl``, from the image the solver uploads
  anyway, 2026-11-30) against the row counts.

Measured (2 CPU cores, PoCL, 2026-11-28, medians of 5, with CI's install beside it):
prefilter 0.240 s against 0.196 s plus the old path's upload (a separate run of the two
with the upload in both: 0.234 against 0.254 s on PoCL, 0.264 against 0.259 s on
Intel's runtime: a wash on a CPU, the host's part 0.03 s instead of 0.2 s), within
8.5e-7 of the peak; tube sums 0.053 against 0.395 s (7.5x), within 2.1e-6 of the
largest sum; median and noise 0.177 against 0.547 s (3.1x), exactly NumPy's; dilation
0.085 against 0.208 s (2.4x), the same mask. 2026-11-30 (Intel's runtime, medians of 5 and
of 3): dilation by shifted ORs 0.011 against 0.106 s (maxima) and 0.240 s
(binary_dilation); background removal 0.052 against 0.135 s, the same bits; lit lenses on
the device 0.004 against 0.135-0.184 s; correlated-sum factors on the device 0.60 against
1.55 s (PoCL 0.64 against 1.54 s), 7.4e-4 apart, the host's float32 sums being the farther
from a float64 computation of the same factors (7.4e-4 against the device's 1.3e-7).

* the blind zone's depth interpolation of a field of the paper pair's 11 x 24 x 40 windows
  (40 % missing): ``refinement.depth_interpolation`` (every column at once, 2026-11-30)
  against ``numpy.interp`` column by column (``reference.refinement``, the code before):
  0.001 against 0.043 s (PoCL machine, medians of 3, 2026-11-30), the same bits.
* the image fit's posterior covariances, one Gauss-Newton step's of ``--particles`` fits
  in the fit's chunks of 128 (``imagefit.posterior_covariance``: each normal matrix
  scaled to a unit diagonal and inverted, 2026-12-01) against the pseudo-inverse it
  replaced, on matrices of the fits' scales (the axes' roots 490, 490, 29 and 0.0026:
  mm and counts); the difference relative to each block's largest element: 0.003
  against 0.009 s (PoCL machine, medians of 5, 2026-12-01), 7.8e-14 apart.
* a camera's uint16 frame's median and noise counted on its integers
  (``rawimage.counted``, 2026-12-01) against the same histogram of its float64 copy
  (the reconstruction's and the fit's path before; the copy itself is made either way,
  the checked image and the fit's data, so it is not timed): 0.086 against 0.147 s
  (PoCL machine, medians of 5, 2026-12-01), the same values; and the reconstruction's
  whole host preparation of that frame (``prepare_on_host``: checks, exposure, median,
  noise, scaling; the exposure check on the counts too) against the same frame given
  as float64, the path the counts took before: 0.234 against 0.311 s (the same day and
  machine, load average 1.9), the same image.
* the image fit's kept rows buffer grown with headroom (``fitsums.KEPT_HEADROOM``, 1.25,
  2026-12-01) against grown to the exact size (1.0, the code before), which the rows
  outgrew a little at most Gauss-Newton steps and were made anew: the particle stage of
  a 116 x 78 pair at the paper's optics (``paper_pair.py --lenses 116 78``'s scene),
  ``--pairs`` pairs each way, taking turns (the pair's fit builds its buffers afresh, as
  every pair of a batch does); the largest difference of the pair's vectors.
  Measured (PoCL machine, 2026-12-01): 1.127 against 1.232 s (medians of 5 each, load
  average 1.3-2.0), 1.034 against 1.234 s in a second run of 6 each; with other work
  beside it (load average 2.3) 1.100 against 1.018 s: a gain of about a tenth, within the
  stage's scatter under load; the same vectors to the bit.
* a particle's peaks merged along its line of sight (``peaks.merge_along_lines``:
  the k-d tree's pairs within the cylinder's enclosing ball, the greedy loop on Python
  lists over the peaks that reach another, the centres by ``bincount``, 2026-12-04)
  against its plain twin (``reference.peaks``, one peak's test against every other at a
  time), on ``--particles`` particles of the paper's grid seen as ridges of two or three
  peaks along their lines (6,160 peaks), and against the code it replaced
  (``ball_query_merge``: a ball query per peak of the larger half-axis, which missed
  peaks in the cylinder's rims, and NumPy calls per peak in the loop). Measured (Intel's
  runtime machine, 2026-12-04, medians of 5): 0.008 against 0.812 s (plain) and 0.043 s
  (before), the same peaks kept by all three and within 1.1e-14 mm: on these peaks no
  rim was missed (the test's denser clouds show it, tests/test_sightlines.py).
* one fit step's normal equations of ``--particles`` particles turned into their
  line-of-sight frames (``imagefit.in_sight_frames``: batched matrix products,
  2026-12-04) against the three-operand ``einsum`` it replaced: 0.001 against 0.005 s
  (8.7x, the same day and machine), 3.5e-16 of the largest element apart.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import pyopencl.array as cl_array  # noqa: E402
from scipy import ndimage  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from plenocl import get_queue  # noqa: E402
from plenocl.bench.accuracy_section import UNIFORM, budget_scene, paper_optics  # noqa: E402
from plenocl.bench.clprofile import OpenCLProfile  # noqa: E402
from plenocl.bench.scripts import script_parser  # noqa: E402
from plenocl.bench.timing import timed  # noqa: E402
from plenocl.metrics import render_particles  # noqa: E402
from plenocl.opencl.program import KernelSet  # noqa: E402
from plenocl.optics.rawimage import median_and_noise, subtract_background  # noqa: E402
from plenocl.optics.sightline import line_of_sight, sight_frames  # noqa: E402
from plenocl.peaks import merge_along_lines  # noqa: E402
from plenocl.pipeline import process_pair  # noqa: E402
from plenocl.piv import fitsums  # noqa: E402
from plenocl.piv.correlation import window_grid  # noqa: E402
from plenocl.piv.deformation import DeviceDeformer  # noqa: E402
from plenocl.piv.devicesums import DeviceSums  # noqa: E402
from plenocl.piv.direct import (  # noqa: E402
    correlate_direct,
    correlated_factors,
    correlation_uncertainty,
    fitted_windows,
)
from plenocl.piv.fitsums import HOST_CHUNK  # noqa: E402
from plenocl.piv.imagefit import (  # noqa: E402
    chunk_slices,
    in_sight_frames,
    posterior_covariance,
)
from plenocl.piv.interpolate import prepare  # noqa: E402
from plenocl.piv.refinement import SIGHT_ACROSS, SightLines, depth_interpolation  # noqa: E402
from plenocl.piv.tube import DeviceTubeSums, host_tube_sums  # noqa: E402
from plenocl.projection.lenses import lit_lenses, lit_lenses_on_device  # noqa: E402
from plenocl.projection.projector import Projector  # noqa: E402
from plenocl.reconstruction import ReconstructionSettings, prepare_on_host  # noqa: E402
from plenocl.reconstruction.schedule import box_dilated  # noqa: E402
from plenocl.reference.peaks import merge_along_lines_reference  # noqa: E402
from plenocl.reference.refinement import depth_interpolation_reference  # noqa: E402


def paper_volume(grid, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A particle volume of the paper's grid and its particles' positions (mm)."""
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(*grid.x, count), rng.uniform(*grid.y, count),
                           rng.uniform(*grid.z, count)])
    vol = render_particles(grid, pos, np.full(count, 100.0), sigma_vox=1.5)
    return (vol + rng.random(vol.shape, np.float32) * 0.01).astype(np.float32), pos


def paper_image(seed: int) -> np.ndarray:
    """A 16 MP float raw image: a dark level with noise and 3 % lit pixels."""
    rng = np.random.default_rng(seed)
    img = 20.0 + rng.normal(0.0, 3.0, (3282, 4914))
    lit = rng.random(img.shape) < 0.03
    img[lit] += rng.exponential(500.0, int(lit.sum()))
    return img


#: The paper camera's lens patch half-width (pixels; ``Projector.lens_reach``).
LENS_REACH = 11


def summed_area_lit_lenses(image: np.ndarray, centres: np.ndarray, reach: int,
                           threshold: float) -> np.ndarray:
    """The lit lenses as ``lit_lenses`` found them before 2026-11-29 (late night): a
    summed-area table of the lit pixels, four corners per lens."""
    lit_px = image > threshold
    h, w = lit_px.shape
    table = np.zeros((h + 1, w + 1), np.int32)
    np.cumsum(lit_px, axis=1, dtype=np.int32, out=table[1:, 1:])
    np.cumsum(table[1:, 1:], axis=0, out=table[1:, 1:])
    c = np.asarray(centres, np.int64)
    x0, x1 = np.clip(c[:, 0] - reach, 0, w), np.clip(c[:, 0] + reach + 1, 0, w)
    y0, y1 = np.clip(c[:, 1] - reach, 0, h), np.clip(c[:, 1] + reach + 1, 0, h)
    return (table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]) > 0


def fit_normals(count: int, seed: int) -> np.ndarray:
    """Normal matrices ``(count, 4, 4)`` of the image fit's scales: a Jacobian's columns
    over (x, y, z mm, intensity) of the roots of the paper pair's fits' diagonals."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(count, 60, 4)) * np.array([490.0, 490.0, 29.0, 0.0026]) / 60**0.5
    jac[:, :, 3] += 0.4 * jac[:, :, 2] * 0.0026 / 29.0  # depth and intensity correlated
    return np.einsum("nki,nkj->nij", jac, jac)


def pseudo_inverse_covariance(normal: np.ndarray) -> np.ndarray:
    """The posterior covariance as ``imagefit.posterior_covariance`` made it before
    2026-12-01: the pseudo-inverse's position block, made symmetric."""
    cov = np.linalg.pinv(normal)[:, :3, :3]
    return (cov + np.swapaxes(cov, 1, 2)) / 2


def in_chunks(covariance, normal: np.ndarray) -> np.ndarray:
    """``covariance`` of ``normal`` in the fit's chunks (``HOST_CHUNK`` particles)."""
    return np.concatenate([covariance(normal[part])
                           for part in chunk_slices(len(normal), HOST_CHUNK)])


def headroom_turns(queue, pairs: int) -> tuple[tuple, tuple, float]:
    """The particle stage's seconds of a 116 x 78 pair with the fit's rows grown with
    :data:`plenocl.piv.fitsums.KEPT_HEADROOM` and grown exactly, ``pairs`` each, taking
    turns: ``((vectors, median s), (vectors, median s), largest difference)``."""
    cam, grid = paper_optics((116, 78))
    proj = Projector(cam, grid, queue)
    scene = budget_scene(cam, grid, 0.05, 3, queue, motion=UNIFORM)
    process_pair(scene.raw_a, scene.raw_b, proj)  # kernels built, projectors made
    kept = fitsums.KEPT_HEADROOM
    seconds, fields = {kept: [], 1.0: []}, {}
    try:
        for _ in range(pairs):
            for headroom in seconds:
                fitsums.KEPT_HEADROOM = headroom
                pair = process_pair(scene.raw_a, scene.raw_b, proj)
                seconds[headroom].append(pair.seconds["particles"])
                fields[headroom] = np.stack([pair.piv.u, pair.piv.v, pair.piv.w])
    finally:
        fitsums.KEPT_HEADROOM = kept
    new, old = ((fields[h], float(np.median(seconds[h]))) for h in (kept, 1.0))
    return new, old, float(np.nanmax(np.abs(new[0] - old[0])))


def direct_fit_row(sums: DeviceSums, vol, moved, grid, n: int) -> None:
    """The deformed pass's direct correlation with its uncertainty fitted on the device
    (``DeviceSums.window_fit``, 2026-12-02) against the same device sums brought to the
    host and fitted there (the code before: ``correlate_direct``, ``fit_direct`` and
    ``correlation_uncertainty`` on the host); both volumes on the device, as the chain
    hands them; the bytes each way read back and the largest displacement difference."""
    a, b = (cl_array.to_device(sums.kernels.queue, v) for v in (vol, moved))

    def on_host():
        direct = correlate_direct(a, b, grid, 0.35, sums)
        sigma = correlation_uncertainty(a, b, grid, 0.35, direct, sums)
        return fitted_windows(direct, sigma)

    def on_device():
        return sums.window_fit(a, b, grid, 0.35, uncertainty=True)
    moved_bytes = []
    for way in (on_device, on_host):
        with OpenCLProfile() as prof:
            way()
        moved_bytes.append(sum(c.nbytes for c in prof.calls if c.kind == "d2h") / 1e6)
    new, old = timed(on_device, n), timed(on_host, n)
    row(f"direct fit, {int(np.prod(grid.count))} windows (device / host)", new, old,
        float(np.abs(new[0].displacement - old[0].displacement).max()), "voxel")
    print(f"{'':44s} back to the host {moved_bytes[0]:.2f} MB against {moved_bytes[1]:.2f} MB")


def ball_query_merge(points, values, directions, along: float, across: float):
    """``peaks.merge_along_lines`` as it was until 2026-12-04, the code it replaced: a
    ball query of radius ``max(along, across)`` per peak (which missed the cylinder's
    rims), lists turned into arrays by generators, and NumPy calls for each peak in the
    greedy loop."""
    pts, w = np.asarray(points, float), np.asarray(values, float)
    keep, out = np.ones(len(pts), bool), pts.copy()
    lists = cKDTree(pts).query_ball_point(pts, max(along, across), return_sorted=False)
    counts = np.fromiter((len(n) for n in lists), int, len(lists))
    owner = np.repeat(np.arange(len(pts)), counts)
    other = np.fromiter((j for n in lists for j in n), int, int(counts.sum()))
    d, line = pts[other] - pts[owner], directions[owner]
    t = np.einsum("ij,ij->i", d, line)
    off = np.linalg.norm(d - t[:, None] * line, axis=1)
    ok = (other != owner) & (np.abs(t) <= along) & (off <= across)
    start = np.concatenate([[0], np.cumsum(np.bincount(owner[ok], minlength=len(pts)))])
    reach = other[ok]
    for i in np.argsort(-w, kind="stable"):
        if not keep[i]:
            continue
        near = reach[start[i]:start[i + 1]]
        near = near[keep[near]]
        if len(near):
            group = np.append(near, i)
            weight = w[group, None]
            out[i] = (pts[group] * weight).sum(axis=0) / weight.sum(axis=0)
            keep[near] = False
    return keep, out


def einsum_sight_frames(normal: np.ndarray, rhs: np.ndarray, frames: np.ndarray):
    """``imagefit.in_sight_frames`` as it was until 2026-12-04: three-operand
    ``einsum``."""
    turn = np.zeros((len(frames), 4, 4))
    turn[:, :3, :3] = frames
    turn[:, 3, 3] = 1.0
    return (np.einsum("nji,njk,nkl->nil", turn, normal, turn),
            np.einsum("nji,nj->ni", turn, rhs))


def frame_turns_row(cam, pos: np.ndarray, repeats: int) -> None:
    """One fit step's normal equations of the particles at ``pos`` (mm) turned into
    their line-of-sight frames: batched products against the einsum they replaced."""
    rng = np.random.default_rng(5)
    jac = rng.normal(size=(len(pos), 6, 4))
    normal, rhs = np.swapaxes(jac, 1, 2) @ jac, rng.normal(size=(len(pos), 4))
    frames = sight_frames(line_of_sight(cam, pos))
    new = timed(lambda: in_sight_frames(normal, rhs, frames), repeats)
    old = timed(lambda: einsum_sight_frames(normal, rhs, frames), repeats)
    row(f"frame turns, {len(pos)} particles (matmul / einsum)", new, old,
        float(np.abs(new[0][0] - old[0][0]).max() / np.abs(old[0][0]).max()),
        "of the largest")


def merge_row(cam, grid, pos: np.ndarray, repeats: int) -> None:
    """Each particle at ``pos`` (mm) seen as a reconstruction's ridge of peaks along its
    line of sight (two 0.6 mm apart, a fifth with a third 0.7 mm behind, 0.03 mm
    scatter): the merge along the lines (:meth:`SightLines.merge`'s reach) against its
    plain twin and against the code it replaced."""
    rng = np.random.default_rng(4)
    lines = line_of_sight(cam, pos)
    third = len(pos) // 5
    pts = np.concatenate([pos, pos + 0.6 * lines, pos[:third] - 0.7 * lines[:third]])
    pts += rng.normal(0.0, 0.03, pts.shape)
    values = rng.uniform(0.1, 1.0, len(pts))
    args = (pts, values, line_of_sight(cam, pts), cam.depth_resolution_mm,
            SIGHT_ACROSS * float(np.mean(grid.spacing[1:])))
    new = timed(lambda: merge_along_lines(*args), repeats)
    old = timed(lambda: merge_along_lines_reference(*args), repeats)
    same = np.array_equal(new[0][0], old[0][0])
    row(f"merge along lines, {len(pts)} peaks (tree / plain)", new, old,
        float(np.abs(new[0][1] - old[0][1])[new[0][0]].max()) if same else np.inf, "mm")
    old = timed(lambda: ball_query_merge(*args), repeats)
    same = np.array_equal(new[0][0], old[0][0])
    row(f"merge along lines, {len(pts)} peaks (tree / before)", new, old,
        float(np.abs(new[0][1] - old[0][1])[new[0][0]].max()) if same else np.inf, "mm")


def row(label: str, new: tuple, old: tuple, difference: float, unit: str) -> None:
    """One comparison: both medians, the speed-up and the largest difference."""
    print(f"{label:44s} {new[1]:7.3f} s against {old[1]:7.3f} s ({old[1] / new[1]:4.1f}x); "
          f"largest difference {difference:.1e} {unit}", flush=True)


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--particles", type=int, default=2800)
    parser.add_argument("--pairs", type=int, default=4,
                        help="116 x 78 pairs each way for the fit's kept rows")
    args = parser.parse_args()
    queue = get_queue()
    cam, grid = paper_optics((289, 193))
    print(f"device: {queue.device.name.strip()}; load average {os.getloadavg()[0]:.2f}; "
          f"medians of {args.repeats}")
    vol, pos = paper_volume(grid, 6000, seed=1)
    n = args.repeats

    deformer = DeviceDeformer(queue, 3)
    coeffs = deformer.prepare(vol).get()  # the deformer keeps them on the device

    def on_device():
        deformer.prepare(vol)
        queue.finish()
    new = (coeffs, timed(on_device, n)[1])
    old = timed(lambda: prepare(vol, 3), n)
    peak = float(np.abs(old[0]).max())
    row("B-spline prefilter (device / SciPy)", new, old,
        float(np.abs(new[0] - old[0]).max()) / peak, "of the peak")

    sight = SightLines.of(cam, grid)
    peaks = grid.to_index(pos[:args.particles])
    mm = grid.from_index(peaks)
    frames = grid.index_jacobian() @ sight_frames(line_of_sight(cam, mm))
    centre, local = grid.to_index(mm), sight.tube_offsets()
    sums = DeviceTubeSums(queue)
    sums(vol, centre, frames, local)
    new = timed(lambda: sums(vol, centre, frames, local), n)
    old = timed(lambda: host_tube_sums(vol, centre, frames, local), n)
    row(f"tube sums, {len(peaks)} particles (device / SciPy)", new, old,
        float(np.abs(new[0] - old[0]).max() / np.abs(old[0]).max()), "of the largest sum")

    merge_row(cam, grid, pos[:args.particles], n)
    frame_turns_row(cam, pos[:args.particles], n)

    img = paper_image(seed=2)

    def numpy_median_and_noise():
        med = float(np.median(img))
        return med, 1.4826 * float(np.median(np.abs(img - med)))
    new = timed(lambda: median_and_noise(img), n)
    old = timed(numpy_median_and_noise, n)
    row("median and noise, 16 MP (bracketed / NumPy)", new, old,
        float(np.max(np.abs(np.subtract(new[0], old[0])))), "counts")
    counts = np.clip(np.rint(img), 0, 65535).astype(np.uint16)  # a camera's frame
    as_float = counts.astype(np.float64)  # made anyway: the checked image, the fit's data
    new = timed(lambda: median_and_noise(counts), n)
    old = timed(lambda: median_and_noise(as_float), n)
    row("median and noise, 16 MP uint16 (as counts / float)", new, old,
        float(np.max(np.abs(np.subtract(new[0], old[0])))), "counts")
    cam16 = paper_optics((289, 193))[0]
    settings = ReconstructionSettings()
    new = timed(lambda: prepare_on_host(counts, cam16, settings), n)
    old = timed(lambda: prepare_on_host(as_float, cam16, settings), n)
    row("host preparation, 16 MP uint16 (counts / float)", new, old,
        float(np.max(np.abs(new[0].image - old[0].image))), "of the scale")

    mask = vol > 0.01 * vol.max()
    box = np.ones((3, 3, 3), bool)
    new = timed(lambda: box_dilated(mask), n)
    old = timed(lambda: ndimage.maximum_filter(mask, size=3, mode="constant", cval=0), n)
    row("support dilation (shifted ORs / maxima)", new, old,
        float(np.count_nonzero(new[0] != old[0])), "voxels")
    old = timed(lambda: ndimage.binary_dilation(mask, box), n)
    row("support dilation (shifted ORs / binary_dilation)", new, old,
        float(np.count_nonzero(new[0] != old[0])), "voxels")

    new = timed(lambda: subtract_background(img, (20.0, 3.0)), n)
    old = timed(lambda: (np.clip(img - 20.0, 0, None).astype(np.float32), 3.0), n)
    row("background removal in float32, 16 MP", new, old,
        float(np.max(np.abs(new[0][0] - old[0][0]))), "counts")

    moved = np.roll(vol, 1, axis=2)
    grid = window_grid(vol.shape, (32, 32, 32), 0.75)
    sums = DeviceSums(queue)
    new = timed(lambda: sums.correlated_factors(vol, moved, grid, 0.35), n)
    old = timed(lambda: correlated_factors(vol, moved, grid, 0.35), n)
    row("correlated-sum factors (device / host)", new, old,
        float(np.max(np.abs(np.subtract(new[0], old[0])) / np.abs(old[0]))), "relative")

    direct_fit_row(sums, vol, moved, grid, n)

    centres = np.rint(cam.microlens_centers.reshape(-1, 2))
    new = timed(lambda: lit_lenses(img, centres, LENS_REACH, 100.0), n)
    old = timed(lambda: summed_area_lit_lenses(img, centres, LENS_REACH, 100.0), n)
    row("lit lenses, 16 MP (row counts / summed-area)", new, old,
        float(np.count_nonzero(new[0] != old[0])), "lenses")
    kernels = KernelSet(queue, "lenses.cl", ["lit_patches", "pack_flags"])
    on_device = kernels.to_device(img.astype(np.float32))  # the solver's copy, uploaded anyway
    table = kernels.to_device(centres.astype(np.int32))
    new = timed(lambda: lit_lenses_on_device(kernels, on_device, table, LENS_REACH, 100.0), n)
    old = timed(lambda: lit_lenses(img, centres, LENS_REACH, 100.0), n)
    row("lit lenses, 16 MP (device / row counts)", new, old,
        float(np.count_nonzero(new[0] != old[0])), "lenses")
    rng = np.random.default_rng(3)  # the paper pair's last field: 11 x 24 x 40 windows
    w = np.where(rng.random((11, 24, 40)) < 0.4, np.nan, rng.normal(0, 1, (11, 24, 40)))
    sigma, z = rng.uniform(0, 0.2, w.shape), np.linspace(-9.0, 9.0, 11)
    new = timed(lambda: depth_interpolation(w, sigma, z), n)
    old = timed(lambda: depth_interpolation_reference(w, sigma, z), n)
    row("depth interpolation (all columns / each)", new, old,
        max(float(np.nanmax(np.abs(a - b))) for a, b in zip(new[0], old[0])), "voxels")
    normal = fit_normals(args.particles, 4)
    new = timed(lambda: in_chunks(posterior_covariance, normal), n)
    old = timed(lambda: in_chunks(pseudo_inverse_covariance, normal), n)
    largest = np.abs(old[0]).max(axis=(1, 2), keepdims=True)
    row(f"fit covariances, {len(normal)} (scaled inverse / pinv)", new, old,
        float(np.max(np.abs(new[0] - old[0]) / largest)), "relative")
    new, old, difference = headroom_turns(queue, args.pairs)
    row("fit's particle stage, 116 x 78 (headroom / exact)", new, old, difference, "voxels")
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
