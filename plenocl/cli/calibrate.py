"""The ``plenocl calibrate`` and ``plenocl refocus`` subcommands (wired into plenocl.cli).

::

    plenocl calibrate white.tif --camera cam.toml --out cam_cal.toml [--diagnostic c.png]
    plenocl refocus raw.tif --camera cam_cal.toml --z -2 0 2 --out stack.tif

The device comes from the top-level ``--device`` option (``args.device``) when present.
"""

from __future__ import annotations

import argparse

import numpy as np

from ..calibration import METHODS
from ..camera import load_camera
from ..io.files import write_tiff


def calibrate_command(args: argparse.Namespace) -> int:
    """Calibrate microlens centres from a white image and write the calibrated camera.

    Parameters
    ----------
    args
        ``white`` (image path), ``camera`` (TOML or preset), ``out`` (TOML path), and
        optionally ``diagnostic`` (PNG path), ``method``, ``fill_missing``.

    Returns
    -------
    int
        0 on success (errors raise ``ValueError``/``FileNotFoundError``).
    """
    from ..calibration import find_centers, save_diagnostic, warn_about
    from ..io.files import read_image

    camera = load_camera(args.camera)
    white = read_image(args.white, args.channel)
    fit = find_centers(white, camera, method=getattr(args, "method", "combined"),
                       fill_missing=getattr(args, "fill_missing", False))
    warn_about(fit)
    calibrated = camera.with_centers(fit.centers)
    calibrated.to_toml(args.out)
    found, total = int(fit.found.sum()), fit.found.size
    print(f"found {found} of {total} microlens centres: rotation {fit.rotation_deg:+.4f} deg, "
          f"pitch {fit.pitch_px[0]:.4f} x {fit.pitch_px[1]:.4f} px, shift "
          f"({fit.shift_px[0]:+.3f}, {fit.shift_px[1]:+.3f}) px, centroid scatter "
          f"{fit.residual_rms_px:.3f} px RMS; wrote {args.out}")
    if getattr(args, "diagnostic", None):
        save_diagnostic(args.diagnostic, white, fit)
        print(f"wrote {args.diagnostic}")
    return 0


def refocus_command(args: argparse.Namespace) -> int:
    """Refocus a raw image at the requested depths and write the focal stack as TIFF.

    Parameters
    ----------
    args
        ``raw`` (image path), ``camera`` (calibrated TOML), ``z`` (list of mm), ``out``
        (TIFF path), optionally ``supersample`` and ``device``.

    Returns
    -------
    int
        0 on success.
    """
    from ..io.files import read_image
    from ..lightfield import LightField

    camera = load_camera(args.camera)
    raw = read_image(args.raw, args.channel)
    lf = LightField(raw, camera, queue=getattr(args, "device", None))
    stack = lf.focal_stack(args.z, supersample=getattr(args, "supersample", 1))
    s = getattr(args, "supersample", 1)
    write_tiff(args.out, np.asarray(stack, np.float32),
               {"z_mm": [float(z) for z in args.z], "alpha": [float(a) for a in
                                                               camera.alpha(args.z)],
                "supersample": s, "axes": "page = depth; rows, columns on the microlens lattice"})
    zs = ", ".join(f"{z:g}" for z in args.z)
    print(f"wrote {args.out}: {len(args.z)} planes of {stack.shape[2]} x {stack.shape[1]} px "
          f"(microlens lattice x {getattr(args, 'supersample', 1)}) at z = {zs} mm")
    return 0


def add_calibrate_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``calibrate`` on an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser("calibrate", help="find the microlens centres in a white image")
    p.add_argument("white", help="white image (TIFF/PNG/NPY) taken with the lens stopped down")
    p.add_argument("--channel", default=None, choices=["r", "g", "b", "luminance"],
                   help="for a colour image: the plane to use, or the Rec. 709 luminance "
                        "(an image whose planes are identical needs none)")
    p.add_argument("--camera", required=True, help="camera TOML file or preset (synthetic, "
                   "paper) with the nominal optics")
    p.add_argument("--out", required=True, help="calibrated camera TOML to write")
    p.add_argument("--diagnostic", default=None,
                   help="PNG of the found centres and the residual map (each lens's centroid "
                        "against the grid model)")
    p.add_argument("--method", choices=list(METHODS), default="combined",
                   help="combined: grid model and each lens's centroid weighted by their "
                        "uncertainties (default); fit: grid model only; centroid: raw "
                        "centroids (the paper's)")
    p.add_argument("--fill-missing", action="store_true",
                   help="give lenses without a spot the grid model's centre instead of NaN")
    p.set_defaults(func=calibrate_command)
    return p


def add_refocus_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``refocus`` on an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser("refocus", help="refocus a raw image at depths (focal stack)")
    p.add_argument("raw", help="raw plenoptic image (TIFF/PNG/NPY)")
    p.add_argument("--channel", default=None, choices=["r", "g", "b", "luminance"],
                   help="for a colour image: the plane to use, or the Rec. 709 luminance "
                        "(an image whose planes are identical needs none)")
    p.add_argument("--camera", required=True, help="calibrated camera TOML file")
    p.add_argument("--z", type=float, nargs="+", required=True,
                   help="object depths in mm (+z away from the camera)")
    p.add_argument("--out", required=True, help="output TIFF stack (float32, one page per z)")
    p.add_argument("--supersample", type=int, default=1,
                   help="output pixels per microlens along each axis (default 1)")
    p.set_defaults(func=refocus_command)
    return p
