"""The package's layering (docs/architecture.md): read from the source's own imports.

Stages (calibration, simulation, light field, projection, reconstruction, PIV, metrics)
sit side by side: none imports another; what two of them share lives in the model layer
below them (``optics/``, ``camera``, ``grid``, ``vectorfield``, ...). The files layer
``io/`` knows no stage (nor anything of plenocl outside itself). Nothing below the
command line imports the package root (``plenocl/__init__.py`` re-exports the public
names for users, and importing it from inside would hide a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "plenocl"
STAGES = frozenset({"calibration", "simulate", "lightfield", "projection", "reconstruction",
                    "piv", "metrics"})
#: modules allowed to import the package root: the entry points above everything
ENTRY_POINTS = ("plenocl.cli", "plenocl.__main__")


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    name = ".".join(rel.parts)
    return name.removesuffix(".__init__")


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """``(module imported from, names)`` of every import in ``path``, relative ones
    resolved against the file's package."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            module = ".".join(base + [node.module]) if node.level and node.module else (
                ".".join(base) if node.level else node.module or "")
            found.append((module, [alias.name for alias in node.names]))
    return found


def _targets(module: str, names: list[str]) -> list[str]:
    """The plenocl modules an import reaches: ``from plenocl.piv import peaks`` reaches
    ``plenocl.piv.peaks``, ``from plenocl.piv.peaks import x`` reaches the module."""
    subs = [f"{module}.{n}" for n in names if _is_module(f"{module}.{n}")]
    return subs or [module]


def _is_module(dotted: str) -> bool:
    path = PACKAGE.parent.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _stage(dotted: str) -> str | None:
    parts = dotted.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "plenocl" and parts[1] in STAGES else None


def _edges() -> list[tuple[str, str, list[str]]]:
    edges = []
    for path in sorted(PACKAGE.rglob("*.py")):
        source = _module_name(path)
        for module, names in _imports(path):
            if module == "plenocl" or module.startswith("plenocl."):
                edges += [(source, t, names) for t in _targets(module, names)]
    return edges


def test_the_rules_see_the_imports():
    """The reader finds the imports that are there (a reader that found none would pass
    every rule below)."""
    edges = _edges()
    assert ("plenocl.projection.projector", "plenocl.grid", ["Grid"]) in edges
    assert any(s.startswith("plenocl.cli") and t.startswith("plenocl.pipeline")
               for s, t, _ in edges)
    assert _stage("plenocl.piv.peaks") == "piv" and _stage("plenocl.grid") is None


def test_no_stage_imports_another_stage():
    bad = [f"{s} -> {t}" for s, t, _ in _edges()
           if _stage(s) and _stage(t) and _stage(s) != _stage(t)]
    assert not bad, "stages import each other (share through the model layer): " + "; ".join(bad)


def test_files_layer_knows_no_stage():
    """io/ writes and reads arrays and numbers: it imports nothing of plenocl outside
    itself (no stage, and no model either: ``vectorfield``, ``volumefile`` sit above it)."""
    bad = [f"{s} -> {t}" for s, t, _ in _edges()
           if s.startswith("plenocl.io") and not t.startswith("plenocl.io")]
    assert not bad, "io/ imports from outside io/: " + "; ".join(bad)


def test_nothing_below_the_command_line_imports_the_package_root():
    bad = [f"{s} imports {names} from the package root" for s, t, names in _edges()
           if t == "plenocl" and s != "plenocl" and not s.startswith(ENTRY_POINTS)]
    assert not bad, "; ".join(bad)
