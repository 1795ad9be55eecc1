"""Built-in examples that run end to end and write files a user can look at."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..io.files import atomic_path, write_particles, write_tiff
from ..opencl.device import DeviceLike
from ..particles import particles_per_microlens, random_particles
from ..simulate import simulate_image


def save_preview_png(path: str | Path, image: np.ndarray, percentile: float = 99.9) -> None:
    """Save an 8-bit PNG of a raw image, contrast-stretched, atomically."""
    import imageio.v3 as iio

    img = np.asarray(image, dtype=np.float64)
    top = np.percentile(img, percentile) or img.max() or 1.0
    png = (np.clip(img / top, 0, 1) ** 0.5 * 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, png, extension=".png")


def particle_demo(out_dir: str | Path, count: int = 200, seed: int = 0,
                  queue: DeviceLike = None) -> Iterator[str]:
    """Simulate the paper's synthetic camera imaging particles in a 5 mm cube.

    Writes ``camera.toml``, ``raw.tif`` (16-bit), ``raw_preview.png`` and
    ``particles.csv`` (the truth) into ``out_dir``; yields progress lines.
    """
    out = Path(out_dir)
    cam = Camera.synthetic_850()
    box = ((-2.5, 2.5), (-2.5, 2.5), (-2.5, 2.5))
    positions, intensities = random_particles(box, count=count, seed=seed,
                                              intensity=(2e4, 4e4))
    yield (f"camera: {cam.describe()}\nparticles: {count} in a 5 mm cube "
           f"({particles_per_microlens(count, cam):.3f} per microlens)")
    image = simulate_image(cam, positions, intensities, rays_per_particle=20000, seed=seed,
                           blur_px=0.5, background=20.0, photon_noise=True, read_noise=3.0,
                           bit_depth=16, queue=queue)
    cam.to_toml(out / "camera.toml")
    write_tiff(out / "raw.tif", image)
    write_particles(out / "particles.csv", positions, intensities)
    save_preview_png(out / "raw_preview.png", image)
    yield f"wrote {out}/raw.tif, raw_preview.png, particles.csv and camera.toml"
