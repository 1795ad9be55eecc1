"""What made each stored product of a pairs run, and what a rerun has to redo.

Every pair's field carries a record (its metadata, :func:`field_record`): the sections
of the experiment that made it, resolved (``images``: channel, dark frame and flat
field by content, ``dt_s``; ``reconstruction``, ``mte``, ``piv``, ``particles``,
``image_fit``), the calibrated camera's and the grid's digests, beside the two source
files (name, size, SHA-256) it already names; and the digests of the stages: ``volumes``
(the source files, camera, grid, frame corrections, the reconstruction's settings and
its method, :data:`plenocl.reconstruction.METHOD`; with motion-tracking enhancement the
PIV settings too, which it reconstructs with), ``field`` (all but ``dt_s``) and
``record`` (everything). Kept volumes carry their ``volumes`` digest.

A rerun compares each finished pair's record with the run's (:func:`decide`), naming
the changed entries as :func:`plenocl.pipeline.resume.changed_keys` does
(``images.dt_s``, ``piv.windows``, ``reconstruction.iterations``, ``camera``):

- nothing changed: the pair is skipped;
- ``images.dt_s`` alone: the stored displacements (voxels) give the velocities again
  (``rescale``), nothing is reconstructed or correlated;
- ``piv``, ``particles`` or ``image_fit`` (and ``dt_s``): the kept volumes, when their
  digest is the run's, are correlated again (``correlate``); otherwise the pair is redone;
- anything else of the reconstruction (``reconstruction``, ``mte``, the frame
  corrections, ``reconstruction_method``: a record written before it was recorded
  lacks it, so such a pair is redone too): the pair is redone (``redo``);
- the camera, the grid, the pair's source files, or a field without a record (written
  before records, or unreadable): refused (:data:`REFUSE`) unless the run is told to
  redo such pairs (``redo=True``, ``plenocl run --redo``).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

from ..io.fieldformat import field_metadata
from ..io.files import volumes_metadata
from ..options import NONE
from ..pipeline.resume import changed_keys, config_digest, config_parts, name_changes
from ..piv.direct import METHOD as CORRELATION_METHOD
from ..piv.ensemble import METHOD as ENSEMBLE_METHOD
from ..piv.refinement import METHOD as REFINEMENT_METHOD
from ..reconstruction import METHOD as RECONSTRUCTION_METHOD
from .config import Experiment
from .pairing import ImagePair, changed_since, fingerprint, sources_present
from .prepare import frame_corrections

#: What a rerun does with a finished pair (see the module notes).
SKIP, RESCALE, CORRELATE, REDO = "skip", "rescale", "correlate", "redo"
#: The entries whose change refuses a rerun (without ``redo``): the results would be of
#: another geometry.
REFUSE = ("camera", "grid")
#: The sections a correlation alone depends on (after the volumes); ``correlation`` and
#: ``refinement``: the correlation's and the particle refinement's methods
#: (:data:`plenocl.piv.direct.METHOD`, :data:`plenocl.piv.refinement.METHOD`), so that a
#: rerun after either changed re-correlates instead of keeping the earlier method's fields.
FIELD_SECTIONS = ("piv", "correlation", "particles", "image_fit", "refinement")
#: The entry of the time between the exposures.
DT = "images.dt_s"
#: Options that change how fast a pair runs, not what it gives (the image fit's
#: particles per launch: the same fit for any chunk, tested bit for bit): left out of the
#: record, and out of the comparison with a record written before they were left out.
SPEED_ONLY = ("image_fit.chunk",)

_UNREADABLE = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile)


def run_record(exp: Experiment, camera, grid) -> dict:
    """The record every pair of this run shares (see the module notes): JSON-ready.
    ``camera``: the camera, or several cameras' list (their digests' list: a camera
    more or less, or one moved, is another geometry)."""
    dark, flat = frame_corrections(exp)
    pair = exp.pair.to_dict(none=NONE)
    for entry in SPEED_ONLY:
        section, key = entry.split(".")
        pair[section].pop(key, None)
    images = {"channel": exp["images"]["channel"] or NONE,
              "dark": _content(dark), "flat": _content(flat),
              "dt_s": float(exp["images"]["dt_s"])}
    digest = (config_digest([c.to_dict() for c in camera]) if isinstance(camera, list)
              else config_digest(camera.to_dict()))
    return {"images": images, "camera": digest,
            "grid": config_digest(grid.to_dict()), **pair,
            "reconstruction_method": {"method": RECONSTRUCTION_METHOD},
            "correlation": {"method": CORRELATION_METHOD},
            "refinement": {"method": REFINEMENT_METHOD}}


def _content(path: str | None) -> str:
    """A frame correction by its content's SHA-256 (``"none"``: none)."""
    return fingerprint(Path(path))["sha256"] if path else NONE


def stage_digests(record: dict, sources: dict) -> dict[str, str]:
    """The ``volumes``, ``field`` and ``record`` digests of a pair's record and its
    source files (:func:`plenocl.batch.pairing.pair_sources`: ``{"a": fingerprint,
    "b": fingerprint}``, several cameras' others under ``"cameras"``)."""
    inputs = [files[tag]["sha256"] for files in [sources, *sources.get("cameras", [])]
              for tag in "ab"]
    field_part = {k: v for k, v in record.items() if k != "images"}
    field_part["images"] = {k: v for k, v in record["images"].items() if k != "dt_s"}
    volumes = {k: v for k, v in field_part.items() if k not in FIELD_SECTIONS}
    if record["mte"].get("cycles"):  # the enhancement reconstructs with the correlation
        volumes["piv"] = record["piv"]
        volumes["correlation"] = record.get("correlation")
    return {"volumes": config_digest({"inputs": inputs, **volumes}),
            "field": config_digest({"inputs": inputs, **field_part}),
            "record": config_digest({"inputs": inputs, **record})}


def field_record(record: dict, sources: dict, index: int) -> dict:
    """The metadata a pair's field is written with: its two source files, its index, the
    run's record and the stage digests (the first two alone without a record)."""
    if not record:
        return {"sources": sources, "pair": index}
    return {"sources": sources, "pair": index, "record": record,
            "digests": stage_digests(record, sources)}


def record_changes(old: dict, new: dict) -> list[str]:
    """The entries that differ between a pair's record and the run's (sorted, as
    :func:`plenocl.pipeline.resume.changed_keys` names them), the
    :data:`SPEED_ONLY` options left out."""
    return [k for k in changed_keys(config_parts(old), config_parts(new))
            if k not in SPEED_ONLY]


@dataclass
class Decision:
    """What a rerun does with one finished pair: ``action`` (:data:`SKIP`,
    :data:`RESCALE`, :data:`CORRELATE`, :data:`REDO`), the changed entries, why it cannot
    be kept or remade as it is (``reason``), and that reason as a refusal (``refused``,
    when the run was not told to redo such pairs)."""

    index: int
    action: str = SKIP
    changed: list[str] = field(default_factory=list)
    refused: str | None = None
    reason: str | None = None


def decide(pair: ImagePair | None, field_file: Path, volumes_file: Path, record: dict,
           redo: bool = False, folders: list[Path] | None = None) -> Decision:
    """What to do with the finished pair in ``field_file`` under the run's ``record``
    (``pair``: the run's pair of that index, ``None`` when the run makes no such pair:
    when its frames are gone, it is kept or rescaled while its record allows, else it
    cannot be remade; when they are still in the run's image ``folders``, the run's
    ``[images]`` selection no longer makes it, and it cannot be kept)."""
    k = int(field_file.stem.removeprefix("pair_"))
    try:
        meta = field_metadata(field_file)
    except _UNREADABLE as exc:
        return _refusal(k, f"{field_file.name} cannot be read ({exc})", redo)
    if pair is None and not meta.get("sources"):
        return _refusal(k, f"{field_file.name} exists but the images give no pair {k}", redo)
    if pair is None and folders and sources_present(meta["sources"], folders):
        return _refusal(k, _unselected(meta["sources"], folders[0]), redo)
    if pair is not None and (why := changed_since(meta.get("sources", {}), pair)) is not None:
        return _refusal(k, why, redo)
    gone = "" if pair is not None else " and its frames are gone"
    if "record" not in meta:
        return _refusal(k, "its field records no settings (written by an older plenocl)"
                        + gone, redo)
    changed = record_changes(meta["record"], record)
    if not changed:
        return Decision(k)
    if changed == [DT]:
        return Decision(k, RESCALE, changed)
    if pair is None:
        return _refusal(k, f"{name_changes(changed)} changed{gone}", redo)
    return _action(k, changed, meta, record, volumes_file, redo)


def _unselected(sources: dict, folder: Path) -> str:
    """Why a pair whose frames are still there cannot be kept: the run's selection."""
    names = " and ".join(str(sources[tag]["name"]) for tag in "ab")
    return (f"it was made from {names}, still in {folder}, which the run's [images] "
            "selection (pattern, first_frame, pairing, pairs) no longer pairs so")


def _action(k: int, changed: list[str], meta: dict, record: dict, volumes_file: Path,
            redo: bool) -> Decision:
    """The action for a pair whose record differs from the run's in ``changed`` (more
    than ``dt_s``)."""
    geometry = [name for name in changed if name in REFUSE]
    if geometry:
        return _refusal(k, f"the {' and '.join(geometry)} changed since it was made", redo,
                        changed)
    if all(name == DT or name.split(".")[0] in FIELD_SECTIONS for name in changed):
        wanted = stage_digests(record, meta["sources"])["volumes"]
        if not record["mte"].get("cycles") and kept_volumes(volumes_file) == wanted:
            return Decision(k, CORRELATE, changed)
    return Decision(k, REDO, changed)


def kept_volumes(path: Path) -> str | None:
    """The ``volumes`` digest of a pair's kept volumes (``None``: none, or unknown)."""
    if not path.is_file():
        return None
    try:
        return volumes_metadata(path).get("volumes")
    except _UNREADABLE:
        return None


def _refusal(k: int, why: str, redo: bool, changed: list[str] | None = None) -> Decision:
    """A pair that cannot be kept or remade as it is: redone when ``redo``."""
    return Decision(k, REDO, changed or [], None if redo else f"pair {k}: {why}", why)


def refuse(decisions: list[Decision], out: Path) -> None:
    """Raise, naming the pairs and the way out, when any decision is a refusal."""
    refused = [d.refused for d in decisions if d.refused]
    if not refused:
        return
    raise ValueError(
        f"{out} holds pairs this run can neither keep nor remake (made from other images, "
        "another camera or grid, or by an older plenocl, no longer in its [images] "
        "selection, or damaged): "
        + "; ".join(refused[:5]) + (f"; and {len(refused) - 5} more" if len(refused) > 5
                                    else "")
        + ". Write this run to another folder (--out), or redo those pairs with --redo "
        "(plenocl.run(..., redo=True)), or remove the old results")


def ensemble_record(fields: dict[int, dict], dt_s: float) -> dict:
    """What the ensemble correlation is made of: each pair's ``field`` digest (the pairs
    whose volumes it correlates), the ensemble's method and the correlation's
    (:data:`plenocl.piv.ensemble.METHOD`, :data:`plenocl.piv.direct.METHOD`), and
    ``dt_s``."""
    return {"pairs": {str(k): meta["digests"]["field"] for k, meta in sorted(fields.items())},
            "method": ENSEMBLE_METHOD, "correlation": CORRELATION_METHOD,
            "dt_s": float(dt_s)}


def store_record(fields: dict[int, dict], ensemble: Path | None = None) -> dict:
    """The time-series store's record: each pair's ``record`` digest (``"none"`` for a
    field without one), the ensemble field's record digest (``"none"``: none), and the
    digest of both."""
    pairs = {str(k): meta.get("digests", {}).get("record", NONE)
             for k, meta in sorted(fields.items())}
    made = NONE
    if ensemble is not None:
        made = config_digest(field_metadata(ensemble).get("record")) or NONE
    return {"pairs": pairs, "ensemble": made,
            "digest": config_digest({"pairs": pairs, "ensemble": made})}
