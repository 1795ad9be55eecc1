"""Resuming interrupted work: one mechanism for the demos' stages and a batch's pairs.

A piece of work is done when all its output files exist. Every file is written atomically
(:func:`plenocl.io.atomic_path`), so a killed run leaves no half-written output, only
temporary files, which :func:`remove_partial_files` deletes before a run goes on.

- :func:`remove_outputs`: results a run makes again, removed before it starts (a file or
  a store folder);
- :class:`StageRunner`: named stages in an output folder; a stage is done when its entry
  in ``state.json`` exists, was made with the same configuration, and its outputs exist
  (the demos, a tracking run). ``state.json`` names a new configuration, with no stage
  done, before any stage runs.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from ..io.atomic import write_json


def outputs_exist(paths: Iterable[str | Path]) -> bool:
    """Whether every output file is present (work done, as the files are written
    atomically)."""
    return all(Path(p).is_file() for p in paths)


def remove_partial_files(*folders: Path) -> list[Path]:
    """Delete what a killed run left half-written in ``folders``: the atomic writers'
    temporary files (``.<name>.*.part*``) and stores being written (``*.partial``)."""
    left = [path for folder in map(Path, folders)
            for pattern in (".*.part*", "*.partial") for path in folder.glob(pattern)]
    return remove_outputs(left, ignore_errors=True)


def remove_outputs(paths: Iterable[str | Path], ignore_errors: bool = False) -> list[Path]:
    """Delete the files and store folders among ``paths`` that exist; those deleted
    (``ignore_errors``: a folder that cannot be deleted whole is left as it is)."""
    gone = [Path(p) for p in paths if Path(p).exists()]
    for path in gone:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=ignore_errors)
        else:
            path.unlink(missing_ok=True)
    return gone


def config_digest(config: dict | None) -> str | None:
    """SHA-256 of a JSON-serialisable configuration (``None`` stays ``None``)."""
    if config is None:
        return None
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def config_parts(config: dict) -> dict[str, str]:
    """A digest of each entry of ``config``, and of each entry of its dictionaries
    (``"settings.tracking"``): what a changed configuration names."""
    parts = {}
    for key, value in config.items():
        if isinstance(value, dict) and value:
            parts.update({f"{key}.{k}": config_digest({"v": v}) for k, v in value.items()})
        else:
            parts[str(key)] = config_digest({"v": value})
    return parts


def changed_keys(old: dict | None, new: dict) -> list[str]:
    """The entries that differ between two :func:`config_parts`, sorted (empty when
    ``old`` is unknown)."""
    if not old:
        return []
    return sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))


def name_changes(names: Sequence[str], most: int = 6) -> str:
    """Changed entries (:func:`changed_keys`) as text: the first ``most``, then a count."""
    names = list(names)
    return ", ".join(names[:most]) + (f" and {len(names) - most} more"
                                      if len(names) > most else "")


class StageRunner:
    """Runs named stages in an output folder, skipping those already done.

    Parameters
    ----------
    out_dir
        Output folder (created).
    config
        JSON-serialisable configuration; a change invalidates every stage. A stage may
        have a key of its own as well (:meth:`run`), whose change reruns that stage.
    log
        Called with progress lines (``print`` by default).
    """

    def __init__(self, out_dir: str | Path, config: dict,
                 log: Callable[[str], None] = print) -> None:
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        for path in remove_partial_files(self.out):
            log(f"removed {path.name}, left half-written by an interrupted run")
        self.key = config_digest(config)
        self.log = log
        self.state_path = self.out / "state.json"
        self.state = {"config": self.key, "parts": config_parts(config), "stages": {}}
        old = json.loads(self.state_path.read_text()) if self.state_path.is_file() else None
        if old is not None and old.get("config") == self.key:
            self.state = old
            return
        if old is not None:
            changed = name_changes(changed_keys(old.get("parts"), self.state["parts"]))
            self.log(f"configuration changed{f' ({changed})' if changed else ''}: "
                     "running every stage again")
        # the new configuration with no stage done, before any stage writes an output: a
        # run stopped after a stage's outputs but before its entry leaves a state that
        # names this configuration, so no later run keeps those outputs for another
        write_json(self.state_path, self.state, sort_keys=True)

    def path(self, name: str) -> Path:
        """A file in the output folder."""
        return self.out / name

    def done(self, name: str, outputs: Sequence[str], key: dict | None = None) -> bool:
        """Whether stage ``name`` finished with the stage key ``key`` and its outputs are
        all present."""
        stage = self.state["stages"].get(name)
        return (stage is not None and stage.get("key") == config_digest(key)
                and outputs_exist(self.path(o) for o in outputs))

    def run(self, name: str, outputs: Sequence[str], fn: Callable[[], None],
            key: dict | None = None) -> float:
        """Run ``fn`` unless the stage is done (with the same stage ``key``: what only this
        stage depends on, JSON-serialisable); returns the stage's (recorded) seconds."""
        if self.done(name, outputs, key):
            seconds = self.state["stages"][name]["seconds"]
            self.log(f"[{name}] done earlier ({seconds:.1f} s), skipped")
            return seconds
        self.log(f"[{name}] ...")
        t0 = time.perf_counter()
        fn()
        seconds = time.perf_counter() - t0
        self.state["stages"][name] = {"seconds": seconds, "outputs": list(outputs),
                                      "key": config_digest(key)}
        write_json(self.state_path, self.state, sort_keys=True)
        self.log(f"[{name}] {seconds:.1f} s")
        return seconds

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per finished stage."""
        return {k: v["seconds"] for k, v in self.state["stages"].items()}
