"""matplotlib plumbing shared by the figures and the benchmark report (Agg backend,
atomic PNG writes)."""

from __future__ import annotations

from pathlib import Path

from .atomic import atomic_path


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | Path, dpi: int = 110) -> None:
    """Write ``fig`` as a PNG atomically and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    pyplot().close(fig)


#: The figure formats :func:`save_figure` writes, by suffix.
FIGURE_FORMATS = {".png": "png", ".pdf": "pdf"}


def check_figure_path(path: str | Path) -> Path:
    """``path`` as a ``Path``, or a ``ValueError`` when its suffix is no figure format."""
    path = Path(path)
    if path.suffix.lower() not in FIGURE_FORMATS:
        raise ValueError(f"cannot write a figure as {path.name!r}: name it .png (PNG) or "
                         ".pdf (PDF)")
    return path


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` as PNG or PDF (by the suffix, :func:`check_figure_path`) atomically
    and close it; a figure with a layout engine (``constrained_layout``) is saved as laid
    out, others cropped to their contents (which draws them twice)."""
    path = check_figure_path(path)
    tight = None if fig.get_layout_engine() is not None else "tight"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches=tight, format=FIGURE_FORMATS[path.suffix.lower()])
    pyplot().close(fig)
    return path
