"""Particle tracking through time (docs/design.md §7.3): particles of consecutive frames
linked into tracks (:mod:`.linking`), each track smoothed by local polynomial fits
(:mod:`.smoothing`) and by a constant-velocity state-space smoother (:mod:`.statespace`)
with its neighbours' velocity as a prior (:mod:`.neighbours`), the result held by
:class:`Tracks` (:mod:`plenocl.ptv.tracks`).

Plain NumPy and SciPy, no device: the driver that finds each frame's particles
(reconstruction and the fit to the raw image) is :func:`plenocl.pipeline.track`.
"""

from .linking import link, mutual_nearest
from .neighbours import neighbour_velocity
from .smoothing import TrackFit, smooth
from .statespace import StateFit, smooth_states
from .tracks import Tracks

__all__ = ["StateFit", "TrackFit", "Tracks", "link", "mutual_nearest", "neighbour_velocity",
           "smooth", "smooth_states"]
