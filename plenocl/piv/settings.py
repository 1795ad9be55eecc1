"""Every option of :func:`plenocl.piv3d` as one validated object."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..options import is_integer, is_number, whole_counts
from .fft import BACKENDS

CORRELATIONS = ("auto", "fft")
#: Where the FFT correlations run: a host backend or the device (``fft=None``: measured).
FFT_ROUTES = (*BACKENDS, "device")
DEFORM_ORDERS = (1, 3, 5)
PREDICTORS = ("cubic", "linear")


@dataclass(frozen=True)
class PIVSettings:
    """The options of :func:`plenocl.piv3d` (see there for their meaning), checked once.

    ``windows`` and ``overlaps`` given as lists are stored as tuples and checked
    (:func:`window_schedule`); whether the windows fit the volume is checked when the
    volumes come (:func:`plenocl.piv3d`), or a batch's grid (before any pair).
    """

    windows: tuple | int | None = None
    overlaps: tuple | float | None = None
    final_iterations: int = 3
    pad_first: bool = True
    weighting: float | None = 0.35
    deform_order: int = 3
    predictor: str = "cubic"
    median_eps: float = 0.1
    median_threshold: float = 2.0
    min_peak_ratio: float | None = None
    workers: int = -1
    fft: str | None = None
    correlation: str = "auto"

    def __post_init__(self) -> None:
        whole_counts(self, ("final_iterations", "workers", "deform_order"))
        for name in ("windows", "overlaps"):
            value = getattr(self, name)
            if isinstance(value, str):
                raise ValueError(f"{name} must be numbers (e.g. windows=(48, 32, 24), "
                                 f"overlaps=0.5), not text: got {value!r}")
            if isinstance(value, np.ndarray):  # as the list it holds: one entry a pass
                value = value.tolist()
            if isinstance(value, Sequence):
                object.__setattr__(self, name, _frozen(value))
        _check(self)


def _frozen(value):
    """Lists (a TOML array) as tuples, nested ones too, so that settings hash and compare."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        return tuple(_frozen(v) for v in value)
    return value


def _check(s: PIVSettings) -> None:
    weighting = s.weighting
    for name in ("median_eps", "median_threshold", "weighting", "min_peak_ratio"):
        value = getattr(s, name)
        if not (is_number(value) or (value is None and name in ("weighting",
                                                               "min_peak_ratio"))):
            raise ValueError(f"{name} must be a number, got {value!r}")
    if s.correlation not in CORRELATIONS:
        raise ValueError(f"correlation must be 'auto' (the deformed passes correlated "
                         f"directly around zero) or 'fft', got {s.correlation!r}")
    if s.deform_order not in DEFORM_ORDERS:
        raise ValueError(f"deform_order must be 1 (trilinear), 3 (cubic B-spline) or 5 "
                         f"(quintic B-spline), got {s.deform_order!r}")
    if s.predictor not in PREDICTORS:
        raise ValueError(f"predictor must be 'cubic' or 'linear', got {s.predictor!r}")
    if not (s.median_eps > 0 and s.median_threshold > 0):
        raise ValueError(f"median_eps and median_threshold must be positive, got "
                         f"{s.median_eps!r} and {s.median_threshold!r}")
    if weighting is not None and not 0.05 <= weighting <= 10:
        raise ValueError(f"weighting is a Gaussian width as a fraction of the window "
                         f"(e.g. 0.35) or None, got {weighting!r}")
    if s.min_peak_ratio is not None and not (np.isfinite(s.min_peak_ratio)
                                             and s.min_peak_ratio >= 1):
        raise ValueError(f"min_peak_ratio must be a finite number >= 1 (a correlation's "
                         f"highest peak over its second: never below 1) or None, got "
                         f"{s.min_peak_ratio!r}")
    if not isinstance(s.pad_first, (bool, np.bool_)):
        raise ValueError(f"pad_first must be true or false, got {s.pad_first!r}")
    _check_counts(s)


def window_schedule(windows, overlaps, final_iterations: int) -> list[tuple[tuple, float]]:
    """The ``(size, overlap)`` of every pass: ``windows`` (one size, or one per pass: an
    int or ``(wz, wy, wx)``, integers >= 8 voxels), ``overlaps`` (``None``: 0.5 for every
    pass but the last, 0.75 for the last; one fraction in ``[0, 1)`` for all, or one per
    pass), the last pass run ``final_iterations`` (>= 1) times. Whether the windows fit a
    volume is :func:`plenocl.piv.multipass.window_passes`'.

    Raises
    ------
    ValueError
        Naming the option and what it takes.
    """
    windows = list(windows) if isinstance(windows, Sequence) else [windows]
    if not windows:
        raise ValueError("windows must list at least one window size, e.g. (48, 32, 24)")
    if overlaps is None:
        overlaps = [0.5] * (len(windows) - 1) + [0.75]
    overlaps = list(overlaps) if isinstance(overlaps, Sequence) else [overlaps] * len(windows)
    if len(overlaps) != len(windows):
        raise ValueError(f"overlaps ({len(overlaps)} values) must match windows "
                         f"({len(windows)} passes) or be a single fraction")
    _check_final_iterations(final_iterations)
    passes = [(_window_size(win, k), _overlap(ovl, k))
              for k, (win, ovl) in enumerate(zip(windows, overlaps), start=1)]
    return passes + [passes[-1]] * (int(final_iterations) - 1)


def _check_final_iterations(value) -> None:
    """How many times the last pass runs: an integer >= 1."""
    if not is_integer(value) or value < 1:
        raise ValueError(f"final_iterations must be an integer >= 1 (how many times the "
                         f"last pass runs), got {value!r}")


def _window_size(win, k: int) -> tuple[int, int, int]:
    """Pass ``k``'s window ``(wz, wy, wx)`` from an int or three, integers >= 8."""
    items = list(np.ravel(win)) if np.ndim(win) else [win] * 3
    if len(items) != 3 or not all(_whole(v) and v >= 8 for v in items):
        raise ValueError(f"window of pass {k} must be integers >= 8 voxels (an int or "
                         f"(wz, wy, wx)), got {win!r}")
    return tuple(int(v) for v in items)


def _whole(value) -> bool:
    """A whole number (an integer, or a float such as 32.0), not a bool."""
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)) and float(value).is_integer())


def _overlap(ovl, k: int) -> float:
    """Pass ``k``'s overlap, a fraction in ``[0, 1)``."""
    if isinstance(ovl, (bool, np.bool_)) or not isinstance(ovl, (int, float, np.number)) \
            or not 0.0 <= float(ovl) < 1.0:
        raise ValueError(f"overlap of pass {k} must be a fraction in [0, 1), got {ovl!r}")
    return float(ovl)


def _check_counts(s: PIVSettings) -> None:
    """The counts and the FFT backend, checked when the settings are made (a batch's
    experiment file is refused before any pair, not in every worker)."""
    if s.windows is not None:  # the windows and overlaps, but whether they fit a volume
        window_schedule(s.windows, s.overlaps, s.final_iterations)
    elif isinstance(s.overlaps, Sequence):
        raise ValueError(f"overlaps {s.overlaps!r} gives one per pass, but without windows "
                         "the passes follow each volume's particles (two or three): give "
                         "the windows they go with, or one overlap for every pass")
    elif s.overlaps is not None:
        _overlap(s.overlaps, 1)
    _check_final_iterations(s.final_iterations)
    if not is_integer(s.workers) or not (s.workers == -1 or s.workers >= 1):
        raise ValueError(f"workers must be -1 (all cores) or a positive integer, got "
                         f"{s.workers!r}")
    if s.fft is not None and s.fft not in FFT_ROUTES:
        raise ValueError(f"fft must be one of {FFT_ROUTES} (the host's FFTW or SciPy, or "
                         f"the OpenCL device) or None (whichever of the device and the "
                         f"host measures faster), got {s.fft!r}")
