"""Simulate a plenoptic raw image of particles in a 5 mm cube (the paper's synthetic
camera) and save it as a 16-bit TIFF, a PNG preview and the particle truth.

    python examples/simulate_particles.py [OUT_DIR] [N_PARTICLES]
"""

from __future__ import annotations

import sys

from plenocl.demo.particle_images import particle_demo


def main(out_dir: str = "plenocl_demo", count: int = 200) -> None:
    """Run the particle demo, printing its progress."""
    for line in particle_demo(out_dir, count=count):
        print(line)


if __name__ == "__main__":
    main(*(sys.argv[1:2] or ["plenocl_demo"]), *(int(a) for a in sys.argv[2:3]))
