"""Resumable pipelines: stages whose outputs are kept, so an interrupted run resumes
without repeating finished work.

A stage is done when its entry in ``state.json`` exists, was made with the same
configuration, and all its output files exist. Every file is written atomically
(:func:`plenocl.io.atomic_path`), so a killed run never leaves a half-written output.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ..io.atomic import write_json


class StageRunner:
    """Runs named stages in an output folder, skipping those already done.

    Parameters
    ----------
    out_dir
        Output folder (created).
    config
        JSON-serialisable configuration; a change invalidates every stage.
    log
        Called with progress lines (``print`` by default).
    """

    def __init__(self, out_dir: str | Path, config: dict,
                 log: Callable[[str], None] = print) -> None:
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.key = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()
        self.log = log
        self.state_path = self.out / "state.json"
        self.state = {"config": self.key, "stages": {}}
        if self.state_path.is_file():
            old = json.loads(self.state_path.read_text())
            if old.get("config") == self.key:
                self.state = old
            else:
                self.log("configuration changed: running every stage again")

    def path(self, name: str) -> Path:
        """A file in the output folder."""
        return self.out / name

    def done(self, name: str, outputs: Sequence[str]) -> bool:
        """Whether stage ``name`` finished and its outputs are all present."""
        return name in self.state["stages"] and all(self.path(o).is_file() for o in outputs)

    def run(self, name: str, outputs: Sequence[str], fn: Callable[[], None]) -> float:
        """Run ``fn`` unless the stage is done; returns the stage's (recorded) seconds."""
        if self.done(name, outputs):
            seconds = self.state["stages"][name]["seconds"]
            self.log(f"[{name}] done earlier ({seconds:.1f} s), skipped")
            return seconds
        self.log(f"[{name}] ...")
        t0 = time.perf_counter()
        fn()
        seconds = time.perf_counter() - t0
        self.state["stages"][name] = {"seconds": seconds, "outputs": list(outputs)}
        write_json(self.state_path, self.state, sort_keys=True)
        self.log(f"[{name}] {seconds:.1f} s")
        return seconds

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per finished stage."""
        return {k: v["seconds"] for k, v in self.state["stages"].items()}
