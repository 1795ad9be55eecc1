"""The ensemble-correlation mean field of a run (``[piv] ensemble = true``): every
finished pair whose volumes were kept, deformed by the mean of the pairs' own fields and
correlated together (:func:`plenocl.piv.ensemble.ensemble_piv`), written to
``OUT/ensemble.npz`` and gathered into the time-series store."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..device import get_queue
from ..grid import Grid
from ..io.files import read_volumes
from ..piv.ensemble import ensemble_piv
from ..vectorfield import PIVResult
from ..vectorfile import read_npz, save_field
from .layout import finished_pairs, volume_file


def ensemble_field(out: Path, dt: float, queue=None, formats: tuple[str, ...] = (),
                   log=print) -> Path | None:
    """Correlate the run's kept volume pairs as one ensemble; the field file written
    (``ensemble.npz``, and a copy in each of ``formats``' suffixes, e.g. ``".vti"``), or
    ``None`` when no pair kept its volumes."""
    fields = [path for _, path in finished_pairs(out) if volume_file(path).is_file()]
    if not fields:
        log("ensemble correlation: no pair kept its volumes ([piv] ensemble was off when "
            "they were processed); skipped")
        return None
    predictor = mean_field([read_npz(path)[0] for path in fields])

    def pairs():
        return (read_volumes(volume_file(path)) for path in fields)

    result = ensemble_piv(pairs, predictor, queue=get_queue(queue))
    grid = Grid.from_toml(out / "grid_used.toml")
    target = out / "ensemble.npz"
    for suffix in formats:
        save_field(target.with_suffix(suffix), result, dt=dt, grid=grid)
    save_field(target, result, dt=dt, grid=grid)
    log(f"ensemble correlation of {len(fields)} pair(s): {result.valid.mean():.0%} valid "
        f"vectors, in {target}")
    return target


def mean_field(results: list[PIVResult]) -> PIVResult:
    """The mean of the valid vectors of fields on one grid (where none is valid: the mean
    of all), as a :class:`PIVResult` carrying the first field's grid and window."""
    first = results[0]
    comps = []
    for name in ("u", "v", "w"):
        stack = np.stack([getattr(r, name) for r in results])
        valid = np.stack([r.valid for r in results]) & np.isfinite(stack)
        count = valid.sum(0)
        total = np.where(valid, stack, 0.0).sum(0)
        fallback = np.nanmean(stack, axis=0)
        comps.append(np.where(count > 0, total / np.maximum(count, 1), fallback))
    nan = np.full(first.shape, np.nan)
    return PIVResult(x=first.x, y=first.y, z=first.z, u=comps[0], v=comps[1], w=comps[2],
                     valid=np.ones(first.shape, bool), peak_ratio=nan,
                     outlier=np.zeros(first.shape, bool), masked=first.masked,
                     window=first.window)
