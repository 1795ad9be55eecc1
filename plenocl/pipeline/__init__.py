"""The default chain for one image pair (docs/design.md §9): :func:`process_pair`
(``pair.py``), its settings (:class:`PairSettings`, ``settings.py``, the single home of
its defaults) and its two-exposure reconstruction, motion-tracking enhancement
(``mte.py``)."""

from .mte import MTESettings, motion_tracking_enhancement
from .pair import PairResult, process_pair
from .settings import PairSettings

__all__ = ["MTESettings", "PairResult", "PairSettings",
           "motion_tracking_enhancement", "process_pair"]
