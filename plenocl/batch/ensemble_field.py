"""The ensemble-correlation mean field of a run (``[piv] ensemble = true``): every
finished pair whose volumes were kept, deformed by the mean of the pairs' own fields and
correlated together (:func:`plenocl.piv.ensemble.ensemble_piv`), written to
``OUT/ensemble.npz`` and gathered into the time-series store.

The field records what it was made of (:func:`plenocl.batch.record.ensemble_record`: each
pair's ``field`` digest, the ensemble's and the correlation's methods, and ``dt_s``);
:func:`update_ensemble` keeps it while that is unchanged, rescales it when ``dt_s`` alone
changed, and makes it again otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..grid import Grid
from ..io.fieldformat import field_metadata
from ..io.files import read_volumes
from ..opencl.device import get_queue
from ..pipeline.resume import remove_outputs
from ..piv.ensemble import ensemble_piv
from ..vectorfield import PIVResult, read_npz
from .layout import field_copies, finished_pairs, volume_file
from .record import ensemble_record, kept_volumes
from .worker import add_copies, rewrite_field, save_with_copies

#: The ensemble field's file in a run's output folder.
ENSEMBLE = "ensemble.npz"


def update_ensemble(out: Path, fields: dict[int, tuple[Path, dict]], dt: float, queue=None,
                    formats: tuple[str, ...] = (), log=print,
                    wanted: bool = True) -> Path | None:
    """The run's ensemble field made, kept or rescaled to match its pairs (see the module
    notes); ``fields``: ``{pair: (field file, its metadata)}`` of the finished pairs.
    Not ``wanted`` (ensemble off, or the run interrupted): an ensemble field that no
    longer matches its pairs is removed, and said so. Returns the field, or ``None``."""
    made = Path(out) / ENSEMBLE
    usable = {k: (path, meta) for k, (path, meta) in fields.items()
              if _volumes_digest(meta) is not None
              and kept_volumes(volume_file(path)) == _volumes_digest(meta)}
    record = ensemble_record({k: meta for k, (_, meta) in usable.items()}, dt)
    old = field_metadata(made).get("record") if made.is_file() else None
    if old == record:
        if wanted:
            log(f"ensemble correlation: no new pair and none changed, {made} kept")
            add_copies(made, Grid.from_toml(made.parent / "grid_used.toml"), formats)
        return made
    if not wanted:
        if made.is_file():
            _remove_with_copies(made)
            log(f"removed {made} and its copies: made from other pairs or another dt_s than "
                "those now here")
        return None
    if old is not None and _but_dt(old) == _but_dt(record):
        _rescale(made, dt, formats, record)
        log(f"ensemble correlation: dt_s changed, {made} rescaled")
        return made
    _remove_with_copies(made)
    return ensemble_field(out, dt, queue, formats, log, [path for path, _ in usable.values()],
                          {"record": record})


def _remove_with_copies(made: Path) -> None:
    """The ensemble field and its copies (``.csv``, ``.vti``...) removed: a copy left
    beside a removed or remade field held the older ensemble's vectors."""
    remove_outputs([made, *field_copies(made)])


def _but_dt(record: dict) -> dict:
    """An ensemble record without its ``dt_s``: equal, only ``dt_s`` changed."""
    return {k: v for k, v in record.items() if k != "dt_s"}


def _volumes_digest(meta: dict) -> str | None:
    return meta.get("digests", {}).get("volumes")


def _rescale(made: Path, dt: float, formats: tuple[str, ...], record: dict) -> None:
    """The ensemble field written again for ``dt`` (its displacements kept)."""
    rewrite_field(made, Grid.from_toml(made.parent / "grid_used.toml"), dt, formats,
                  {"record": record})


def ensemble_field(out: Path, dt: float, queue=None, formats: tuple[str, ...] = (),
                   log=print, fields: list[Path] | None = None,
                   metadata: dict | None = None) -> Path | None:
    """Correlate the run's kept volume pairs as one ensemble; the field file written, or
    ``None`` when no pair kept its volumes. ``fields``: the pairs' field files (default:
    every finished pair with kept volumes); ``metadata``: written with the field."""
    if fields is None:
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
    target = out / ENSEMBLE
    save_with_copies(target, result, grid, dt, formats, metadata or {})
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
