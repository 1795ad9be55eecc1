"""The ``plenocl calibrate`` and ``plenocl refocus`` subcommands (wired into plenocl.cli).

::

    plenocl calibrate white.tif --camera cam.toml --out cam_cal.toml [--diagnostic c.png]
    plenocl refocus raw.tif --camera cam_cal.toml --z -2 0 2 --out stack.tif

The device comes from the top-level ``--device`` option (``args.device``) when present.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from ..calibration import APERTURES, METHODS
from ..camera import load_camera
from ..io.centres import write_centers_csv
from ..io.files import write_tiff
from .frames import add_frame_options, camera_for_frames, read_frame


def calibrate_command(args: argparse.Namespace) -> int:
    """Calibrate microlens centres from a white image and write the calibrated camera.

    Parameters
    ----------
    args
        ``white`` (image path), ``camera`` (TOML or preset), ``out`` (TOML path), and
        optionally ``diagnostic`` (PNG path), ``method``, ``fill_missing``, ``aperture``.

    Returns
    -------
    int
        0 on success (errors raise ``ValueError``/``FileNotFoundError``).
    """
    from ..calibration import find_centers, save_diagnostic, save_failure_diagnostic, warn_about

    camera = camera_for_frames(args, load_camera(args.camera))
    if getattr(args, "centres", None):
        return _import_centres(args, camera)
    if args.white is None:
        raise ValueError("give a white image, or --centres CSV to take the centres from "
                         "another tool's calibration")
    white = read_frame(args, args.white, camera, white=True)
    try:
        fit = find_centers(white, camera, method=getattr(args, "method", "combined"),
                           fill_missing=getattr(args, "fill_missing", False),
                           aperture=getattr(args, "aperture", "auto"))
    except ValueError as exc:
        if getattr(args, "diagnostic", None):  # when it helps most
            save_failure_diagnostic(args.diagnostic, white, camera, str(exc))
            print(f"calibration failed; wrote {args.diagnostic} (what was found)",
                  file=sys.stderr)
        raise
    warn_about(fit)
    calibrated = fit.camera.with_centers(fit.centers)
    calibrated.to_toml(args.out)
    if getattr(args, "centres_out", None):
        write_centers_csv(args.centres_out, fit.centers)
    found, total = int(fit.found.sum()), fit.found.size
    print(f"found {found} of {total} microlens centres: rotation {fit.rotation_deg:+.4f} deg, "
          f"pitch {fit.pitch_px[0]:.4f} x {fit.pitch_px[1]:.4f} px, shift "
          f"({fit.shift_px[0]:+.3f}, {fit.shift_px[1]:+.3f}) px, centroid scatter "
          f"{fit.residual_rms_px:.3f} px RMS; wrote {args.out}")
    if getattr(args, "diagnostic", None):
        save_diagnostic(args.diagnostic, white, fit)
        print(f"wrote {args.diagnostic}")
    return 0


def _import_centres(args: argparse.Namespace, camera) -> int:
    """``plenocl calibrate --centres CSV``: the camera calibrated with another tool's
    centres (:func:`plenocl.calibration.import_centers`), written to ``args.out``."""
    from ..calibration import import_centers

    if args.white is not None:
        raise ValueError("give either a white image or --centres CSV, not both")
    if getattr(args, "diagnostic", None):
        raise ValueError("--diagnostic draws a white image's fit: with --centres there is "
                         "none; leave --diagnostic out (or calibrate from the white image)")
    calibrated = import_centers(args.centres, camera)
    calibrated.to_toml(args.out)
    found = int(np.isfinite(calibrated.microlens_centers).all(-1).sum())
    print(f"imported {found} of {calibrated.microlens_centers[..., 0].size} microlens "
          f"centres from {args.centres}; wrote {args.out}")
    if getattr(args, "centres_out", None):  # another tool's centres (an LFIT .mat) as CSV
        write_centers_csv(args.centres_out, calibrated.microlens_centers)
        print(f"wrote {args.centres_out}")
    return 0


def _pixel_mm(positions: np.ndarray) -> tuple[float, float]:
    """``(rows, columns)`` spacing (mm) of the refocused pixels' array-plane positions
    ``(H, W, 2)``: their median steps down the columns and along the rows."""
    down = np.linalg.norm(np.diff(positions, axis=0), axis=-1)
    along = np.linalg.norm(np.diff(positions, axis=1), axis=-1)
    return float(np.median(down)), float(np.median(along))


def refocus_command(args: argparse.Namespace) -> int:
    """Refocus a raw image at the requested depths and write the focal stack as TIFF.

    Parameters
    ----------
    args
        ``raw`` (image path), ``camera`` (calibrated TOML), ``z`` (list of mm), ``out``
        (TIFF path), optionally ``upsample`` (output pixels per microlens) and
        ``device``.

    Returns
    -------
    int
        0 on success.
    """
    from ..lightfield import LightField

    if getattr(args, "supersample", None) is not None:
        raise ValueError("refocus takes --upsample N (output pixels per microlens); "
                         "--supersample means lateral sub-voxels, in reconstruct")
    camera = camera_for_frames(args, load_camera(args.camera))
    _check_refocus_depths(camera, args.z)
    raw = read_frame(args, args.raw, camera)
    lf = LightField(raw, camera, queue=getattr(args, "device", None))
    s = getattr(args, "upsample", 1)
    stack = lf.focal_stack(args.z, supersample=s)
    pixel = _pixel_mm(lf.output_positions_mm(s))
    write_tiff(args.out, np.asarray(stack, np.float32),
               {"z_mm": [float(z) for z in args.z], "alpha": [float(a) for a in
                                                               camera.alpha(args.z)],
                "upsample": s, "axes": "page = depth; rows, columns on the microlens lattice",
                "pixel_mm": list(pixel), "pixel_mm_note": "(rows, columns) on the array "
                "plane: a hexagonal array's rows are 0.866 of its columns"}, pixel_mm=pixel)
    zs = ", ".join(f"{z:g}" for z in args.z)
    print(f"wrote {args.out}: {len(args.z)} planes of {stack.shape[2]} x {stack.shape[1]} px "
          f"(microlens lattice x {s}) at z = {zs} mm")
    return 0


def _check_refocus_depths(camera, depths) -> None:
    """Refuse depths the camera does not resolve (as ``plenocl grid`` refuses a range
    beyond them): a plane refocused there is no image of that depth."""
    from ..optics.depthrange import resolved_depth_range

    near, far = resolved_depth_range(camera)
    outside = [float(z) for z in depths if not near <= float(z) <= far]
    if outside:
        raise ValueError(f"--z {', '.join(f'{z:g}' for z in outside)} mm lies beyond the "
                         f"depths the camera resolves, [{near:.2f}, {far:.2f}] mm: refocus "
                         "within them")


def add_calibrate_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``calibrate`` on an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser("calibrate", help="find the microlens centres in a white image")
    p.add_argument("white", nargs="?", default=None,
                   help="white image (TIFF/PNG/NPY): main lens stopped down (spots) or "
                   "at full aperture (disks, as vendors supply them); leave out with --centres")
    add_frame_options(p)
    p.add_argument("--camera", required=True, help="camera TOML file or preset (synthetic, "
                   "paper) with the nominal optics")
    p.add_argument("--out", required=True, help="calibrated camera TOML to write")
    p.add_argument("--diagnostic", default=None,
                   help="PNG of the found centres and the residual map (each lens's centroid "
                        "against the grid model)")
    p.add_argument("--method", choices=list(METHODS), default="combined",
                   help="combined: grid model and each lens's centroid (at full aperture: "
                        "its disk fitted with its neighbours') weighted by their "
                        "uncertainties (default); fit: grid model only; centroid: raw "
                        "centroids (the paper's)")
    p.add_argument("--fill-missing", action="store_true",
                   help="give lenses without a spot the grid model's centre instead of NaN")
    p.add_argument("--aperture", choices=list(APERTURES), default="auto",
                   help="stopped: one small spot per lens; full: one disk filling each lens "
                        "(vendor white images); auto (default): full when most pixels are "
                        "bright")
    p.add_argument("--centres", metavar="FILE", default=None,
                   help="take the centres from another tool's calibration instead of a white "
                        "image: a CSV with the header lens_col,lens_row,x_px,y_px (lens "
                        "indices from 0, pixel centres from 0; docs/design.md §3), or LFIT's "
                        "calibration file (*_calData.mat)")
    p.add_argument("--centres-out", metavar="CSV", default=None,
                   help="also write the centres found as such a CSV (for other tools)")
    p.set_defaults(func=calibrate_command)
    return p


def add_refocus_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``refocus`` on an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser("refocus", help="refocus a raw image at depths (focal stack)")
    p.add_argument("raw", help="raw plenoptic image (TIFF/PNG/NPY)")
    add_frame_options(p)
    p.add_argument("--camera", required=True, help="calibrated camera TOML file")
    p.add_argument("--z", type=float, nargs="+", required=True,
                   help="object depths in mm (+z away from the camera)")
    p.add_argument("--out", required=True, help="output TIFF stack (float32, one page per z)")
    p.add_argument("--upsample", type=int, default=1,
                   help="output pixels per microlens along each axis (default 1)")
    p.add_argument("--supersample", type=int, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=refocus_command)
    return p
