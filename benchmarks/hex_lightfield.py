"""The light field and refocusing of a hexagonal microlens array against a rectangular one
of the same pitch, on the 850 px synthetic camera (issue 29; docs/design.md §4): single
ray-traced particles refocused (the depth of the focal stack's brightest plane, the
position at that depth against ``X'/α``) and the light field's build and focal-stack
times, medians of repeated runs, both cameras in the same run.

    python benchmarks/hex_lightfield.py [--particles 12] [--repeats 3]
"""

from __future__ import annotations

import numpy as np

from plenocl import Camera, get_queue
from plenocl.bench.core import hexagonal_cut
from plenocl.bench.scripts import script_parser
from plenocl.bench.timing import median_time
from plenocl.lightfield import LightField
from plenocl.opencl.device import device_info
from plenocl.simulate import simulate_image

ZS = np.round(np.arange(-3.0, 3.001, 0.1), 2)


def refocus_errors(cam: Camera, point: np.ndarray, queue) -> tuple[float, float]:
    """Depth error (mm) of the focal stack's brightest plane, and lateral error (mm) of the
    particle's centroid there against ``X'/α``, for one particle."""
    raw = simulate_image(cam, point[None], 1e5, 20000, seed=1, queue=queue)
    lf = LightField(raw, cam, queue=queue)
    stack = lf.focal_stack(ZS, supersample=2)
    best = int(stack.reshape(len(ZS), -1).max(1).argmax())
    img = stack[best]
    w = np.clip(img - 0.2 * img.max(), 0, None)
    found = (w[..., None] * lf.output_positions_mm(supersample=2)).sum((0, 1)) / w.sum()
    expected = cam.image_points(point[None])[0, :2] / cam.alpha(point[2])
    return ZS[best] - point[2], float(np.hypot(*(found - expected)))


def row(cam: Camera, points: np.ndarray, queue, repeats: int) -> str:
    """One camera's line: RMS depth and lateral errors over the particles, build and
    focal-stack times."""
    err = np.array([refocus_errors(cam, p, queue) for p in points])
    raw = simulate_image(cam, points, 1e4, 2000, seed=1, queue=queue)
    t_build = median_time(lambda: LightField(raw, cam, queue=queue), repeats)
    lf = LightField(raw, cam, queue=queue)
    t_stack = median_time(lambda: lf.focal_stack(np.linspace(-3, 3, 9)), repeats)
    depth, lateral = np.sqrt(np.mean(err**2, axis=0))
    lenses = f"{cam.ml_count[0]}x{cam.ml_count[1]}"
    return (f"{cam.ml_layout:12s} {lenses:>8s} {depth:12.3f} {lateral:14.4f} "
            f"{lateral / cam.ml_pitch_mm:8.3f} {t_build:8.3f} {t_stack:10.4f}")


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--particles", type=int, default=12)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    queue = get_queue()
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-2.0, 2.0, (args.particles, 2)),
                              rng.uniform(-2.5, 2.5, args.particles)])
    print(f"device: {device_info(queue).name}; {args.particles} single particles, focal "
          f"stack of {len(ZS)} planes (0.1 mm), supersample 2; times: medians of "
          f"{args.repeats}")
    print(f"{'array':12s} {'lenses':>8s} {'depth RMS mm':>12s} {'lateral RMS mm':>14s} "
          f"{'(pitch)':>8s} {'build s':>8s} {'9 planes s':>10s}")
    for base in (Camera.synthetic_850(), hexagonal_cut(Camera.synthetic_850())):
        print(row(base.with_centers(base.ideal_microlens_centers()), points, queue,
                  args.repeats))


if __name__ == "__main__":
    main()
