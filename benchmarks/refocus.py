"""Refocusing throughput: the OpenCL kernel against a straightforward SciPy shift-and-add
(``scipy.ndimage.map_coordinates``, the same quadratic B-spline weights: ``order=2``
without prefilter, one call per view) and the NumPy reference, on the same light field
in the same run; medians of repeated runs. A tap is one view's sample of one lens (9 per
view and output pixel).

    python benchmarks/refocus.py [--camera synthetic|paper] [--planes 9] [--supersample 1]
"""

from __future__ import annotations

import numpy as np

from plenocl import Camera, get_queue
from plenocl.bench.lightfield_section import scipy_shift_and_add
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.lightfield import LightField
from plenocl.opencl.device import device_info
from plenocl.reference.refocus import refocus_views
from plenocl.simulate import simulate_image


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--camera", choices=["synthetic", "paper"], default="synthetic")
    parser.add_argument("--planes", type=int, default=9, help="depths in the focal stack")
    parser.add_argument("--supersample", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    cam = Camera.synthetic_850() if args.camera == "synthetic" else Camera.paper_16mp()
    cam = cam.with_centers(cam.ideal_microlens_centers())
    queue = get_queue()
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-2, 2, (200, 2)), rng.uniform(-3, 3, 200)])
    raw = simulate_image(cam, pts, 1e4, 2000, seed=1, queue=queue)
    t_build = median_time(lambda: LightField(raw, cam, queue=queue), max(1, args.repeats // 2))
    lf = LightField(raw, cam, queue=queue)
    z = np.linspace(-3, 3, args.planes)
    s = args.supersample
    shifts = lf.shifts(cam.alpha(z))
    views = lf.views.reshape(-1, *lf.shape)
    n_views = int(np.isfinite(views).any((1, 2)).sum())
    t_dev = median_time(lambda: lf.focal_stack(z, supersample=s), args.repeats)
    t_scipy = median_time(lambda: scipy_shift_and_add(views, shifts, s), args.repeats)
    t_ref = median_time(lambda: refocus_views(views, shifts[:1], s), 1) * args.planes
    a, b = lf.focal_stack(z, supersample=s), scipy_shift_and_add(views, shifts, s)
    out_px = lf.shape[0] * lf.shape[1] * s * s
    info = device_info(queue)
    print(f"device: {info.name} ({info.platform})")
    print(f"camera: {cam.pixels[0]} x {cam.pixels[1]} px, {cam.ml_count[0]} x {cam.ml_count[1]} "
          f"lenses; light field {len(lf.v)} x {len(lf.u)} (u, v) samples ({n_views} inside "
          f"the aperture); focal stack of {args.planes} planes, {out_px} px each "
          f"(supersample {s})")
    print(f"light-field resampling (host, once per image): {t_build:.4f} s")
    print(f"{'refocus path':34s} {'median s':>10s} {'planes/s':>10s} {'Gtap/s':>8s}")
    taps = args.planes * out_px * n_views * 9 / 1e9
    for name, t in (("OpenCL kernel", t_dev), ("SciPy shift-and-add (ndimage)", t_scipy),
                    ("NumPy reference (1 plane, scaled)", t_ref)):
        print(f"{name:34s} {t:10.4f} {args.planes / t:10.2f} {taps / t:8.3f}")
    print(f"kernel speed-up over SciPy: {t_scipy / t_dev:.1f}x; max |kernel - SciPy| / max = "
          f"{np.abs(a - b).max() / np.abs(b).max():.2e}")


if __name__ == "__main__":
    main()
