"""Figures of the boundary-layer example, like the paper's Figs. 14-19 (matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_png


def boundary_layer_figures(out: Path, fields, z_wall: float, summary: dict,
                           u_inf: float) -> None:
    """Write ``fig_profile.png``, ``fig_streamwise.png``, ``fig_vorticity.png`` and
    ``fig_vectors3d.png`` into ``out``.

    ``fields`` is ``(measured, true, valid, (x, y, z))``, ``true`` the truth averaged over
    each final window (as the headline error is measured); ``z_wall`` the wall's depth
    (mm) and ``u_inf`` the free-stream velocity (m/s)."""
    out = Path(out)
    meas, true, valid, (x, y, z) = fields
    depth = z_wall - z  # wall distance, mm
    profile_figure(out / "fig_profile.png", depth, summary, u_inf)
    label = "truth, window-averaged"  # the truth the headline error is measured against
    slices_figure(out / "fig_streamwise.png", meas[1], true[1], x, y, depth,
                  "streamwise V (m/s)", label)
    vort_m, vort_t = (_vorticity_magnitude(f, x, y, z) for f in (meas, true))
    slices_figure(out / "fig_vorticity.png", vort_m, vort_t, x, y, depth, "|vorticity| (1/s)",
                  label)
    vectors_figure(out / "fig_vectors3d.png", meas, valid, x, y, z)


def _vorticity_magnitude(vel: np.ndarray, x, y, z) -> np.ndarray:
    """|curl V| of a ``(3, nz, ny, nx)`` field in m/s on mm coordinates (1/s)."""
    g = [np.gradient(np.nan_to_num(vel[c]), z * 1e-3, y * 1e-3, x * 1e-3) for c in range(3)]
    # g[c][a]: d vel_c / d axis a, axes (z, y, x)
    wx = g[2][1] - g[1][0]
    wy = g[0][0] - g[2][2]
    wz = g[1][2] - g[0][1]
    return np.sqrt(wx**2 + wy**2 + wz**2)


def profile_figure(path: Path, depth: np.ndarray, summary: dict, u_inf: float) -> None:
    """The spatially averaged streamwise profile against the truth (paper Fig. 19): wall
    distance upward from the marked wall, error bars the spread over each plane."""
    plt = pyplot()
    prof = summary["profile"]
    fig, ax = plt.subplots(figsize=(5.2, 4.4), constrained_layout=True)
    dense = summary.get("profile_dense", {"analytic": prof["analytic"],
                                          "wall_distance_mm": list(depth)})
    ax.plot(np.array(dense["analytic"]) / u_inf, dense["wall_distance_mm"], "k-", lw=1.2,
            label="Musker mean profile (the flow's mean)")
    ax.plot(np.array(prof["truth_at_vectors"]) / u_inf, depth, "b--", lw=1.0,
            label="truth averaged at the vectors (with eddies)")
    spread = np.array(prof.get("measured_std", np.zeros(len(depth)))) / u_inf
    ax.errorbar(np.array(prof["measured"]) / u_inf, depth, xerr=spread, fmt="o", color="r",
                ms=5, capsize=3, label="plenocl: plane mean ± spread over the plane")
    ax.axhline(0.0, color="0.3", lw=2)
    ax.fill_between([0, 1.2], -0.04 * max(depth), 0.0, color="0.8", hatch="///", lw=0)
    ax.set_xlim(0.0, 1.15)
    ax.set_ylim(-0.04 * max(depth), 1.08 * max(depth))
    ax.text(0.02, 0.01 * max(depth), "wall", fontsize=8, va="bottom")
    ax.set_xlabel("streamwise velocity U / U∞")
    ax.set_ylabel("wall distance y_w (mm)")
    ax.set_title(f"mean profile: RMS error {100 * summary['mean_profile_rms_error']:.1f}% "
                 "of U∞", fontsize=10)
    ax.legend(loc="upper left", fontsize=7, frameon=False)
    save_png(fig, path)


def _shared_limits(*fields: np.ndarray) -> tuple[float, float]:
    """A colour range both fields share, from their 1st to 99th percentiles (no
    saturation by a few outliers)."""
    both = np.concatenate([np.ravel(f)[np.isfinite(np.ravel(f))] for f in fields])
    lo, hi = np.percentile(both, [1, 99]) if both.size else (0.0, 1.0)
    return float(lo), float(hi if hi > lo else lo + 1e-12)


def slices_figure(path: Path, meas: np.ndarray, true: np.ndarray, x, y, depth,
                  label: str, truth_label: str = "truth") -> None:
    """Measured and true fields side by side on three planes parallel to the wall (paper
    Figs. 16-18), one shared colour scale; ``truth_label`` says which truth it is."""
    plt = pyplot()
    picks = np.unique(np.linspace(0, len(depth) - 1, 3).round().astype(int))
    fig, axes = plt.subplots(len(picks), 2, figsize=(6.4, 2.6 * len(picks) + 0.6),
                             squeeze=False, constrained_layout=True, sharex=True, sharey=True)
    lo, hi = _shared_limits(meas, true)
    ext = (x[0], x[-1], y[0], y[-1])
    for row, k in enumerate(picks):
        for col, (field, name) in enumerate(((meas, "plenocl"), (true, truth_label))):
            ax = axes[row, col]
            im = ax.imshow(field[k], origin="lower", extent=ext, vmin=lo, vmax=hi,
                           cmap="viridis", aspect="equal")
            ax.set_title(f"{name}, wall distance {depth[k]:.2f} mm", fontsize=8)
            if row == len(picks) - 1:
                ax.set_xlabel("x spanwise (mm)", fontsize=8)
            if col == 0:
                ax.set_ylabel("y streamwise (mm)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=axes, label=label, shrink=0.9)
    save_png(fig, path)


def vectors_figure(path: Path, vel: np.ndarray, valid: np.ndarray, x, y, z) -> None:
    """3-D velocity fluctuations about the mean profile (the plane mean of each wall
    distance removed), coloured by the streamwise fluctuation, with a colour bar and a
    reference arrow (paper Fig. 14)."""
    plt = pyplot()
    fluct = vel.copy()
    for k in range(vel.shape[1]):
        plane = valid[k]
        if plane.any():
            fluct[:, k] -= np.array([np.mean(vel[c, k][plane]) for c in range(3)])[:, None, None]
    fig = plt.figure(figsize=(7.5, 5.8))
    ax = fig.add_subplot(projection="3d")
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    # three planes parallel to the wall, at most 12 vectors a side: arrows that do not
    # hide each other (every vector of a 9 x 9 x 5 field drawn at once cannot be read)
    planes = np.zeros(len(z), bool)
    planes[np.unique(np.linspace(0, len(z) - 1, min(3, len(z))).round().astype(int))] = True
    step = max(1, max(vel.shape[2:]) // 12)
    sl = (slice(None), slice(None, None, step), slice(None, None, step))
    keep = valid[sl] & planes[:, None, None]
    comps = [f[sl][keep] for f in fluct]
    ref = float(np.percentile(np.sqrt(sum(c**2 for c in comps)), 90)) or 1.0
    scale = 0.8 * step * float(np.diff(x[:2])[0]) / ref  # mm per m/s: the 90th percentile
    lim = float(np.percentile(np.abs(comps[1]), 98)) or 1.0
    norm = plt.Normalize(-lim, lim)
    colours = plt.get_cmap("coolwarm")(norm(comps[1]))
    colours = np.concatenate([colours, np.repeat(colours, 2, axis=0)])  # shaft + 2 head lines
    ax.quiver(xx[sl][keep], yy[sl][keep], zz[sl][keep], *(c * scale for c in comps),
              colors=colours, linewidth=0.8, arrow_length_ratio=0.3)
    x0, y0, z0 = x[0], y[0], z[-1]
    ax.quiver([x0], [y0], [z0], [ref * scale], [0], [0], color="k", linewidth=1.5)
    ax.text(x0, y0, z0, f"  {ref:.2f} m/s", fontsize=8)
    mappable = plt.cm.ScalarMappable(norm=norm, cmap="coolwarm")
    fig.colorbar(mappable, ax=ax, shrink=0.6, pad=0.1,
                 label="streamwise fluctuation v' (m/s)")
    ax.set_xlabel("x spanwise (mm)", labelpad=6)
    ax.set_ylabel("y streamwise (mm)", labelpad=6)
    ax.set_zlabel("z depth (mm; wall at the far face)", labelpad=6)
    ax.tick_params(labelsize=7)
    which = "" if step == 1 else f", one vector in {step} per lateral axis"
    ax.set_title(f"velocity fluctuations about the mean profile on {int(planes.sum())} "
                 f"planes parallel to the wall{which}\n(arrows to scale, reference "
                 f"{ref:.2f} m/s)", fontsize=9)
    save_png(fig, path)


def tracks_figure(path: Path, tracks, speed_unit: str = "mm per dt") -> None:
    """Every track of :class:`plenocl.Tracks` in 3-D (its smoothed positions, mm),
    coloured by speed, with a colour bar."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    plt = pyplot()
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    segments, speeds = [], []
    for pos, vel in zip(tracks.positions, tracks.velocities):
        ok = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(vel), axis=1)
        pts = pos[ok]
        segments += [pts[k:k + 2] for k in range(len(pts) - 1)]
        speed = np.linalg.norm(vel[ok], axis=1)
        speeds += list((speed[1:] + speed[:-1]) / 2)
    lines = Line3DCollection(segments, cmap="viridis", linewidths=1.2)
    lines.set_array(np.asarray(speeds))
    ax.add_collection3d(lines)
    if segments:
        every = np.concatenate(segments)
        for axis, lo, hi in zip("xyz", every.min(axis=0), every.max(axis=0)):
            getattr(ax, f"set_{axis}lim")(lo, hi if hi > lo else lo + 1)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"{len(tracks.positions)} tracks, coloured by speed")
    fig.colorbar(lines, ax=ax, shrink=0.7, label=f"speed ({speed_unit})")
    save_png(fig, path)
