"""What every run of an experiment file makes before its work: the camera (calibrated
from a white image if one is given), the grid, and the record of the configuration used
in the output folder (``experiment_used.toml``, ``camera_used.toml``, ``grid_used.toml``);
shared by the pairs' run (:mod:`plenocl.batch.run`) and the tracking run
(:mod:`plenocl.batch.tracking`)."""

from __future__ import annotations

import warnings
from pathlib import Path

from ..camera import Camera
from ..camera.pose import check_distinct_views
from ..grid import Grid
from ..io.tomlfile import write_toml
from ..optics.depthrange import check_grid
from ..options import is_integer
from ..piv import PIVSettings
from ..piv.multipass import auto_windows, window_passes
from ..version import __version__
from .config import Experiment


def check_cluster_device(queue, workers: int | None, scheduler: str | None) -> None:
    """A cluster's workers are a positive number of processes, and on a cluster the
    device is a name each worker looks up, never an OpenCL object: refused before the
    run writes anything."""
    if workers is not None and not (is_integer(workers) and workers >= 1):
        raise ValueError(f"workers must be a positive number of processes (--workers N), "
                         f"got {workers!r}; without it the pairs run in this process")
    if (workers or scheduler) and not (queue is None or isinstance(queue, str)):
        raise ValueError("with --workers or --scheduler the device must be a name each "
                         "worker looks up (e.g. 'cpu' or 'NVIDIA'), not an OpenCL object")


def run_cameras(exp: Experiment, queue, log) -> list[Camera]:
    """The experiment's cameras (:func:`run_camera`; several: each ``[[cameras]]``
    table's, its pose kept through its calibration)."""
    tables = exp.cameras or (exp["camera"],)
    cameras = [run_camera(exp, queue, log, table) for table in tables]
    if len(cameras) > 1:  # before any frame is read: every pair would fail at it
        check_distinct_views(cameras)
    return cameras


def run_camera(exp: Experiment, queue, log, cam: dict | None = None) -> Camera:
    """The experiment's camera (``cam``: a ``[[cameras]]`` table instead of
    ``[camera]``), calibrated from its white image when one is given (the white image
    read as a frame: its channel and dark frame, not the flat field)."""
    from ..camera import load_camera

    cam = exp["camera"] if cam is None else cam
    camera = load_camera(exp.base / cam["file"] if cam["file"] else cam["preset"])
    if not cam["white"]:
        return camera
    from ..calibration import calibrate
    from ..io.files import read_image
    from ..pipeline.frames import load_frame

    log(f"calibrating from {cam['white']}")
    img = exp["images"]
    dark = read_image(exp.base / img["dark"], img["channel"]) if img["dark"] else None
    # a white image is a flat field itself: the dark frame only
    calibrated = calibrate(load_frame(exp.base / cam["white"], camera, img["channel"], dark,
                                      white=True), camera.with_pose(None))
    return calibrated.with_pose(camera.pose)  # a calibration finds the lenses, not the pose


def run_grid(exp: Experiment, camera: Camera | list[Camera]) -> Grid:
    """The experiment's grid: its file, or fitted to the camera (``z_mm``; several
    cameras: the first, unposed); refused before any work when a camera cannot image it
    (:func:`plenocl.optics.depthrange.check_grid`)."""
    cameras = list(camera) if isinstance(camera, (list, tuple)) else [camera]
    g = exp["grid"]
    if g["file"]:
        grid = Grid.from_toml(exp.base / g["file"])
    elif cameras[0].pose is not None:
        raise ValueError(
            "[grid] z_mm fits the grid to the camera in its own frame, but the (first) "
            "camera has a [pose]: the grid then lies in the world frame, so give it as "
            "[grid] file = \"grid.toml\" (written by plenocl grid for that camera without "
            "its [pose], carried into the world by hand, or made with plenocl.Grid)")
    else:
        grid = Grid.for_camera(cameras[0], tuple(g["z_mm"]), voxel_mm=g["voxel_mm"],
                               depth_voxel_mm=g["depth_voxel_mm"], fraction=g["fraction"])
    for cam in cameras:
        check_grid(cam, grid)
    return grid


def check_windows(piv: PIVSettings, grid: Grid) -> None:
    """``[piv]``'s windows (given, or the default schedule cut to the grid) checked on the
    grid's volume before any frame is read: a window larger than the grid would fail
    every pair after its two reconstructions."""
    shape = grid.shape
    where = f"the grid's {shape[0]} x {shape[1]} x {shape[2]} voxels (z, y, x)"
    try:
        if piv.windows is None:  # the schedule follows each volume's particles: it fits
            auto_windows(shape)  # the grid when its smallest window does
            return
        with warnings.catch_warnings():  # windows that grow: piv3d's warning, per pair
            warnings.simplefilter("ignore")
            window_passes(shape, piv.windows, piv.overlaps, piv.final_iterations)
    except ValueError as exc:
        raise ValueError(f"[piv] windows do not fit {where}: {exc}; or a larger grid "
                         "([grid])") from exc


def check_corrections(exp: Experiment, cameras: list[Camera]) -> None:
    """The experiment's dark frame and flat field checked before any frame is read
    (:func:`plenocl.pipeline.frames.load_corrections`): a bad one is refused once, naming
    its file, not blamed on every pair's images."""
    from ..pipeline.frames import load_corrections

    load_corrections(*frame_corrections(exp), cameras, exp["images"]["channel"])


def frame_corrections(exp: Experiment) -> tuple[str | None, str | None]:
    """The absolute paths of the dark frame and the flat field (``None``: none)."""
    img = exp["images"]
    return tuple(str((exp.base / img[k]).resolve()) if img[k] else None
                 for k in ("dark", "flat"))


def camera_files(count: int) -> list[str]:
    """The names of a run's cameras as written in its folder: ``camera_used.toml``, or
    ``camera_K_used.toml`` (``K`` from 1) for several cameras."""
    if count == 1:
        return ["camera_used.toml"]
    return [f"camera_{k}_used.toml" for k in range(1, count + 1)]


def write_used_config(exp: Experiment, out: Path, camera: Camera | list[Camera], grid: Grid,
                      settings: dict) -> None:
    """The configuration used (a record, not read back: the work gets its settings as an
    object), the camera(s) (:func:`camera_files`) and the grid, beside the results.
    ``settings``: the resolved settings' sections (a pair's, or the tracking's), over
    the file's own."""
    cameras = list(camera) if isinstance(camera, (list, tuple)) else [camera]
    out.mkdir(parents=True, exist_ok=True)
    used = {name: {k: v for k, v in values.items() if v is not None}
            for name, values in {**exp.sections, **settings}.items()}
    dark, flat = frame_corrections(exp)  # absolute: the record holds wherever it is read
    for key, value in (("dark", dark), ("flat", flat)):
        if value is not None:
            used["images"][key] = value
    used["run"] = {"plenocl_version": __version__,
                   "grid_shape": list(grid.shape), "grid_rotation_deg": grid.rotation_deg}
    if exp.cameras:
        used.pop("camera", None)
        used["cameras"] = [{k: v for k, v in cam.items() if v is not None}
                           for cam in exp.cameras]
    write_toml(out / "experiment_used.toml", used)
    for cam, name in zip(cameras, camera_files(len(cameras)), strict=True):
        cam.to_toml(out / name)
    grid.to_toml(out / "grid_used.toml")
