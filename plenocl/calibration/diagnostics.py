"""The calibration's diagnostic figures: the found centres and the residual map
(:func:`save_diagnostic`), and what a failed calibration saw
(:func:`save_failure_diagnostic`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from .checks import image_pitch_px
from .result import CenterFit
from .spots import detect_spots, remove_hot_pixels


def save_diagnostic(path: str | Path, white_image, fit: CenterFit) -> None:
    """Write a PNG: the white image with the found centres (green) and missing lenses
    (red), and the residual map, each lens's centroid offset from the grid model (px),
    colour for its size and an arrow for its direction, with the estimated centroid
    noise and lattice scatter in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    img = np.asarray(white_image, dtype=np.float64)
    fig, (ax, res) = plt.subplots(1, 2, figsize=(13, 6.8), dpi=130)
    rows, cols = fit.found.shape
    c = fit.centers[fit.found]
    miss = fit.model[~fit.found]
    half = _zoom_panel(ax, img, np.nanmean(fit.model.reshape(-1, 2), 0),
                       float(np.mean(fit.pitch_px)))
    ax.plot(c[:, 0], c[:, 1], "x", color="lime", ms=7, mew=1.0, label="centres")
    ax.plot(miss[:, 0], miss[:, 1], "o", mfc="none", color="red", ms=9, mew=1.0,
            label=f"no spot ({fit.n_missing} in all)")
    ax.set_title(f"central {2 * half} x {2 * half} lenses of {cols} x {rows}: "
                 f"{int(fit.found.sum())} centres found in all, rotation "
                 f"{fit.rotation_deg:.3f}°", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    _residual_panel(fig, res, fit)
    _save_figure(fig, path)


def _zoom_panel(ax, img: np.ndarray, centre, pitch: float, half: int = 6) -> int:
    """The image around ``centre`` (``half`` lenses each way, so that single spots and
    crosses stay readable on any array), square-root scaled; returns ``half``."""
    h, w = img.shape
    x0, x1 = max(centre[0] - half * pitch, -0.5), min(centre[0] + half * pitch, w - 0.5)
    y0, y1 = max(centre[1] - half * pitch, -0.5), min(centre[1] + half * pitch, h - 0.5)
    ax.imshow(np.sqrt(np.clip(img, 0, None) / max(img.max(), 1e-30)), cmap="gray",
              interpolation="nearest")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    return half


def _save_figure(fig, path) -> None:
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_path

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def save_failure_diagnostic(path: str | Path, white_image, camera: Camera,
                            message: str) -> None:
    """Write a PNG of what a calibration that failed saw: the whole image with the bright
    spots found and the outline of the array the camera file describes, and the centre
    enlarged with the spots (green) and the camera's nominal centres (red), the reason
    in the title. It shows a wrong pitch, count, rotation or a white image that is not
    one at a glance."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = np.asarray(white_image, dtype=np.float64)
    pitch = image_pitch_px(camera)
    try:
        peaks = detect_spots(remove_hot_pixels(img, pitch), pitch)[0]
    except (ValueError, IndexError):
        peaks = np.empty((0, 2))
    nominal = camera.ideal_microlens_centers().reshape(-1, 2)
    fig, (whole, zoom) = plt.subplots(1, 2, figsize=(13, 7.2), dpi=110)
    whole.imshow(np.sqrt(np.clip(img, 0, None) / max(img.max(), 1e-30)), cmap="gray")
    lo, hi = nominal.min(0) - pitch / 2, nominal.max(0) + pitch / 2
    whole.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]],
               color="red", lw=1, label="the camera file's array")
    whole.legend(loc="upper right", fontsize=7)
    whole.set_title(f"{len(peaks)} bright spots found; the camera file expects "
                    f"{camera.ml_count[0]} x {camera.ml_count[1]} lenses {pitch:.2f} px "
                    "apart", fontsize=9)
    _zoom_panel(zoom, img, np.array(img.shape[::-1]) / 2 - 0.5, pitch)
    zoom.plot(peaks[:, 0], peaks[:, 1], "+", color="lime", ms=8, label="spots found")
    zoom.plot(nominal[:, 0], nominal[:, 1], "o", mfc="none", color="red", ms=8,
              label="nominal centres")
    zoom.legend(loc="upper right", fontsize=7)
    fig.suptitle("calibration failed: " + "\n".join(textwrap.wrap(message, 150)),
                 fontsize=8)
    _save_figure(fig, path)


def _residual_panel(fig, ax, fit: CenterFit) -> None:
    """Each lens's centroid minus the grid model, on the lens grid (rows x columns)."""
    offset = np.where(fit.found[..., None], fit.centroids - fit.model, np.nan)
    size = np.hypot(offset[..., 0], offset[..., 1])
    top = max(float(np.nanpercentile(size, 99)) if np.isfinite(size).any() else 0.0, 1e-3)
    im = ax.imshow(size, cmap="viridis", vmin=0, vmax=top, interpolation="nearest")
    rows, cols = size.shape
    if rows * cols <= 4000:  # arrows stay readable up to ~60 x 60 lenses
        ky, kx = np.mgrid[0:rows, 0:cols]
        ax.quiver(kx, ky, offset[..., 0], -offset[..., 1], color="white", angles="xy",
                  scale_units="xy", scale=top / 0.45, width=0.003)
    out = fit.found & ~fit.inlier
    ax.plot(*np.nonzero(out.T), "s", mfc="none", color="orange", ms=4, mew=0.6,
            label=f"left out of the fit ({int(out.sum())})")
    if out.any():
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("lens column kx")
    ax.set_ylabel("lens row ky")
    ax.set_title(f"centroid - grid model: {fit.residual_rms_px:.3f} px RMS (centres: "
                 f"{fit.method})\ncentroid noise {float(np.nanmedian(fit.noise_px)):.3f} px, "
                 f"lenses' scatter about the lattice {fit.lattice_scatter_px:.3f} px (per axis)",
                 fontsize=8)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, label="offset (px)")
