"""The default chain for one image pair (docs/design.md §9): :func:`process_pair`
(``pair.py``) and its two-exposure reconstruction, motion-tracking enhancement
(``mte.py``)."""

from .mte import MTESettings, motion_tracking_enhancement
from .pair import PairResult, process_pair

__all__ = ["MTESettings", "PairResult", "motion_tracking_enhancement", "process_pair"]
