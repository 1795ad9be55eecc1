"""The ``[tracking]`` section of an experiment file: a time-resolved recording tracked
(:func:`plenocl.track`) instead of processed as pairs (docs/batch.md).

Example::

    [images]
    folder = "raw"
    pattern = "frame_*.tif"              # every frame, by number, no gap
    [tracking]
    enabled = true                       # the default when the section is given
    frame_interval_s = 1e-3              # between successive frames (s)
    min_length = 4                       # any TrackSettings option: threshold, search,
    window = 7                           # gap, window, degree, refits, min_length,
    neighbours = 12                      # acceleration, neighbours, merge
    field_window = 16                    # the binned field's windows (voxels, or
                                         # [z, y, x]; 16 or the grid's size where smaller)
    field_step = 8                       # their spacing (default: half a window)
    field_min_samples = 3                # fewest track steps for a vector
    field_steps = 0                      # steps pooled per field: 0 all (one mean field);
                                         # n: one field per n steps, a time series

``[reconstruction]``, ``[piv]`` and ``[image_fit]`` set the same parts of the
:class:`~plenocl.pipeline.TrackSettings` as of a pair's settings; ``[mte]``,
``[particles]``, ``[piv] ensemble`` and the pair keys of ``[images]`` (``dt_s``,
``pair_interval_s``, ``pairing = "ab"`` or ``"list"``) belong to the pair chain and are
refused with tracking.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

from ..options import field_names, from_table, is_integer, is_number, to_table
from ..pipeline.settings import PairSettings
from ..pipeline.track import TrackSettings
from ..units import check_dt

#: The parts of :class:`TrackSettings` that are sections of their own.
PARTS = ("reconstruction", "image_fit", "piv")
#: The keys of ``[tracking]`` besides :class:`TrackSettings`' own, with their defaults.
KEYS = {"enabled": True, "frame_interval_s": None, "field_window": None, "field_step": None,
        "field_min_samples": 3, "field_steps": 0}
#: The binned field's window (voxels) where ``field_window`` is not given.
FIELD_WINDOW = 16
#: Sections and keys of the pair chain that a tracking run refuses.
PAIR_ONLY = ("mte", "particles")


@dataclass(frozen=True)
class TrackingOptions:
    """A checked ``[tracking]`` section.

    Attributes
    ----------
    settings
        :func:`plenocl.track`'s settings.
    interval_s
        The time between successive frames (s).
    field_window, field_step
        The binned field's windows and their spacing ``(z, y, x)`` voxels (``None``:
        :data:`FIELD_WINDOW` cut to the grid, half a window).
    field_min_samples
        Fewest track steps for a vector of the binned field.
    field_steps
        Steps pooled into each binned field (0: all of them, one field).
    """

    settings: TrackSettings
    interval_s: float
    field_window: tuple[int, int, int] | None = None
    field_step: tuple[int, int, int] | None = None
    field_min_samples: int = 3
    field_steps: int = 0

    def layout(self, grid) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """The binned field's window and step on ``grid``; a window that does not fit
        is an error naming the key (checked before any frame is tracked)."""
        shape = tuple(int(n) for n in grid.shape)
        window = self.field_window or tuple(min(FIELD_WINDOW, n) for n in shape)
        if any(w > n for w, n in zip(window, shape)):
            raise ValueError(f"[tracking] field_window {list(window)} (z, y, x voxels) is "
                             f"larger than the grid {list(shape)}: give a smaller window")
        step = self.field_step or tuple(max(1, w // 2) for w in window)
        return window, step

    def field_record(self) -> dict:
        """The binned field's options as given (``None``: the default): what only the
        field stage depends on."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in asdict(self).items() if k.startswith("field_")}

    def record(self) -> dict:
        """The sections this run used, resolved (``experiment_used.toml``): ``[tracking]``
        and the :data:`PARTS`."""
        parts = PairSettings(reconstruction=self.settings.reconstruction,
                             piv=self.settings.piv, image_fit=self.settings.image_fit)
        doc = parts.to_dict(none="none")
        own = to_table(self.settings, skip=PARTS)
        fields = {k: v for k, v in self.field_record().items() if v is not None}
        tracking = {"enabled": True, "frame_interval_s": self.interval_s, **own, **fields}
        return {"tracking": tracking, **{part: doc[part] for part in PARTS}}


def tracking_options(table, parts: Mapping, images: Mapping, path: Path
                     ) -> TrackingOptions | None:
    """The ``[tracking]`` section checked (``None``: not given, or ``enabled = false``).

    Parameters
    ----------
    table
        The ``[tracking]`` table (``None`` when absent).
    parts
        The file's pair-settings sections (``[reconstruction]``, ``[piv]`` without
        ``ensemble``, ``[image_fit]``, ...).
    images
        The checked ``[images]`` section (for ``force_dt``).
    path
        The experiment file (named in every error).

    Raises
    ------
    ValueError
        An unknown key, a bad value or a pair-only section, naming it and the fix.
    """
    if table is None:
        return None
    where = f"{path}: [tracking]"
    own = field_names(TrackSettings)
    allowed = [*KEYS, *(k for k in own if k not in PARTS)]
    if not isinstance(table, Mapping):
        raise ValueError(f"{where} must be a table of options, got {table!r}")
    bad = sorted(set(table) - set(allowed))
    if bad:
        raise ValueError(f"{where}: unknown key(s) {bad}; it takes {allowed}")
    given = {**KEYS, **table}
    if not isinstance(given["enabled"], bool):
        raise ValueError(f"{where} enabled must be true or false, got {given['enabled']!r}")
    if not given["enabled"]:
        return None
    _refuse_pair_parts(parts, path)
    # the weights named, as the pairs' are (config.py): the key names those that made
    # the volumes the tracks come from
    chain = PairSettings.from_dict({k: v for k, v in parts.items() if k in PARTS},
                                   source=str(path)).with_named_weights()
    scalars = {k: v for k, v in table.items() if k not in KEYS}
    settings = from_table(TrackSettings, {**scalars, "reconstruction": chain.reconstruction,
                                          "piv": chain.piv, "image_fit": chain.image_fit},
                          where)
    return TrackingOptions(settings, _interval(given["frame_interval_s"], images, where),
                           _voxels(given["field_window"], "field_window", where),
                           _voxels(given["field_step"], "field_step", where),
                           _count(given["field_min_samples"], "field_min_samples", 1, where),
                           _count(given["field_steps"], "field_steps", 0, where))


def _refuse_pair_parts(parts: Mapping, path: Path) -> None:
    """The pair chain's own sections have no meaning for tracking."""
    given = [name for name in PAIR_ONLY if name in parts]
    if given:
        raise ValueError(f"{path}: [{given[0]}] belongs to the pair chain, and [tracking] "
                         f"tracks the frames instead: remove [{given[0]}], or set "
                         "[tracking] enabled = false to process pairs")


def check_images_for_tracking(images: Mapping, ensemble: bool, path: Path,
                              formats: tuple[str, ...] = ()) -> None:
    """``[images]``, ``[piv]`` and ``[output]`` keys that make no sense for a tracked
    recording (``formats``: the pair fields' copies, ``[output] formats`` and ``vti``):
    an error naming the key and the fix."""
    if images["pairing"] not in ("sequence", "sliding"):
        raise ValueError(f"{path}: [tracking] follows the frames in the order of their "
                         f"numbers, so [images] pairing = {images['pairing']!r} does not "
                         "apply: remove pairing (and pairs, a_suffix, b_suffix), or set "
                         "[tracking] enabled = false to process the pairs")
    for key, what in (("dt_s", "the time between a pair's exposures"),
                      ("pair_interval_s", "the time between pairs")):
        if images[key] is not None:
            raise ValueError(f"{path}: [images] {key} is {what}; a tracked recording's "
                             "time is [tracking] frame_interval_s (the time between "
                             f"successive frames): remove {key}")
    if ensemble:
        raise ValueError(f"{path}: [piv] ensemble belongs to the pair chain; remove it "
                         "with [tracking] (the tracks' field is binned instead)")
    if formats:
        raise ValueError(f"{path}: [output] formats and vti ({', '.join(formats)}) are the "
                         "copies of each pair's field, which a [tracking] run does not make "
                         "(it writes tracks.npz, tracks.vtu and tracks.zarr): remove them")


def _interval(value, images: Mapping, where: str) -> float:
    if not (is_number(value) and math.isfinite(value) and value > 0):
        raise ValueError(f"{where} frame_interval_s must be the time between successive "
                         f"frames in seconds, a positive number (e.g. 1e-3), got {value!r}")
    return check_dt(value, f"{where} frame_interval_s", images["force_dt"],
                    flag="[images] force_dt = true")


def _voxels(value, key: str, where: str) -> tuple[int, int, int] | None:
    """``None``, or a positive voxel count, or three (z, y, x)."""
    if value is None:
        return None
    items = [value] * 3 if not isinstance(value, list) else value
    if len(items) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1
                                  for v in items):
        raise ValueError(f"{where} {key} must be a positive number of voxels or three of "
                         f"them [z, y, x], got {value!r}")
    return tuple(int(v) for v in items)


def _count(value, key: str, least: int, where: str) -> int:
    if not is_integer(value) or value < least:
        raise ValueError(f"{where} {key} must be an integer >= {least}, got {value!r}")
    return int(value)
