"""Progress display for long stages (tqdm), usable as a reconstruction callback.

Bars are drawn on terminals only: written to a log file or a pipe they would become
long runs of carriage returns, so there they stay silent (tqdm's ``disable=None``).
"""

from __future__ import annotations

from contextlib import contextmanager

from tqdm.auto import tqdm


def _disable(enabled: bool) -> bool | None:
    """tqdm's ``disable``: ``True`` when not wanted, else ``None`` (only on a terminal)."""
    return None if enabled else True


@contextmanager
def iteration_bar(total: int, desc: str, enabled: bool = True):
    """A progress bar whose ``callback(iteration, residual)`` advances it.

    Yields a callback suitable for :func:`plenocl.reconstruct`.
    """
    bar = tqdm(total=total, desc=desc, unit="it", disable=_disable(enabled), leave=False)

    def callback(iteration: int, residual: float) -> None:
        bar.update(iteration - bar.n)
        bar.set_postfix(residual=f"{residual:.3g}")

    try:
        yield callback
    finally:
        bar.close()


@contextmanager
def pair_bar(total: int, enabled: bool = True):
    """A progress bar over the pairs of a batch: pairs done, pairs per second (tqdm's
    rate) and the time left; yields a function to call with ``failed=`` per pair."""
    bar = tqdm(total=total, desc="pairs", unit="pair", disable=_disable(enabled and total > 0),
               smoothing=0.1)
    failures = 0

    def advance(failed: bool = False) -> None:
        nonlocal failures
        failures += int(failed)
        if failures:
            bar.set_postfix(failed=failures)
        bar.update(1)

    try:
        yield advance
    finally:
        bar.close()


@contextmanager
def step_bar(desc: str, unit: str, enabled: bool = True):
    """A progress bar for a callback ``progress(done, total)`` (e.g.
    :func:`plenocl.track`'s), whose total it learns from the first call."""
    bar = tqdm(desc=desc, unit=unit, disable=_disable(enabled), smoothing=0.1)

    def progress(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
            bar.refresh()
        bar.update(done - bar.n)

    try:
        yield progress
    finally:
        bar.close()
