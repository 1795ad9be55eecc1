"""Checks of the physical quantities a user types: one place for the plausible range of
the time between the two exposures of a pair.

PIV's exposure separations run from about 0.1 µs (high-speed air flows) to about a
second (slow water flows). A value outside that range is almost always a unit mistake
(``175`` for 175 µs), which would otherwise give a silently wrong field (a velocity
10^6 times too small) or black images; it is refused before any work starts, naming
the fix. ``force=True`` (``--force``, ``force_dt = true``) accepts it for the rare real
case.
"""

from __future__ import annotations

import math

#: Shortest and longest plausible time between two exposures (s).
DT_RANGE_S = (1e-7, 1.0)


def check_dt(dt, what: str = "dt", force: bool = False, flag: str = "--force") -> float:
    """Return ``dt`` as a float after checking it is a plausible exposure separation.

    Raises
    ------
    ValueError
        ``dt`` is not a positive finite number (always), or lies outside
        :data:`DT_RANGE_S` without ``force``; the message names ``what`` and the fix.
    """
    try:
        value = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be the time between the exposures in seconds "
                         f"(e.g. 175e-6), got {dt!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{what} must be the time between the exposures in seconds "
                         f"(e.g. 175e-6), got {dt!r}")
    if value <= 0:
        sign = "negative" if value < 0 else "zero"
        raise ValueError(f"{what} = {value:g} s is {sign}: it must be positive, the time "
                         "from the first exposure to the second in seconds (e.g. 175e-6); "
                         "for a pair recorded the other way round, swap its two volumes "
                         "or images")
    lo, hi = DT_RANGE_S
    if not force and not lo <= value <= hi:
        guess = f"; {value:g} µs would be {value * 1e-6:g}" if value > hi else ""
        raise ValueError(
            f"{what} = {value:g} s between the two exposures is outside what PIV uses "
            f"({lo:g} s to {hi:g} s): it is in seconds{guess}. If the value is real, "
            f"give {flag}")
    return value


def check_displacement(displacement_mm: float, extent_mm: float, force: bool = False,
                       flag: str = "--force") -> None:
    """Refuse a displacement between exposures larger than the field it is imaged in:
    every particle would leave it (a ``dt`` or velocity in the wrong units)."""
    if not force and displacement_mm > extent_mm:
        raise ValueError(
            f"the particles move {displacement_mm:.4g} mm between the exposures, more than "
            f"the {extent_mm:.4g} mm field of view: check the units of dt (seconds) and of "
            f"the velocity (m/s, rad/s); if the value is real, give {flag}")
