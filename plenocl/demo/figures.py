"""Figures of the boundary-layer example, like the paper's Figs. 14-19 (matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_png


def boundary_layer_figures(out: Path, fields, z_wall: float, summary: dict,
                           u_inf: float) -> None:
    """Write ``fig_profile.png``, ``fig_streamwise.png``, ``fig_vorticity.png`` and
    ``fig_vectors3d.png`` into ``out``.

    ``fields`` is ``(measured, true, valid, (x, y, z))`` as
    :func:`plenocl.demo.boundary_layer.measured_and_true` returns it; ``z_wall`` the wall's
    depth (mm) and ``u_inf`` the free-stream velocity (m/s)."""
    out = Path(out)
    meas, true, valid, (x, y, z) = fields
    depth = z_wall - z  # wall distance, mm
    profile_figure(out / "fig_profile.png", depth, summary, u_inf)
    slices_figure(out / "fig_streamwise.png", meas[1], true[1], x, y, z, "streamwise V (m/s)")
    vort_m, vort_t = (_vorticity_magnitude(f, x, y, z) for f in (meas, true))
    slices_figure(out / "fig_vorticity.png", vort_m, vort_t, x, y, z, "|vorticity| (1/s)")
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
    """The spatially averaged streamwise profile against the truth (paper Fig. 19)."""
    plt = pyplot()
    prof = summary["profile"]
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(np.array(prof["analytic"]) / u_inf, depth, "k-", label="truth: mean profile")
    ax.plot(np.array(prof["truth_at_vectors"]) / u_inf, depth, "b--",
            label="truth at the vectors")
    ax.plot(np.array(prof["measured"]) / u_inf, depth, "ro", label="plenocl")
    ax.set_xlabel("U / U∞")
    ax.set_ylabel("wall distance (mm)")
    ax.set_title(f"mean profile: RMS error {100 * summary['mean_profile_rms_error']:.1f}% U∞")
    ax.legend(loc="upper left", fontsize=8)
    save_png(fig, path)


def slices_figure(path: Path, meas: np.ndarray, true: np.ndarray, x, y, z, label: str) -> None:
    """Measured and true fields on three depth slices (paper Figs. 16-18)."""
    plt = pyplot()
    picks = np.unique(np.linspace(0, len(z) - 1, 3).round().astype(int))
    fig, axes = plt.subplots(2, len(picks), figsize=(3.2 * len(picks), 5.6), squeeze=False)
    lo, hi = np.nanmin(true), np.nanmax(true)
    ext = (x[0], x[-1], y[0], y[-1])
    for col, k in enumerate(picks):
        for row, (field, name) in enumerate(((meas, "plenocl"), (true, "truth"))):
            ax = axes[row, col]
            im = ax.imshow(field[k], origin="lower", extent=ext, vmin=lo, vmax=hi,
                           cmap="viridis", aspect="equal")
            ax.set_title(f"{name}, z = {z[k]:.1f} mm", fontsize=9)
            ax.set_xlabel("x spanwise (mm)", fontsize=8)
            ax.set_ylabel("y streamwise (mm)", fontsize=8)
    fig.colorbar(im, ax=axes, label=label, shrink=0.8)
    save_png(fig, path)


def vectors_figure(path: Path, vel: np.ndarray, valid: np.ndarray, x, y, z) -> None:
    """3-D vectors coloured by streamwise velocity with an iso-surface (paper Fig. 14)."""
    from skimage.measure import marching_cubes

    plt = pyplot()
    fig = plt.figure(figsize=(7, 5.5))
    ax = fig.add_subplot(projection="3d")
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    step = max(1, max(vel.shape[1:]) // 12)
    sl = (slice(None, None, step),) * 3
    keep = valid[sl]
    ax.quiver(xx[sl][keep], yy[sl][keep], zz[sl][keep], vel[0][sl][keep], vel[1][sl][keep],
              vel[2][sl][keep], length=0.4 * (x[-1] - x[0]) / max(len(x), 1) / 2,
              normalize=False, color="k", linewidth=0.5)
    v = np.nan_to_num(vel[1], nan=float(np.nanmean(vel[1])))
    level = float(np.percentile(v, 30))
    if v.min() < level < v.max() and min(v.shape) >= 2:
        verts, faces, _, _ = marching_cubes(v, level)
        pts = [np.interp(verts[:, i], np.arange(len(a)), a) for i, a in enumerate((z, y, x))]
        ax.plot_trisurf(pts[2], pts[1], faces, pts[0], color="tab:orange", alpha=0.35)
    ax.set_xlabel("x spanwise (mm)")
    ax.set_ylabel("y streamwise (mm)")
    ax.set_zlabel("z depth (mm)")
    ax.set_title(f"velocity vectors; iso-surface V = {level:.2f} m/s")
    save_png(fig, path)
