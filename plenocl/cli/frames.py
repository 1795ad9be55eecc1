"""The options of every command that reads camera frames, and reading one with them:
a colour plane (``--channel``), a dark frame and a flat field (``--dark``, ``--flat``),
and a region of interest (``--crop``) recorded with the camera."""

from __future__ import annotations

import argparse

import numpy as np

from ..camera import Camera
from ..io.files import CHANNELS, read_image
from ..pipeline.frames import load_frame


def add_frame_options(p: argparse.ArgumentParser) -> None:
    """Add ``--channel``, ``--dark``, ``--flat`` and ``--crop`` to a command."""
    p.add_argument("--channel", default=None, choices=list(CHANNELS),
                   help="for a colour image: the plane to use, or the Rec. 709 luminance "
                        "(an image whose planes are identical needs none)")
    p.add_argument("--dark", default=None,
                   help="dark frame (lens capped, same exposure) subtracted from each frame")
    p.add_argument("--flat", default=None,
                   help="flat field (uniformly lit frame) each frame is divided by, after "
                        "the dark frame, normalised to a mean of 1")
    p.add_argument("--crop", type=int, nargs=4, default=None,
                   metavar=("COLUMN", "ROW", "WIDTH", "HEIGHT"),
                   help="region of interest of the frames; recorded in the calibrated "
                        "camera, so later frames are cut alike without it")


def camera_for_frames(args: argparse.Namespace, camera: Camera) -> Camera:
    """``camera`` through ``--crop``: cropped if not calibrated yet, or calibrated on
    the whole sensor (its centres kept, :meth:`Camera.cropped`); a camera calibrated on
    a region keeps it, and a different ``--crop`` is refused."""
    crop = args.crop
    if not crop:
        return camera
    origin, size = tuple(crop[:2]), tuple(crop[2:])
    if not camera.calibrated or camera.crop_origin is None:
        return camera.cropped(origin, size)
    if camera.crop_origin == origin and camera.pixels == size:
        return camera
    raise ValueError(f"--crop {' '.join(map(str, crop))} is not the region the camera was "
                     f"calibrated on ({camera.crop_origin}, {camera.pixels} px): leave "
                     "--crop out (the camera cuts frames to its region itself)")


def read_frame(args: argparse.Namespace, path, camera: Camera, white: bool = False
               ) -> np.ndarray:
    """One frame as ``camera`` sees it: read with ``--channel``, corrected by ``--dark``
    and ``--flat``, cut to the camera's region of interest; a blank or (unless
    ``white``) saturated frame is refused naming the file."""
    dark, flat = (read_image(name, args.channel) if name else None
                  for name in (args.dark, args.flat))
    return load_frame(path, camera, args.channel, dark, flat, white)
