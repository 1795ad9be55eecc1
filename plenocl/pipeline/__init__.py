"""The default chain for one image pair (docs/design.md §9): :func:`process_pair`
(``pair.py``), its settings (:class:`PairSettings`, ``settings.py``, the single home of
its defaults) and its two-exposure reconstruction, motion-tracking enhancement
(``mte.py``); two volumes to their refined velocity field (:func:`refined_field`,
``velocity.py``: the one composition of the pair, the ``piv`` command and the demo);
particles tracked through a time-resolved recording (:func:`track`, ``track.py``); a
camera's pose from images of a dot target (:func:`calibrate_pose`) and several
cameras' poses refined from their particle images (:func:`self_calibrate`,
``posecal.py``)."""

from .mte import MTESettings, motion_tracking_enhancement
from .pair import PairResult, correlate_volumes, process_pair
from .posecal import PoseCalibration, SelfCalibration, calibrate_pose, self_calibrate
from .settings import PairSettings
from .track import TrackSettings, bin_tracks, smooth_tracks, track
from .velocity import StageClock, refine_particles, refined_field

__all__ = ["MTESettings", "PairResult", "PairSettings", "PoseCalibration",
           "SelfCalibration", "StageClock", "TrackSettings", "bin_tracks", "calibrate_pose",
           "correlate_volumes", "motion_tracking_enhancement", "process_pair",
           "refine_particles", "refined_field", "self_calibrate", "smooth_tracks", "track"]
