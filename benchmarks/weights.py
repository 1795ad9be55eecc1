"""How true the weighting function is to the camera's images, by depth (issue 47; the
paper's Fig. 8 validation of its weights).

    python benchmarks/weights.py [--depths MM ...] [--rays N] [--blur PX ...]

For a voxel of the paper's synthetic case (850 x 850 px behind 50 x 50 lenses, M = 1,
f/2; cubic voxels of 0.125 mm, the 5 mm cube at 40³, one lens wide) at several depths,
the focal plane among them, and at four places against the lenses (:data:`PLACES`): the
voxel's column of the weight matrix (its footprint,
:meth:`plenocl.Projector.voxel_weights`) against the raw image of
particles spread uniformly through the voxel, ray traced by the simulator (``--rays``
per particle, without blur and with each ``--blur``). Per depth, averaged over the
four places:

- ``corr``: the Pearson correlation of the footprint with the traced image over the
  pixels either lights (1: the weights are the image, to scale);
- ``dark``: the share of the footprint's weight on pixels the traced particles leave
  dark (below 1 % of the traced image's peak): what a geometric-mean update (the paper's
  MART) multiplies towards zero (docs/design.md §6.2);
- ``px``: pixels the footprint touches against pixels the traced image lights.

Rows, in the same run: the paper's weighting function at the projector's default
aperture sampling (the baseline), the same with the voxel integrated over 3 x 3 lateral
sub-voxels (the default reconstruction's grid, docs/design.md §6.4), the aperture sampled
four times as finely (the model's own sampling error), and each of the 3 x 3 sub-voxels
alone against particles spread through it alone (what the default reconstruction's
weights must match); then the same with the lens weights that integrate the voxel's
extent (``Projector(lens_weights="extent")``, issue 47). A weighting true to the
camera would reach ``corr`` near 1 and ``dark`` near 0 at every depth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from plenocl import Camera, Grid, Projector, get_queue, simulate_image  # noqa: E402
from plenocl.opencl.device import device_info  # noqa: E402

#: The paper's synthetic voxel (mm): the 5 mm cube at 40³.
VOXEL_MM = 0.125
#: Where the voxel's centre sits against the lenses (pitches along x and y; the voxel is
#: one pitch wide at M = 1): on a lens's axis, a quarter and half a pitch off it, and at
#: a corner of four lenses.
PLACES = ((0.0, 0.0), (0.25, 0.0), (0.5, 0.0), (0.5, 0.5))
#: The voxel measured in each grid: (iy, ix) of the 8 x 8 slice.
VOXEL = (4, 4)
#: Particles spread through each voxel.
PARTICLES = 64
#: Below this fraction of the traced image's peak a pixel counts as dark.
DARK = 0.01


def depth_grid(z_mm: float, place: tuple[float, float], pitch_mm: float) -> Grid:
    """One slice of 8 x 8 voxels of the paper's size at depth ``z_mm``, shifted so that
    the centre of :data:`VOXEL` sits ``place`` pitches (``pitch_mm`` in object space) off
    a lens's axis."""
    half = 4 * VOXEL_MM
    dx, dy = (p * pitch_mm for p in place)
    return Grid((1, 8, 8), x=(-half + dx, half + dx), y=(-half + dy, half + dy),
                z=(z_mm - VOXEL_MM / 2, z_mm + VOXEL_MM / 2))


def footprint(proj: Projector, factor: int) -> np.ndarray:
    """:data:`VOXEL`'s footprint on the sensor, flat, the sum of its ``factor x factor``
    lateral sub-voxels' (each a ``1/factor²`` share of the voxel)."""
    iy, ix = VOXEL
    fine = proj.refined(factor)
    image = np.zeros(proj.camera.pixels[0] * proj.camera.pixels[1])
    for sy in range(factor):
        for sx in range(factor):
            idx, w = fine.voxel_weights(0, iy * factor + sy, ix * factor + sx)
            np.add.at(image, idx, w / factor**2)
    return image


def voxel_box(grid: Grid, factor: int = 1, sy: int = 0, sx: int = 0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Low corner ``(x, y, z)`` mm and size of :data:`VOXEL` of ``grid``, or of its
    sub-voxel ``(sy, sx)`` of ``factor x factor``."""
    iy, ix = VOXEL
    step = VOXEL_MM / factor
    low = np.array([grid.x[0] + ix * VOXEL_MM + sx * step,
                    grid.y[0] + iy * VOXEL_MM + sy * step, grid.z[0]])
    return low, np.array([step, step, VOXEL_MM])


def traced(camera: Camera, box: tuple[np.ndarray, np.ndarray], rays: int, blur: float,
           seed: int, queue) -> np.ndarray:
    """The raw image (flat) of :data:`PARTICLES` particles spread uniformly through
    ``box`` (low corner, size)."""
    low, size = box
    pos = low + np.random.default_rng(seed).random((PARTICLES, 3)) * size
    return simulate_image(camera, pos, 1e4, rays, seed=seed, blur_px=blur,
                          queue=queue).ravel().astype(np.float64)


def subvoxels_alone(base: Projector, rays: int, blur: float, seed: int
                    ) -> list[tuple[float, float, int, int]]:
    """:func:`agreement` of each of :data:`VOXEL`'s 3 x 3 lateral sub-voxels' footprint
    (the default reconstruction's grid) against particles spread through that
    sub-voxel alone."""
    fine, (iy, ix) = base.refined(3), VOXEL
    out = []
    for sy in range(3):
        for sx in range(3):
            idx, w = fine.voxel_weights(0, 3 * iy + sy, 3 * ix + sx)
            model = np.zeros(base.camera.pixels[0] * base.camera.pixels[1])
            model[idx] = w
            image = traced(base.camera, voxel_box(base.grid, 3, sy, sx), rays, blur,
                           seed * 9 + 3 * sy + sx, base.queue)
            out.append(agreement(model, image))
    return out


def agreement(model: np.ndarray, image: np.ndarray) -> tuple[float, float, int, int]:
    """``(corr, dark, model px, image px)`` of one footprint against one traced image."""
    lit = image > DARK * image.max()
    either = (model > 0) | lit
    corr = float(np.corrcoef(model[either], image[either])[0, 1])
    dark = float(model[~lit].sum() / model.sum())
    return corr, dark, int((model > 0).sum()), int(lit.sum())


def print_row(z: float, label: str, per_blur: list[list[tuple]]) -> None:
    """One table row: the mean ``corr`` and ``dark`` per blur, then the pixel counts."""
    cells = []
    for got in map(np.array, per_blur):
        cells.append(f"{got[:, 0].mean():9.3f}  {got[:, 1].mean():7.3f}")
    sizes = np.array(per_blur[0])[:, 2:].mean(0)
    print(f"{z:6.2f}  {label:28s} {'  '.join(cells)}  {sizes[0]:8.0f} {sizes[1]:9.0f}",
          flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--depths", type=float, nargs="+",
                        default=[-2.0, -1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0, 2.0],
                        help="voxel centres' depths, mm from the focal plane")
    parser.add_argument("--rays", type=int, default=20000, help="rays per particle")
    parser.add_argument("--blur", type=float, nargs="+", default=[1.0],
                        help="particle blurs (px) traced besides the sharp image")
    args = parser.parse_args()
    queue = get_queue()
    camera = Camera.synthetic_850()
    print(f"device: {device_info(queue).name}; {camera.describe()}")
    print(f"voxels of {VOXEL_MM} mm, {len(PLACES)} places across a lens per depth, "
          f"{PARTICLES} particles x {args.rays} rays each; dark: below {DARK:g} of the peak")
    blurs = [0.0, *args.blur]
    rows = (("paper's weights (baseline)", "paper", 1, 1.0),
            ("3 x 3 sub-voxels", "paper", 3, 1.0),
            ("aperture sampled 4x finer", "paper", 1, 4.0),
            ("extent weights", "extent", 1, 1.0),
            ("extent, 3 x 3 sub-voxels", "extent", 3, 1.0))
    head = "  ".join(f"corr {b:g}px  dark {b:g}px" for b in blurs)
    print(f"{'z mm':>6s}  {'weights':28s} {head}  {'model px':>8s} {'traced px':>9s}")
    pitch = camera.ml_pitch_mm / camera.magnification  # a lens's width in object space
    for z in args.depths:
        grids = [depth_grid(z, place, pitch) for place in PLACES]
        bases = {w: [Projector(camera, grid, queue, lens_weights=w) for grid in grids]
                 for w in ("paper", "extent")}
        images = {b: [traced(camera, voxel_box(grid), args.rays, b, k, queue)
                      for k, grid in enumerate(grids)] for b in blurs}
        for label, weights, factor, finer in rows:
            models = [footprint(base.sampled(base.oversample * finer), factor)
                      for base in bases[weights]]
            print_row(z, label, [[agreement(m, i) for m, i in zip(models, images[b])]
                                 for b in blurs])
        for weights, label in (("paper", "a 3 x 3 sub-voxel alone"),
                               ("extent", "extent, a sub-voxel alone")):
            print_row(z, label, [[a for k, base in enumerate(bases[weights])
                                  for a in subvoxels_alone(base, args.rays, b, k)]
                                 for b in blurs])
    return 0


if __name__ == "__main__":
    sys.exit(main())
