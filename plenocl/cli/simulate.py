"""``plenocl simulate``, ``plenocl white`` and ``plenocl grid``: synthetic raw images,
displaced pairs, white images and grid files from the command line.

::

    plenocl simulate --camera cam.toml --particles p.csv --out raw.tif
    plenocl simulate --camera cam.toml --particles p.csv --velocity 4.5 0 0 --dt 175e-6 \
        --out raw.tif                                 # raw_a.tif and raw_b.tif
    plenocl simulate --camera cam1.toml cam2.toml --particles p.csv --out raw.tif
                                                      # cam1/raw.tif, cam2/raw.tif
    plenocl white --camera cam.toml --out white.tif
    plenocl grid --camera cam_cal.toml --z -2 2 --out grid.toml
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from ..camera import load_camera
from ..units import check_displacement, check_dt
from .outputs import check_not_inputs


def cmd_simulate(args: argparse.Namespace) -> int:
    """Simulate the raw image of the particles in a CSV file (16-bit TIFF); with a flow,
    the pair of images ``dt`` apart, the particles at ``-dt/2`` and ``+dt/2``. Several
    cameras (each file's ``[pose]`` placing it in the world the particles are given in,
    docs/design.md §2.2): each camera's images in its folder ``camK`` (K from 1) beside
    ``OUT``, the same particles seen by all."""
    from ..flows import SolidBodyRotation, Uniform, displace
    from ..io.files import read_particles, write_particles

    cams = [load_camera(c) for c in (args.camera or [None])]
    cam = cams[0]
    positions, intensities = read_particles(args.particles)
    out = Path(args.out)
    check_not_inputs(args, _written(out, len(cams), args.velocity is None
                                    and args.omega is None), {"out"})
    if args.velocity is None and args.omega is None:
        if args.dt is not None:
            raise ValueError("--dt is the time between a displaced pair's exposures: give the "
                             "flow that moves them (--velocity U V W or --omega WX WY WZ), or "
                             "leave --dt out for one image")
        _write_images(cams, out, _camera_images(args, cams, positions, intensities))
        write_particles(truth_path(out), positions, intensities)
        return 0
    if args.dt is None:
        raise ValueError("a displaced pair needs --dt, the time between the exposures (s)")
    check_dt(args.dt, "--dt", args.force)
    flow = (Uniform(tuple(1e3 * v for v in args.velocity)) if args.omega is None
            else SolidBodyRotation(tuple(args.omega)))  # mm/s; rad/s
    moved = displace(positions, flow, args.dt) - positions
    check_displacement(float(np.abs(moved).max(initial=0.0)),
                       min(cam.sensor_size_mm) / cam.magnification, args.force)
    # every image made before any is written: a refused one leaves no other behind
    exposures = []
    for tag, sign in (("a", -0.5), ("b", 0.5)):
        moved = displace(positions, flow, sign * args.dt)
        exposures.append((exposure_path(out, tag), moved,
                          _camera_images(args, cams, moved, intensities)))
    for path, moved, images in exposures:
        _write_images(cams, path, images)
        write_particles(truth_path(path), moved, intensities)
    return 0


def exposure_path(out: Path, tag: str) -> Path:
    """Exposure ``tag``'s image of a pair named ``out`` (``raw.tif`` → ``raw_a.tif``)."""
    return out.with_name(f"{out.stem}_{tag}{out.suffix}")


def truth_path(image: Path) -> Path:
    """The particles' truth beside an image (``raw_a.tif`` → ``raw_a_particles.csv``)."""
    return image.with_name(image.stem + "_particles.csv")


def _written(out: Path, cameras: int, single: bool) -> list[Path]:
    """Every file ``plenocl simulate`` writes for ``out``: the images (one camera's, or
    each camera's in ``camK``) and the particles' truth beside them."""
    images = [out] if single else [exposure_path(out, tag) for tag in "ab"]
    return [*(image if cameras == 1 else camera_image_path(image, k, make=False)
              for image in images for k in range(1, cameras + 1)),
            *(truth_path(image) for image in images)]


def _camera_images(args, cams: list, positions, intensities) -> list:
    """Each camera's image of the particles, camera ``K``'s ray sampling seeded
    ``seed + K - 1``."""
    return [_simulate_one(args, cam, positions, intensities, args.seed + k)
            for k, cam in enumerate(cams)]


def _write_images(cams: list, out: Path, images: list) -> None:
    """The cameras' images: ``out`` for one camera; for several, in each camera's folder
    ``camK`` beside it (``K`` from 1; the names, and so their frame numbers, are the same
    in every folder, as the batch pairs them: docs/batch.md)."""
    from ..io.files import write_tiff

    for k, image in enumerate(images, start=1):
        path = out if len(cams) == 1 else camera_image_path(out, k)
        write_tiff(path, image)
        print(f"wrote {path} ({image.shape[1]} x {image.shape[0]} px, max {image.max()})")


def camera_image_path(out: Path, k: int, make: bool = True) -> Path:
    """Camera ``k``'s image of ``out`` (``run/raw_a.tif`` → ``run/cam2/raw_a.tif``),
    its folder made (``make``)."""
    folder = out.parent / f"cam{k}"
    if make:
        folder.mkdir(parents=True, exist_ok=True)
    return folder / out.name


def _simulate_one(args, cam, positions, intensities, seed: int) -> np.ndarray:
    """One camera's 16-bit raw image of the particles."""
    from ..simulate import simulate_image

    return simulate_image(cam, positions, intensities, args.rays, seed,
                          blur_px=args.blur, background=args.background,
                          photon_noise=args.photon_noise, read_noise=args.read_noise,
                          bit_depth=16, queue=args.device)


def cmd_white(args: argparse.Namespace) -> int:
    """Simulate a white (calibration) image of the camera's physical array."""
    from ..io.files import write_tiff
    from ..simulate import simulate_white_image

    cam = load_camera(args.camera)
    image = simulate_white_image(cam, stop_f_number=args.stop_f_number,
                                 intensity=args.intensity, seed=args.seed,
                                 photon_noise=args.photon_noise, read_noise=args.read_noise,
                                 bit_depth=16, queue=args.device)
    write_tiff(args.out, image)
    print(f"wrote {args.out} ({image.shape[1]} x {image.shape[0]} px, max {image.max()})")
    return 0


def cmd_grid(args: argparse.Namespace) -> int:
    """Write the grid that fits the camera's field of view (Grid.for_camera)."""
    from ..grid import Grid
    from ..optics.depthrange import resolved_depth_range

    camera = load_camera(args.camera)
    depth_voxel = (min(camera.depth_resolution_mm / 2, abs(args.z[1] - args.z[0]) / THREE_LAYERS)
                   if args.depth_voxel_mm is None else args.depth_voxel_mm)  # 0: refused
    # refused before anything is written when the camera does not resolve args.z
    grid = Grid.for_camera(camera, tuple(args.z), voxel_mm=args.voxel_mm,
                           depth_voxel_mm=depth_voxel, fraction=args.fraction)
    grid.to_toml(args.out)
    dz, dy, dx = grid.spacing
    near, far = resolved_depth_range(camera)
    print(f"wrote {args.out}: {grid.shape} voxels of {dz:.4g} x {dy:.4g} x {dx:.4g} mm "
          f"(z, y, x), rotated {grid.rotation_deg:.4f} deg; the camera resolves z in "
          f"[{near:.2f}, {far:.2f}] mm")
    if grid.shape[0] < THREE_LAYERS:  # a warning: -q (stdout silenced) still shows it
        warnings.warn(f"{grid.shape[0]} voxels deep: PIV's final 24-voxel windows give "
                      f"fewer than 3 layers of vectors in depth (at least {THREE_LAYERS} "
                      "voxels give 3); widen --z (within the depths the camera resolves) "
                      "or give thinner voxels (--depth-voxel-mm)", stacklevel=1)
    return 0


#: Voxels along an axis for three vectors of 24-voxel windows at 50 % overlap.
THREE_LAYERS = 48


def _camera_and_noise(p, sensor_noise: bool = True, several: bool = False) -> None:
    if several:
        p.add_argument("--camera", default=None, nargs="+",
                       help="camera TOML file or preset (synthetic, paper); default "
                            "synthetic; several files: several cameras, each placed by "
                            "its [pose], camera K writing into the folder camK beside "
                            "OUT")
    else:
        p.add_argument("--camera", default=None,
                       help="camera TOML file or preset (synthetic, paper); default synthetic")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the ray sampling (the same seed gives the same image)")
    if sensor_noise:
        p.add_argument("--photon-noise", action="store_true", help="add Poisson shot noise")
        p.add_argument("--read-noise", type=float, default=0.0, help="read noise (counts)")


def add_simulate_parsers(sub) -> None:
    """Register ``simulate``, ``white`` and ``grid``."""
    p = sub.add_parser("simulate", help="simulate a raw plenoptic image of particles, or a "
                                        "displaced pair")
    _camera_and_noise(p, several=True)
    p.add_argument("--particles", required=True,
                   help="CSV with header x_mm,y_mm,z_mm[,intensity] (counts per particle)")
    p.add_argument("--out", required=True, help="output 16-bit TIFF (a pair: OUT_a, OUT_b)")
    p.add_argument("--rays", type=int, default=2000, help="rays per particle")
    p.add_argument("--blur", type=float, default=0.0, help="particle-image blur (px)")
    p.add_argument("--background", type=float, default=0.0, help="background (counts)")
    motion = p.add_mutually_exclusive_group()  # one flow: both would drop one silently
    motion.add_argument("--velocity", type=float, nargs=3, default=None,
                        metavar=("U", "V", "W"), help="a pair moved by a uniform flow (m/s)")
    motion.add_argument("--omega", type=float, nargs=3, default=None,
                        metavar=("WX", "WY", "WZ"),
                        help="a pair moved by a solid-body rotation about the origin (rad/s)")
    p.add_argument("--dt", type=float, default=None, help="time between the pair (s)")
    p.add_argument("--force", action="store_true",
                   help="accept a dt or displacement outside the plausible range (a dt "
                        "beyond 0.1 µs to 1 s, particles moving further than the field "
                        "of view); without it they are refused as a likely unit mistake")
    p.set_defaults(func=cmd_simulate)
    w = sub.add_parser("white", help="simulate a white (calibration) image")
    _camera_and_noise(w)
    w.add_argument("--out", required=True, help="output 16-bit TIFF")
    w.add_argument("--stop-f-number", type=float, default=16.0,
                   help="f-number the main lens is stopped down to")
    w.add_argument("--intensity", type=float, default=10000.0, help="counts per microlens")
    w.set_defaults(func=cmd_white)
    g = sub.add_parser("grid", help="write a grid file fitting the camera's field of view")
    g.add_argument("--camera", default=None, help="(calibrated) camera TOML file or preset")
    g.add_argument("--z", type=float, nargs=2, required=True, metavar=("Z0", "Z1"),
                   help="depth range (mm, +z away from the camera), within the depths the "
                        "camera resolves (refused otherwise, naming them)")
    g.add_argument("--out", required=True, help="grid TOML to write")
    g.add_argument("--voxel-mm", type=float, default=None,
                   help="lateral voxel (default: one microlens in object space)")
    g.add_argument("--depth-voxel-mm", type=float, default=None,
                   help="depth voxel (default: half the camera's depth resolution, "
                        f"thinner where that leaves fewer than {THREE_LAYERS} voxels in "
                        "depth, so the final windows give 3 layers of vectors)")
    g.add_argument("--fraction", type=float, default=1.0, help="fraction of the field of view")
    g.set_defaults(func=cmd_grid)
