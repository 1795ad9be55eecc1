"""Particle tracking through time (docs/design.md §7.3): particles of consecutive frames
linked into tracks (:mod:`.linking`), each track smoothed by local polynomial fits
(:mod:`.smoothing`), the result held by :class:`Tracks` (:mod:`.tracks`).

Plain NumPy and SciPy, no device: the driver that finds each frame's particles
(reconstruction and the fit to the raw image) is :func:`plenocl.pipeline.track`.
"""

from .linking import link, mutual_nearest
from .smoothing import TrackFit, smooth
from .tracks import Tracks

__all__ = ["TrackFit", "Tracks", "link", "mutual_nearest", "smooth"]
