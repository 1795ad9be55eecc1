"""3-D PIV: multi-pass FFT cross-correlation with window deformation (docs/design.md §7).

- :mod:`.correlation`: windows, batched FFT correlation, sub-voxel peak fit;
- :mod:`.interpolate`: predictor resampling, B-spline volume sampling (the host reference);
- :mod:`.deformation`: deforming volumes on the host or an OpenCL device (``deform.cl``);
- :mod:`.direct`, :mod:`.devicesums`: the deformed passes' direct correlation, its window
  sums on the host or the deformer's device (``windowsums.cl``);
- :mod:`.validation`: outlier detection and replacement;
- :mod:`.settings`: :class:`PIVSettings` (every option of :func:`piv3d`, checked once);
- :mod:`.multipass`: :func:`piv3d`; its result :class:`plenocl.vectorfield.PIVResult`
  (velocities, gradients, the arrays written to files) lives in the model layer;
- :mod:`.refinement`: the refinement by the volumes' matched particle pairs;
- :mod:`.pairoutliers`: the pairs that disagree with their neighbours, left out of it;
- :mod:`.imagefit`: those particles fitted to the raw images (the camera's rays:
  :mod:`plenocl.optics.raybundle`).
"""

from ..vectorfield import (
    PIVResult,
    displacement_to_velocity,
    q_criterion,
    velocity_gradient,
    vorticity,
    voxel_size,
)
from .multipass import (
    DEFAULT_WINDOWS,
    MIN_PARTICLES_PER_WINDOW,
    auto_windows,
    count_particles,
    piv3d,
)
from .settings import PIVSettings

__all__ = ["DEFAULT_WINDOWS", "MIN_PARTICLES_PER_WINDOW", "PIVResult", "PIVSettings",
           "auto_windows", "count_particles", "displacement_to_velocity", "piv3d",
           "q_criterion", "velocity_gradient", "voxel_size", "vorticity"]
