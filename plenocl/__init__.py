"""plenocl: volumetric 3-D PIV from a single plenoptic camera, with OpenCL kernels."""

from . import flows, metrics
from .batch import run
from .calibration import calibrate
from .camera import PRESETS, Camera
from .grid import Grid
from .lightfield import LightField
from .opencl.device import DeviceInfo, NoOpenCLError, create_context, describe_devices, get_queue
from .particles import random_particles
from .pipeline import (
    MTESettings,
    PairResult,
    PairSettings,
    TrackSettings,
    bin_tracks,
    calibrate_pose,
    process_pair,
    self_calibrate,
    track,
)
from .piv import PIVResult, PIVSettings, piv3d
from .projection import Projector
from .ptv import Tracks
from .reconstruction import ReconstructionSettings, reconstruct
from .simulate import Simulator, simulate_image, simulate_white_image
from .vectorfield import read_npz, save_field
from .version import __version__
from .volumefile import load_volume, save_volume

__all__ = [
    "PRESETS",
    "Camera",
    "DeviceInfo",
    "Grid",
    "LightField",
    "MTESettings",
    "NoOpenCLError",
    "PIVResult",
    "PIVSettings",
    "PairResult",
    "PairSettings",
    "Projector",
    "ReconstructionSettings",
    "Simulator",
    "TrackSettings",
    "Tracks",
    "__version__",
    "bin_tracks",
    "calibrate",
    "calibrate_pose",
    "create_context",
    "describe_devices",
    "flows",
    "get_queue",
    "load_volume",
    "metrics",
    "piv3d",
    "process_pair",
    "random_particles",
    "read_npz",
    "reconstruct",
    "run",
    "self_calibrate",
    "save_field",
    "save_volume",
    "simulate_image",
    "simulate_white_image",
    "track",
]
