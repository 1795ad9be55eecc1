"""Progress display for long stages (tqdm), usable as a reconstruction callback."""

from __future__ import annotations

from contextlib import contextmanager

from tqdm.auto import tqdm


@contextmanager
def iteration_bar(total: int, desc: str, enabled: bool = True):
    """A progress bar whose ``callback(iteration, residual)`` advances it.

    Yields a callback suitable for :func:`plenocl.reconstruct`.
    """
    bar = tqdm(total=total, desc=desc, unit="it", disable=not enabled, leave=False)

    def callback(iteration: int, residual: float) -> None:
        bar.update(iteration - bar.n)
        bar.set_postfix(residual=f"{residual:.3g}")

    try:
        yield callback
    finally:
        bar.close()
