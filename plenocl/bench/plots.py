"""Plots of the benchmark report (matplotlib, Agg backend): Pareto fronts and scaling."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_png


def _pareto_panel(ax, xs, ys, front, label: str, colour) -> None:
    """Points of one series, its front highlighted and joined by a step line."""
    xs, ys, front = np.asarray(xs, float), np.asarray(ys, float), np.asarray(front, bool)
    ax.scatter(xs[~front], ys[~front], s=22, color=colour, alpha=0.45)
    ax.scatter(xs[front], ys[front], s=60, color=colour, edgecolor="black", zorder=3,
               label=f"{label} (front)")
    order = np.argsort(xs[front])
    ax.plot(xs[front][order], ys[front][order], color=colour, lw=1.2, drawstyle="steps-post")


def _annotate(ax, xs, ys, labels) -> None:
    """Each point's number (the ``#`` column of the report's table)."""
    for x, y, text in zip(xs, ys, labels):
        ax.annotate(str(text), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")


def _log_axes(ax, x: bool = True, y: bool = False) -> None:
    """Log scale with ticks at 1, 2, 5 per decade, plainly labelled (no minor labels)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for on, axis, setter in ((x, ax.xaxis, ax.set_xscale), (y, ax.yaxis, ax.set_yscale)):
        if on:
            setter("log")
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(NullFormatter())


def _short(n: float) -> str:
    """``2048`` as ``2k``, ``2890000`` as ``2.9M``."""
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if n >= scale:
            return f"{n / scale:.3g}{suffix}"
    return f"{n:g}"


def plot_recon_pareto(rows: list[dict], path: Path) -> None:
    """Time vs recovery and time vs Q of the reconstruction settings, one colour per
    particle count; front points (``front_recovery``, ``front_q``) highlighted."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    counts = sorted({r["count"] for r in rows})
    colours = plt.cm.viridis(np.linspace(0.1, 0.85, len(counts)))
    for ax, key, flag, name in ((axes[0], "recovery", "front_recovery", "particle recovery"),
                                (axes[1], "q", "front_q", "Q")):
        for count, colour in zip(counts, colours):
            sub = [r for r in rows if r["count"] == count]
            xs, ys = [r["seconds"] for r in sub], [r[key] for r in sub]
            _pareto_panel(ax, xs, ys, [r[flag] for r in sub], f"{count} particles", colour)
            _annotate(ax, xs, ys, [r["number"] for r in sub])
        _log_axes(ax)
        ax.set_xlabel("reconstruction time (s)")
        ax.set_ylabel(name)
        ax.set_title(f"time vs {name}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_png(fig, path, dpi=100)


def plot_piv_pareto(rows: list[dict], path: Path) -> None:
    """Time vs RMS error of the PIV settings, one panel per flow; front highlighted."""
    plt = pyplot()
    names = list(dict.fromkeys(r["flow"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 4.5), squeeze=False)
    for ax, name in zip(axes[0], names):
        sub = [r for r in rows if r["flow"] == name]
        xs, ys = [r["seconds"] for r in sub], [r["rms"] for r in sub]
        _pareto_panel(ax, xs, ys, [r["front"] for r in sub], "settings", "tab:blue")
        _annotate(ax, xs, ys, [r["number"] for r in sub])
        _log_axes(ax, y=True)
        ax.set_xlabel("PIV time (s)")
        ax.set_ylabel("interior RMS error (voxel)")
        ax.set_title(name)
        ax.grid(True, which="both", alpha=0.3)
    save_png(fig, path, dpi=100)


def plot_scaling(data: dict, labels: dict, path: Path) -> None:
    """Log-log time (and memory, right axis) against each size axis with fitted slopes.

    ``data[axis]`` lists points ``{"n", "seconds", "bytes"}``; ``labels[axis]`` is
    ``(what is counted, what memory is measured)``.
    """
    plt = pyplot()
    cols = min(2, len(data))
    rows = -(-len(data) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 4.4 * rows), squeeze=False)
    for ax, (axis, pts) in zip(axes.ravel(), data.items()):
        n = np.array([p["n"] for p in pts], float)
        _fit_series(ax, n, np.array([p["seconds"] for p in pts]), "time", "tab:blue", "o-")
        ax.set_ylabel("time (s)")
        mem = ax.twinx()
        _fit_series(mem, n, np.array([p["bytes"] for p in pts]) / 2**20,
                    f"memory: {labels[axis][1]}", "tab:orange", "s--")
        mem.set_ylabel("memory (MiB)")
        ax.set_xticks(n, [_short(v) for v in n])
        ax.set_xlabel(labels[axis][0])
        ax.grid(True, which="both", alpha=0.3)
        lines = [ln for ln in ax.get_lines() + mem.get_lines()
                 if not ln.get_label().startswith("_")]
        ax.legend(lines, [ln.get_label() for ln in lines], fontsize=7, loc="upper left")
    fig.tight_layout()
    save_png(fig, path, dpi=100)


def _fit_series(ax, n: np.ndarray, y: np.ndarray, label: str, colour: str, style: str) -> None:
    """Measured points and the least-squares power law through them, on log-log axes."""
    ok = (n > 0) & (y > 0)
    slope = np.nan
    if ok.sum() >= 2:
        slope, icpt = np.polyfit(np.log(n[ok]), np.log(y[ok]), 1)
        ax.plot(n[ok], np.exp(icpt) * n[ok] ** slope, color=colour, lw=0.8, alpha=0.6,
                label="_fit")
    ax.plot(n, y, style, color=colour, label=f"{label} (slope {slope:.2f})", ms=5)
    _log_axes(ax, y=True)
    if ok.any() and y[ok].max() < 2 * y[ok].min():  # nearly constant: show it flat
        ax.set_ylim(y[ok].min() / 3, y[ok].max() * 3)
