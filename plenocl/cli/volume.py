"""The ``plenocl reconstruct`` and ``plenocl piv`` subcommands (wired into plenocl.cli).

::

    plenocl reconstruct raw.tif --camera cam_cal.toml --grid grid.toml --out vol.npz
    plenocl piv volA.npz volB.npz --dt 175e-6 --grid grid.toml --out field.vti
"""

from __future__ import annotations

import argparse
import warnings

from ..camera import LAYOUTS, load_camera
from ..io.files import CHANNELS
from ..pipeline.frames import load_frame
from ..projection.weighting import DEFAULT_OVERSAMPLE
from ..reconstruction.settings import (
    COARSE_ITERATIONS,
    COARSE_OVERSAMPLE,
    DEFAULTS,
    FINE_DEFAULTS,
    SUPERSAMPLE,
    SUPPORT,
)
from .frames import add_frame_options, camera_for_frames, read_frame


def reconstruct_command(args: argparse.Namespace) -> int:
    """Reconstruct a volume from one raw image, with a progress display."""
    from ..grid import Grid
    from ..io.progress import iteration_bar
    from ..projection.projector import Projector
    from ..reconstruction import reconstruct
    from ..volumefile import save_volume

    camera = camera_for_frames(args, load_camera(args.camera))
    grid = Grid.from_toml(args.grid)
    if not camera.calibrated:
        warnings.warn(f"the camera {args.camera} has no [calibration]: the nominal microlens "
                      "centres are used; calibrate real cameras first (plenocl calibrate)",
                      stacklevel=2)
    image = read_frame(args, args.raw, camera)
    mask = _pixel_mask(args, camera)
    settings = reconstruction_settings(args)
    proj = Projector(camera, grid, args.device)
    with iteration_bar(settings.total_iterations, f"{args.method} {grid.shape}") as bar:
        vol, info = reconstruct(image, proj, settings=settings, callback=bar,
                                return_info=True, pixel_mask=mask)
    save_volume(args.out, vol, grid)
    print(f"wrote {args.out}: {grid.shape} voxels, {info.iterations} {args.method} iterations "
          f"in {info.seconds:.1f} s, residual {info.residuals[-1] if info.residuals else 0:.3g}")
    return 0


def reconstruction_settings(args: argparse.Namespace):
    """The reconstruction the command line asks for: its options over
    :class:`~plenocl.reconstruction.ReconstructionSettings`' defaults, so that
    ``plenocl reconstruct``, :func:`plenocl.reconstruct` and ``process_pair`` reconstruct
    alike."""
    from ..reconstruction import ReconstructionSettings

    given = dict(method=args.method, iterations=args.iterations, relax=args.relax,
                 start=args.start, threshold=args.threshold, mask_fraction=args.mask_fraction,
                 min_sensitivity=args.min_sensitivity, tol=args.tol,
                 supersample=args.supersample, coarse_iterations=args.coarse_iterations,
                 support=args.support, coarse_oversample=args.coarse_oversample,
                 smooth_px=args.smooth_px)
    table = {k: v for k, v in given.items() if v is not None}
    table["background"] = "median" if args.background == "median" else None
    return ReconstructionSettings(**table)


def _pixel_mask(args: argparse.Namespace, camera):
    """``--mask``: the raw image's alpha (``alpha``) or a mask file, nonzero where the
    image holds data; ``None`` without it."""
    if not args.mask:
        return None
    from ..io.files import read_alpha, read_image

    if args.mask == "alpha":
        alpha = read_alpha(args.raw)
        if alpha is None:
            raise ValueError(f"--mask alpha: {args.raw} has no alpha channel; give a mask "
                             "file (nonzero where the image holds data) instead")
        return camera.fit_image(alpha, f"{args.raw}'s alpha")
    return camera.fit_image(read_image(args.mask) != 0, args.mask)


def piv_command(args: argparse.Namespace) -> int:
    """Correlate two volumes and write the velocity field."""
    from ..pipeline.settings import PairSettings
    from ..pipeline.velocity import refined_field
    from ..piv import PIVSettings
    from ..piv.multipass import check_volume
    from ..units import check_dt
    from ..vectorfield import save_field
    from ..volumefile import load_volume

    if args.raw and not args.camera:
        raise ValueError("--raw needs --camera: the particles are fitted to the raw images "
                         "with the camera's rays (give the calibrated camera TOML)")
    check_dt(args.dt, "--dt", args.force)  # before any work
    settings = PairSettings(piv=PIVSettings(windows=tuple(args.windows) if args.windows else None),
                            particles=args.particles, image_fit=bool(args.raw))
    vol_a, grid_a = load_volume(args.vol_a)
    vol_b, grid_b = load_volume(args.vol_b)
    # checked under the files' names (piv3d's own checks say vol_a, vol_b)
    vol_a, vol_b = check_volume(str(args.vol_a), vol_a), check_volume(str(args.vol_b), vol_b)
    grid = _volume_grid(args, (grid_a, grid_b), (vol_a.shape, vol_b.shape))
    camera = load_camera(args.camera) if args.camera else None
    raws = [load_frame(path, camera, args.channel) for path in args.raw] if args.raw else None
    with warnings.catch_warnings():  # said above under the files' names
        warnings.filterwarnings("ignore", message=r"vol_[ab]'s darkest voxel")
        res = refined_field(vol_a, vol_b, grid, settings, args.device, camera=camera,
                            raws=raws)
    if settings.particles:
        log = res.refinement
        print(f"particle refinement: {log['pairs']} particle pairs, {log['vectors']} vectors"
              + (f", {log['dropped']} particle(s) dropped by the image fit (left the grid "
                 "or not finite)" if log.get("dropped") else "")
              + ("" if camera else "; without --camera the depth uncertainty has no "
                 "focal-zone term (docs/design.md §7.1)")
              + ("" if args.raw else "; without --raw the particles are the volumes' peaks, "
                 "not fitted to the raw images (docs/design.md §7.2)"))
    used = ", ".join(str(w) for w in dict.fromkeys(p["window"] for p in res.passes))
    print(f"windows per pass (z, y, x voxels): {used}")
    save_field(args.out, res, dt=args.dt, grid=grid)
    print(f"wrote {args.out}: {res.u.size} vectors ({100 * res.valid.mean():.1f}% valid), "
          f"final window {res.window}")
    return 0


def _volume_grid(args: argparse.Namespace, grids, shapes):
    """The grid of both volumes: the one they carry, or ``--grid`` for volumes without
    one (``.npy``); a conflict between them, or with ``--grid``, is refused."""
    from ..grid import Grid

    names = (args.vol_a, args.vol_b)
    carried = [g for g in grids if g is not None]
    if len(carried) == 2 and carried[0] != carried[1]:
        raise ValueError(f"{names[0]} and {names[1]} were reconstructed on different "
                         f"grids ({carried[0]} and {carried[1]}); reconstruct both images on "
                         "one grid")
    given = Grid.from_toml(args.grid) if args.grid else None
    if given is not None and carried and given != carried[0]:
        raise ValueError(f"--grid {args.grid} ({given}) is not the grid the volumes carry "
                         f"({carried[0]}): leave --grid out to use theirs, or reconstruct "
                         "on the grid you mean")
    grid = given or (carried[0] if carried else None)
    if grid is None:
        raise ValueError("the volumes carry no grid (.npy): give --grid grid.toml (the grid "
                         "they were reconstructed on) so that displacements become "
                         "millimetres and metres per second")
    for name, shape in zip(names, shapes):
        if tuple(shape) != tuple(grid.shape):
            raise ValueError(f"{name} holds {tuple(shape)} voxels but the grid is "
                             f"{tuple(grid.shape)} (z, y, x): give the grid it was "
                             "reconstructed on")
    return grid


def add_reconstruct_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``reconstruct``."""
    p = subparsers.add_parser("reconstruct", help="reconstruct a particle volume from a raw image")
    p.add_argument("raw", help="raw image (TIFF, PNG or .npy)")
    add_frame_options(p)
    p.add_argument("--camera", required=True, help="calibrated camera TOML (or a preset name)")
    p.add_argument("--grid", required=True, help="grid TOML ([grid] shape, x_mm, y_mm, z_mm)")
    p.add_argument("--out", required=True, help="output volume: .npz (with grid), .npy or .h5")
    p.add_argument("--method", default="mlem", choices=["mlem", "smart", "mart"],
                   help="mlem: multiplicative EM, keeps in-focus particles; smart: "
                        "simultaneous MART; mart: the paper's block MART")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"default: per method (mlem on sub-voxels after coarse "
                        f"iterations {FINE_DEFAULTS[0]}; mlem on the voxels and smart "
                        f"{DEFAULTS['smart'][0]}, mart {DEFAULTS['mart'][0]}); 0 returns "
                        "the start")
    p.add_argument("--relax", type=float, default=None,
                   help=f"relaxation: 0 < mu < 2 for mlem (default {FINE_DEFAULTS[1]:g} "
                        "on sub-voxels after coarse iterations, else 1), 0 < mu <= 1 for "
                        "smart and mart")
    p.add_argument("--start", default="uniform", choices=["uniform", "mlos"],
                   help="first guess: a uniform volume carrying the image's light, or MLOS")
    p.add_argument("--background", default="median", choices=["median", "none"],
                   help="subtract the median background (default, as plenocl.reconstruct "
                        "does) or use the image as is")
    p.add_argument("--threshold", type=float, default=None,
                   help="dark-pixel threshold (default: 4x the estimated noise)")
    p.add_argument("--mask-fraction", type=float, default=None,
                   help="zero voxels sending more than this fraction of light to dark pixels")
    p.add_argument("--smooth-px", type=float, default=None,
                   help="smooth the image by a Gaussian of this many pixels before the "
                        "dark threshold (default: 1 for smart and mart, which keeps a noisy "
                        "image's particles, none for mlem; 0: none)")
    p.add_argument("--min-sensitivity", type=float, default=0.5,
                   help="skip voxels sending no more than this fraction of light to the sensor")
    p.add_argument("--tol", type=float, default=None, help="early-stop tolerance")
    p.add_argument("--mask", default=None,
                   help="pixels without data (unrendered, dead): 'alpha' takes the raw "
                        "image's alpha channel, or a mask image file, nonzero where the "
                        "image holds data; those pixels are left out instead of read as "
                        "dark")
    p.add_argument("--supersample", type=int, default=None,
                   help=f"lateral sub-voxels per voxel and axis (default {SUPERSAMPLE}, as "
                        "plenocl.reconstruct, process_pair and plenocl run; 1: the voxels "
                        "themselves, cheaper, with about 3x the depth error)")
    p.add_argument("--coarse-iterations", type=int, default=None,
                   help="with sub-voxels: iterations on the voxels first, whose support "
                        "the sub-voxel iterations keep to (default "
                        f"{COARSE_ITERATIONS}, as plenocl.reconstruct and process_pair, "
                        "mlem's whatever the method, and then "
                        f"{FINE_DEFAULTS[0]} mlem iterations on the sub-voxels; 0: the "
                        "sub-voxels from the start)")
    p.add_argument("--support", type=float, default=None,
                   help="support threshold of the coarse volume, a fraction of its "
                        f"brightest voxel (default {SUPPORT:g})")
    p.add_argument("--coarse-oversample", type=float, default=None,
                   help="aperture samples per pixel footprint of the coarse iterations "
                        f"(default {COARSE_OVERSAMPLE:g}; the projector's own, "
                        f"{DEFAULT_OVERSAMPLE:g}, costs about 3x and finds the same support)")
    p.set_defaults(func=reconstruct_command)
    return p


def add_piv_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``piv``."""
    p = subparsers.add_parser("piv", help="3-D PIV between two volumes")
    p.add_argument("vol_a", help="first volume (.npz from reconstruct, .npy or .h5)")
    p.add_argument("vol_b", help="second volume")
    p.add_argument("--dt", type=float, required=True, help="time between exposures (s)")
    p.add_argument("--force", action="store_true",
                   help="accept a --dt outside 0.1 µs to 1 s (refused by default as a "
                        "likely unit mistake: --dt is in seconds)")
    p.add_argument("--grid", default=None, help="grid TOML (default: stored in the .npz)")
    p.add_argument("--out", required=True,
                   help="output field: .vti (ParaView; velocity its default vector), .npz, "
                        ".h5, .dat (Tecplot ASCII) or .csv (one vector per row)")
    p.add_argument("--windows", type=int, nargs="+", default=None,
                   help="window size per pass (voxels; default: 48 32 24, each cut per axis "
                        "to what the volume holds)")
    p.add_argument("--no-particles", dest="particles", action="store_false",
                   help="keep the correlation's field (default: each window's vector refined "
                        "by its matched particle pairs, as process_pair)")
    p.add_argument("--camera", default=None,
                   help="camera TOML (or a preset name) the volumes were reconstructed with: "
                        "the depth uncertainty of pairs near its focal plane, whose depth is "
                        "not measured, gets their systematic term, as in process_pair")
    p.add_argument("--raw", nargs=2, default=None, metavar=("RAW_A", "RAW_B"),
                   help="the raw images the volumes came from (needs --camera): each "
                        "particle is fitted to its raw image before pairing, as in "
                        "process_pair (a third less depth error)")
    p.add_argument("--channel", default=None, choices=list(CHANNELS),
                   help="for colour raw images (--raw): the plane to use, or the Rec. 709 "
                        "luminance")
    p.set_defaults(func=piv_command)
    return p


def demo_command(args: argparse.Namespace) -> int:
    """Run a built-in example."""
    if args.layout is not None and args.name != "boundary-layer":
        raise ValueError(f"--layout {args.layout} applies to the boundary-layer demo only; "
                         f"the {args.name} demo uses the paper's rectangular array")
    if args.name == "particles":
        from ..demo.particle_images import particle_demo

        for line in particle_demo(args.out, count=200, seed=args.seed, queue=args.device):
            print(line)
        return 0
    if args.name == "time-series":
        return _time_series(args)
    if args.name == "tracking":
        return _tracking(args)
    if args.cameras == 2:
        return _two_cameras(args)
    from ..demo.boundary_layer import run_boundary_layer

    s = run_boundary_layer(args.size, args.out, queue=args.device, seed=args.seed,
                           layout=args.layout or "rectangular")
    rec = s["recovery"]["default_mlem"]
    win = s["lateral_depth_error"]["window_averaged"]
    print(f"boundary layer ({args.size}, {s['layout']} array): velocity RMS error "
          f"{100 * s['velocity_rms_error']:.1f}% of U∞ (lateral "
          f"{win['lateral_voxels']:.2f} voxel = {100 * win['lateral_u_inf']:.1f}%, depth "
          f"{win['depth_voxels']:.2f} voxel = {100 * win['depth_u_inf']:.1f}%, against the "
          f"window-averaged truth), mean-profile RMS error "
          f"{100 * s['mean_profile_rms_error']:.1f}% of U∞, {100 * s['valid_fraction']:.0f}% "
          f"valid vectors, {100 * rec['recovered_fraction']:.0f}% of particles recovered; "
          f"outputs in {args.out}/ (summary.json, field.vti, fig_*.png)")
    return 0


def _two_cameras(args: argparse.Namespace) -> int:
    if args.name != "boundary-layer" or args.size != "small" or args.layout is not None:
        raise ValueError("--cameras 2 runs the small boundary-layer demo on the rectangular "
                         "array: leave --size, --layout and the demo's name at their "
                         "defaults")
    from ..demo.two_cameras import run_two_cameras

    s = run_two_cameras(args.out, queue=args.device, seed=args.seed)
    two, one = s["fields"]["two_cameras"], s["fields"]["camera_1_alone"]
    poses = ", ".join(f"{p['angle_deg']:.3f} deg / {p['translation_mm']:.4f} mm"
                      for p in s["pose_errors"])
    print(f"boundary layer, two cameras {s['apart_deg']:.0f} deg apart: lateral "
          f"{two['lateral_voxels']:.3f} / depth {two['depth_voxels']:.3f} voxel "
          f"({100 * two['lateral_u_inf']:.1f}% / {100 * two['depth_u_inf']:.1f}% of U∞), "
          f"{100 * two['recovered_fraction']:.0f}% of particles recovered; the first camera "
          f"alone {one['lateral_voxels']:.3f} / {one['depth_voxels']:.3f} voxel, "
          f"{100 * one['recovered_fraction']:.0f}%; poses calibrated within {poses}; "
          f"outputs in {args.out}/ (summary.json, field.vti, fig_*.png)")
    return 0


def _tracking(args: argparse.Namespace) -> int:
    from ..demo.tracking import run_tracking

    s = run_tracking(args.out, frames=args.frames, queue=args.device, seed=args.seed)
    steps, tracks, pair = (s["particles_per_step"], s["field_tracks"], s["field_pair"])
    print(f"boundary layer tracked over {s['frames']} frames: {s['tracks']} tracks, "
          f"{100 * steps['tracked']:.0f}% of the particles that stay 4 frames; per step "
          f"lateral {steps['smoothed']['lateral']:.3f} / depth {steps['smoothed']['depth']:.3f}"
          f" voxel; binned field lateral {tracks['lateral_voxels']:.2f} / depth "
          f"{tracks['depth_voxels']:.2f} voxel against the pair chain's "
          f"{pair['lateral_voxels']:.2f} / {pair['depth_voxels']:.2f}; "
          f"{s['seconds_per_frame']:.1f} s per frame; outputs in {args.out}/ "
          "(summary.json, tracks.vtu, fig_tracks.png)")
    return 0


def _time_series(args: argparse.Namespace) -> int:
    from ..demo.time_series import run_time_series

    s = run_time_series(args.out, pairs=args.pairs, queue=args.device, seed=args.seed,
                        workers=args.workers, size=args.size)
    err = s.get("rms_error", {})
    print(f"time series ({args.size}): {s['processed']} of {s['pairs']} pairs, "
          f"{s['seconds_per_pair']:.1f} s per pair; velocity RMS error per pair "
          + ", ".join(f"{c} {100 * v:.1f}%" for c, v in err.items()) + " of U∞, ensemble "
          "mean " + ", ".join(f"{c} {100 * v:.1f}%" for c, v in
                              s.get("ensemble_mean_rms_error", {}).items())
          + ", ensemble correlation " + ", ".join(
              f"{c} {100 * v:.1f}%" for c, v in
              s.get("ensemble_correlation_rms_error", {}).items())
          + f"; {args.out}/experiment.toml, results in {args.out}/results/")
    return 1 if s["failed"] else 0


def add_demo_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``demo``."""
    p = subparsers.add_parser("demo", help="run a built-in example end to end")
    p.add_argument("name", nargs="?", default="boundary-layer",
                   choices=["boundary-layer", "particles", "time-series", "tracking"],
                   help="boundary-layer (default): the paper's experiment on synthetic data; "
                        "particles: simulate one raw image; time-series: raw pairs and "
                        "their experiment.toml, processed by plenocl run; tracking: the "
                        "boundary layer recorded in time, its particles tracked")
    p.add_argument("--size", default="small", choices=["small", "paper"],
                   help="small: 850 x 850 px camera, minutes on 2 cores; paper: 16 MP, "
                        "300 x 200 x 150 voxels")
    p.add_argument("--layout", default=None, choices=list(LAYOUTS),
                   help="boundary-layer: the camera's microlens array, rectangular (the "
                        "paper's, the default) or hexagonal, of the same pitch on the same "
                        "sensor")
    p.add_argument("--cameras", type=int, default=1, choices=[1, 2],
                   help="boundary-layer, small: 2 sees the flow with two cameras 25 degrees "
                        "apart, each calibrated (lenses and pose from a dot target), "
                        "against the first camera alone (docs/design.md §6.7)")
    p.add_argument("--out", default="plenocl_demo", help="output folder (resumable)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pairs", type=int, default=6, help="time-series: pairs to write")
    p.add_argument("--frames", type=int, default=8, help="tracking: frames to record")
    p.add_argument("--workers", type=int, default=None,
                   help="time-series: process on a local Dask cluster of N workers")
    p.set_defaults(func=demo_command)
    return p
