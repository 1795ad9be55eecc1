"""Reconstruction of particle volumes from plenoptic images (docs/design.md §6).

- :mod:`.settings`: :class:`ReconstructionSettings` (every option, validated once; the
  one default of every entry point, coarse-to-fine on sub-voxels) and
  :class:`ReconstructionInfo` (what a run did);
- :mod:`.images`: the raw image's scaling and background (its checks:
  :mod:`plenocl.optics.rawimage`);
- :mod:`.operator`: the contract a projector fulfils for the solver;
- :mod:`.solver`: the device buffers and kernels (:class:`Solver`) and one update per
  method;
- :mod:`.blocks`: MART's view blocks from the lens lattice;
- :mod:`.supersample`: lateral sub-voxels (binning back, spreading a start volume);
- :mod:`.reconstruct`: :func:`reconstruct`, the iterations.
"""

from .blocks import device_view_blocks, view_blocks
from .deviceimage import prepares_on_device
from .images import (
    FLOAT32_LIMIT,
    NOISE_SIGMAS,
    UnusableImageError,
    prepare_on_host,
    preprocess,
    scale_raw_image,
)
from .operator import ProjectionOperator, RefinableOperator
from .reconstruct import reconstruct, run_reconstruction
from .settings import (
    COARSE_ITERATIONS,
    DEFAULTS,
    FINE_DEFAULTS,
    MAX_MART_BLOCKS,
    METHOD,
    METHODS,
    SMOOTH_DEFAULTS,
    SUPERSAMPLE,
    SUPPORT,
    ReconstructionInfo,
    ReconstructionSettings,
)
from .solver import CROP_BELOW, UPDATES, Solver, extent_box, nonzero_box
from .supersample import MAX_SUPERSAMPLE, bin_lateral, spread_lateral

__all__ = ["COARSE_ITERATIONS", "CROP_BELOW", "DEFAULTS", "FINE_DEFAULTS", "FLOAT32_LIMIT",
           "MAX_MART_BLOCKS", "MAX_SUPERSAMPLE", "METHOD", "METHODS", "NOISE_SIGMAS",
           "SMOOTH_DEFAULTS", "SUPERSAMPLE", "SUPPORT", "UPDATES", "UnusableImageError",
           "bin_lateral",
           "prepare_on_host", "prepares_on_device", "preprocess", "spread_lateral",
           "ProjectionOperator", "ReconstructionInfo", "ReconstructionSettings",
           "RefinableOperator", "Solver",
           "device_view_blocks", "extent_box", "nonzero_box", "reconstruct",
           "run_reconstruction", "scale_raw_image", "view_blocks"]
