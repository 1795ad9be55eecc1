"""Figures of the boundary-layer example, as the paper shows them (its Figs. 14-19):
the mean profile, contour slices of the streamwise velocity and of the vorticity
magnitude beside the truth with their difference, iso-surfaces of both, and the
velocity fluctuations in 3-D, thinned so they read (:mod:`plenocl.plot`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..io.plotting import pyplot, save_png
from ..plot.data import VectorData
from ..plot.derivatives import vorticity_magnitude
from ..plot.slices import DERIVATIVE_GAPS, comparison_figure
from ..plot.vectors3d import isosurface_figure, vectors_figure

#: The figures :func:`boundary_layer_figures` writes.
FIGURES = ("fig_profile.png", "fig_streamwise.png", "fig_vorticity.png",
           "fig_iso_velocity.png", "fig_iso_vorticity.png", "fig_vectors3d.png")


def wall_frame(vel: np.ndarray, valid: np.ndarray, x, y, z, z_wall: float) -> VectorData:
    """A camera-frame field (x spanwise, y streamwise, z depth towards the wall at
    ``z_wall``) in the wall's frame: the third axis is the wall distance ``z_wall - z``
    (mm) and the third component the wall-normal velocity away from the wall."""
    turned = np.stack([vel[0], vel[1], -vel[2]])
    return VectorData(np.asarray(x, float), np.asarray(y, float), z_wall - np.asarray(z, float),
                      velocity=turned, valid=valid,
                      axis_labels=("x spanwise (mm)", "y streamwise (mm)",
                                   "wall distance (mm)"),
                      component_labels=("u spanwise", "v streamwise", "w wall-normal"))


def boundary_layer_figures(out: Path, fields, z_wall: float, summary: dict,
                           u_inf: float) -> None:
    """Write :data:`FIGURES` into ``out``.

    ``fields`` is ``(measured, true, valid, (x, y, z))``, ``true`` the truth averaged over
    each final window (as the headline error is measured); ``z_wall`` the wall's depth
    (mm) and ``u_inf`` the free-stream velocity (m/s)."""
    out = Path(out)
    meas, true, valid, (x, y, z) = fields
    measured = wall_frame(meas, valid, x, y, z, z_wall)
    truth = wall_frame(true, np.ones_like(valid), x, y, z, z_wall)
    profile_figure(out / "fig_profile.png", z_wall - z, summary, u_inf)
    label = "truth, window-averaged"  # the truth the headline error is measured against
    comparison_figure(out / "fig_streamwise.png", measured, measured.component("v"),
                      truth.component("v"), measured.label("v"), "x", truth_label=label,
                      vectors=measured)
    # the same least-squares derivatives on the measured and the window-averaged truth
    vort_m, vort_t = (vorticity_magnitude(f.velocity, f.valid, f.x, f.y, f.z)
                      for f in (measured, truth))
    comparison_figure(out / "fig_vorticity.png", measured, vort_m, vort_t,
                      "vorticity magnitude |ω| (1/s)", "x", truth_label=label,
                      gap_note=DERIVATIVE_GAPS)
    levels = [round(f * u_inf, 2) for f in (0.6, 0.75, 0.9)]
    isosurface_figure(out / "fig_iso_velocity.png", measured, measured.component("v"),
                      levels, measured.label("v"),
                      "iso-surfaces of the streamwise velocity (0.6, 0.75, 0.9 U∞)",
                      arrows=150)
    # the strongest tenth to third of the field: lower levels fill the volume
    vort_levels = [float(f"{v:.2g}") for v in np.nanpercentile(vort_m, [70, 85, 95])]
    isosurface_figure(out / "fig_iso_vorticity.png", measured, vort_m, vort_levels,
                      "|ω| (1/s)", "iso-surfaces of the vorticity magnitude "
                      "(its 70th, 85th, 95th percentiles)")
    vectors_figure(out / "fig_vectors3d.png", fluctuations(measured), colour="v",
                   title="velocity fluctuations about the mean profile (each wall-parallel "
                         "plane's mean removed)")


def fluctuations(data: VectorData) -> VectorData:
    """The field less each wall-parallel plane's mean of its valid vectors."""
    vel = np.where(data.valid, data.velocity, np.nan)
    counts = data.valid.sum(axis=(1, 2))
    means = np.where(counts > 0, np.nansum(vel, axis=(2, 3)) / np.maximum(counts, 1), 0.0)
    return replace(data.with_velocity(data.velocity - means[:, :, None, None]),
                   component_labels=tuple(c.replace(" ", "' ", 1) if " " in c else f"{c}'"
                                          for c in data.component_labels))


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
    ax.set_xlabel(f"streamwise velocity U / U∞ (U∞ = {u_inf:g} m/s)")
    ax.set_ylabel("wall distance y_w (mm)")
    ax.set_title(f"mean profile: RMS error {100 * summary['mean_profile_rms_error']:.1f}% "
                 "of U∞", fontsize=10)
    ax.legend(loc="upper left", fontsize=7, frameon=False)
    save_png(fig, path)
