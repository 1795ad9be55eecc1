"""The paper's experiment (§IV) on synthetic data with known truth: a turbulent boundary
layer seen with the wall-normal direction along the camera's depth, calibrated from a
simulated white image, reconstructed and correlated (``plenocl demo boundary-layer``).

Frames: the camera's ``x`` is spanwise, ``y`` streamwise and ``z`` (depth, away from
the camera) wall-normal; the wall is the far face of the volume, ``z = z_wall``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..calibration import calibrate
from ..camera import Camera
from ..flows import TurbulentBoundaryLayer, centred_displacement, displace
from ..grid import Grid
from ..io.atomic import write_json
from ..io.files import read_image, read_particles, write_particles, write_tiff
from ..metrics import recovery
from ..particles import particles_per_microlens, random_particles
from ..pipeline.resume import StageRunner
from ..pipeline.settings import PairSettings
from ..piv.direct import METHOD as CORRELATION_METHOD
from ..piv.refinement import METHOD as REFINEMENT_METHOD
from ..piv.settings import PIVSettings
from ..reconstruction import METHOD as RECONSTRUCTION_METHOD
from ..reconstruction import ReconstructionSettings
from ..volumefile import load_volume, save_volume

U_INF = 4.57          # free-stream velocity, m/s (the paper's 15 ft/s)
DT = 175e-6           # time between the two exposures, s


@dataclass(frozen=True)
class Scenario:
    """Everything that defines one boundary-layer experiment."""

    size: str
    camera: Camera                # nominal camera (what the user's camera file says)
    grid: Grid
    delta_mm: float               # boundary-layer thickness
    re_tau: float
    particles_per_lens: float     # seeding density
    rays: int                     # rays per particle
    iterations: int               # default solver (MLEM) iterations
    windows: tuple[int, ...]      # PIV passes
    ml_offset_mm: tuple[float, float] = (0.0021, -0.0013)  # the real array's shift

    @property
    def z_wall(self) -> float:
        """The wall: the far face of the volume."""
        return self.grid.z[1]

    @property
    def physical_camera(self) -> Camera:
        """The camera as built (its array slightly shifted): only the simulator sees it."""
        return replace(self.camera, ml_offset_mm=self.ml_offset_mm, microlens_centers=None)

    def config(self) -> dict:
        """JSON-ready description (resuming requires it unchanged)."""
        doc = {k: v for k, v in asdict(self).items() if k not in ("camera", "grid")}
        doc["camera"] = self.camera.to_dict()
        doc["grid"] = self.grid.to_dict()
        return doc


def scenario(size: str, layout: str = "rectangular") -> Scenario:
    """The ``paper`` experiment (16 MP, 300 x 200 x 150 voxels over 55 x 35 x 20 mm) or its
    ``small`` twin (850 x 850 px, 48 x 48 x 32 voxels over 6 x 6 x 4 mm), behind a
    rectangular microlens array (the paper's) or a ``"hexagonal"`` one of the same pitch
    filling the same sensor (:meth:`plenocl.camera.Camera.with_layout`)."""
    sc = _rectangular_scenario(size)
    return replace(sc, camera=sc.camera.with_layout(layout))


def _rectangular_scenario(size: str) -> Scenario:
    """The paper's camera and its ``small`` twin (:func:`scenario`)."""
    if size == "paper":
        return Scenario("paper", Camera.paper_16mp(),
                        Grid((150, 200, 300), x=(-27.5, 27.5), y=(-17.5, 17.5), z=(-10.0, 10.0)),
                        delta_mm=15.0, re_tau=230.0, particles_per_lens=0.05, rays=4000,
                        iterations=30, windows=(48, 32, 24))
    if size == "small":
        return Scenario("small", Camera.synthetic_850(),
                        Grid((32, 48, 48), x=(-3.0, 3.0), y=(-3.0, 3.0), z=(-2.0, 2.0)),
                        delta_mm=3.0, re_tau=230.0, particles_per_lens=0.08, rays=8000,
                        iterations=30, windows=(24, 16))
    raise ValueError(f"size must be 'small' or 'paper', got {size!r}")


class CameraFrameFlow:
    """A boundary-layer flow (streamwise x, wall-normal y, spanwise z) in camera
    coordinates (spanwise x, streamwise y, depth z towards the wall); velocity in mm/s."""

    def __init__(self, sc: Scenario, seed: int = 0) -> None:
        g = sc.grid
        self.z_wall = sc.z_wall
        self.flow = TurbulentBoundaryLayer(u_inf=U_INF * 1e3, delta=sc.delta_mm,
                                           re_tau=sc.re_tau, x_range=g.y, z_range=g.x, seed=seed)

    def __call__(self, pts: np.ndarray) -> np.ndarray:
        p = np.asarray(pts, float).reshape(-1, 3)
        vel = self.flow(np.column_stack([p[:, 1], self.z_wall - p[:, 2], p[:, 0]]))
        return np.column_stack([vel[:, 2], vel[:, 0], -vel[:, 1]])

    def mean_streamwise(self, z: np.ndarray) -> np.ndarray:
        """The analytic mean streamwise velocity (mm/s) at depths ``z``."""
        return self.flow.mean_velocity(self.z_wall - np.asarray(z, float))


def seed_particles(sc: Scenario, flow: CameraFrameFlow, seed: int):
    """Particles at mid-time filling the volume (plus the distance they travel), then
    moved back and forth by half the exposure interval."""
    g, cam = sc.grid, sc.camera
    margin = U_INF * 1e3 * DT  # mm travelled streamwise
    box = (g.x, (g.y[0] - margin, g.y[1] + margin), g.z)
    count = int(round(sc.particles_per_lens * cam.ml_count[0] * cam.ml_count[1]
                      * (box[1][1] - box[1][0]) / (g.y[1] - g.y[0])))
    mid, inten = random_particles(box, count=count, seed=seed, intensity=(2e4, 4e4))
    mid = mid[mid[:, 2] < sc.z_wall - 1e-3]
    inten = inten[:len(mid)]
    return displace(mid, flow, -DT / 2), displace(mid, flow, DT / 2), inten


def run_boundary_layer(size: str, out_dir: str | Path, queue=None, seed: int = 0,
                       figures: bool = True, log: Callable[[str], None] = print,
                       layout: str = "rectangular") -> dict:
    """Run the whole chain; outputs, intermediates and ``summary.json`` go to ``out_dir``.

    ``layout``: the camera's microlens array, ``"rectangular"`` (the paper's) or
    ``"hexagonal"`` (:func:`scenario`). Finished stages are skipped when the same run is
    started again.
    """
    sc = scenario(size, layout)
    flow = CameraFrameFlow(sc, seed)
    settings = chain_settings(sc).with_named_weights()
    chain = {"supersample": settings.reconstruction.supersample,
             "lens_weights": settings.reconstruction.lens_weights,
             "refinement": "particles fitted to the raw images on the device, the calibrated "
                           f"camera's lines of sight (issue 48); {REFINEMENT_METHOD}",
             "correlation": CORRELATION_METHOD, "reconstruction": RECONSTRUCTION_METHOD}
    run = StageRunner(out_dir, {**sc.config(), "seed": seed, "chain": chain}, log)
    run.run("particles", ["particles_a.csv", "particles_b.csv"],
            lambda: stage_particles(run, sc, flow, seed))
    run.run("calibration", ["white.tif", "camera_calibrated.toml"],
            lambda: _stage_calibration(run, sc, seed, queue))
    run.run("images", ["raw_a.tif", "raw_b.tif"], lambda: _stage_images(run, sc, seed, queue))
    cam = Camera.from_toml(run.path("camera_calibrated.toml"))
    run.run("reconstruction", ["vol_a.npz", "vol_b.npz"],
            lambda: _stage_reconstruction(run, sc, cam, settings.reconstruction, queue))
    run.run("reconstruction_mart", ["vol_a_mart.npz"],
            lambda: _stage_mart(run, sc, cam, queue))
    run.run("piv", ["field.npz", "field.vti"], lambda: _stage_piv(run, sc, cam, settings, queue))
    truths = field_truths(run.out / "field.npz", sc, flow)  # the flow's slow part, once
    summary = evaluate(run, sc, flow, truths)
    if figures:
        stage_figures(run, sc, truths, summary)
    summary["seconds"] = run.timings
    write_json(run.path("summary.json"), summary, sort_keys=True)
    return summary


def stage_figures(run: StageRunner, sc: Scenario, truths, profile: dict) -> None:
    """The demo's figures (:data:`plenocl.demo.figures.FIGURES`) of a field beside its
    truths (:func:`field_truths`); ``profile`` holds :func:`mean_profile`'s entries."""
    from .figures import FIGURES, boundary_layer_figures

    meas, _, averaged, valid, coords = truths
    run.run("figures", list(FIGURES),
            lambda: boundary_layer_figures(run.out, (meas, averaged, valid, coords),
                                           sc.z_wall, profile, U_INF))


def stage_particles(run: StageRunner, sc: Scenario, flow, seed: int) -> None:
    """The particles of both exposures (``particles_a.csv``, ``particles_b.csv``)."""
    pos_a, pos_b, inten = seed_particles(sc, flow, seed)
    write_particles(run.path("particles_a.csv"), pos_a, inten)
    write_particles(run.path("particles_b.csv"), pos_b, inten)
    run.log(f"  {len(inten)} particles, "
            f"{particles_per_microlens(len(inten), sc.camera):.3f} per microlens")


def sensor_options(seed: int) -> dict:
    """The simulated sensor of the demo (blur, background, photon and read noise, 16 bit)."""
    return dict(blur_px=0.5, background=20.0, photon_noise=True, read_noise=3.0, bit_depth=16,
                seed=seed)


def _stage_calibration(run: StageRunner, sc: Scenario, seed: int, queue) -> None:
    from ..simulate import simulate_white_image

    kw = sensor_options(seed + 101)
    white = simulate_white_image(sc.physical_camera, intensity=3e4, vignetting=0.3,
                                 queue=queue, **{k: v for k, v in kw.items() if k != "blur_px"})
    write_tiff(run.path("white.tif"), white)
    cam = calibrate(white, sc.camera)
    truth = sc.physical_camera.ideal_microlens_centers()
    err = np.sqrt(np.nanmean(np.sum((cam.microlens_centers - truth) ** 2, -1)))
    run.log(f"  microlens centres within {err:.4f} px RMS of the truth")
    cam.to_toml(run.path("camera_calibrated.toml"))


def _stage_images(run: StageRunner, sc: Scenario, seed: int, queue) -> None:
    from ..simulate import seeded_beyond_view, simulate_image

    for tag, offset in (("a", 1), ("b", 2)):
        pos, inten = read_particles(run.path(f"particles_{tag}.csv"))
        kw = sensor_options(seed + offset)
        with seeded_beyond_view():  # the streamwise margin the flow carries into view
            img = simulate_image(sc.physical_camera, pos, inten, sc.rays, queue=queue, **kw)
        write_tiff(run.path(f"raw_{tag}.tif"), img)


def chain_settings(sc: Scenario) -> PairSettings:
    """The demo's chain: :func:`plenocl.process_pair`'s defaults (3 x 3 lateral
    sub-voxels, particles fitted to the raw images) with the scenario's iterations and
    windows."""
    base = PairSettings()
    return PairSettings(reconstruction=replace(base.reconstruction, iterations=sc.iterations),
                        piv=PIVSettings(windows=sc.windows))


def _reconstruct_file(run, sc, proj, tag: str, settings: ReconstructionSettings,
                      suffix: str = "") -> None:
    from ..io.progress import iteration_bar
    from ..reconstruction import reconstruct

    img = read_image(run.path(f"raw_{tag}.tif"))
    with iteration_bar(settings.total_iterations, f"{settings.method} {tag}") as bar:
        # the default preprocessing, as the API and the CLI: median background, 4 sigma
        vol = reconstruct(img, proj, settings=settings, callback=bar)
    save_volume(run.path(f"vol_{tag}{suffix}.npz"), vol, sc.grid)


def _stage_reconstruction(run, sc, cam, settings: ReconstructionSettings, queue) -> None:
    from ..projection.projector import Projector

    proj = Projector(cam, sc.grid, queue)
    for tag in ("a", "b"):  # process_pair's reconstruction: 3 x 3 lateral sub-voxels
        _reconstruct_file(run, sc, proj, tag, settings)


def _stage_mart(run, sc, cam, queue) -> None:
    """The paper's method for comparison: 5 MART iterations at μ = 1 on the voxels
    themselves, with the paper's lens weights, on the image as it is (no smoothing; first
    exposure)."""
    from ..projection.projector import Projector

    _reconstruct_file(run, sc, Projector(cam, sc.grid, queue), "a",
                      ReconstructionSettings("mart", 5, 1.0, supersample=1,
                                             lens_weights="paper", smooth_px=0), "_mart")


def _stage_piv(run: StageRunner, sc: Scenario, cam: Camera, settings: PairSettings,
               queue) -> None:
    from ..io.files import read_image
    from ..pipeline.velocity import refined_field
    from ..vectorfield import save_field

    vol_a, _ = load_volume(run.path("vol_a.npz"))
    vol_b, _ = load_volume(run.path("vol_b.npz"))
    # process_pair's correlation: the field refined by the volumes' particle pairs, each
    # particle first fitted to its raw image, all with the calibrated camera
    raws = [read_image(run.path(f"raw_{tag}.tif")) for tag in "ab"]
    res = refined_field(vol_a, vol_b, sc.grid, settings, queue, camera=cam, raws=raws)
    for name in ("field.npz", "field.vti"):
        save_field(run.path(name), res, dt=DT, grid=sc.grid)


def measured_and_true(field: Path, sc: Scenario, flow: CameraFrameFlow):
    """Measured and true velocity (m/s, camera frame, ``(3, nz', ny', nx')``) of a field
    file (``.npz``), the valid mask and the window-centre coordinates (mm)."""
    from ..vectorfield import read_npz

    res, _ = read_npz(field)
    dz, dy, dx = sc.grid.spacing
    origin = (sc.grid.z[0] + dz / 2, sc.grid.y[0] + dy / 2, sc.grid.x[0] + dx / 2)
    x, y, z = res.positions_mm(sc.grid.spacing, origin)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    pts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    true = centred_displacement(pts, flow, DT) / 1e3 / DT
    true = true.T.reshape((3,) + res.shape)
    meas = np.stack(res.velocity(sc.grid.spacing, DT))
    return meas, true, res.valid & np.all(np.isfinite(meas), 0), (x, y, z)


def field_truths(field: Path, sc: Scenario, flow: CameraFrameFlow):
    """:func:`measured_and_true` with the truth averaged over each final window (what a
    window measures, and what the headline lateral and depth errors compare with):
    ``(measured, point truth, window-averaged truth, valid, (x, y, z))``."""
    from ..vectorfield import read_npz

    meas, true, valid, coords = measured_and_true(field, sc, flow)
    averaged = window_averaged(read_npz(field)[0].window, coords, sc, flow)
    return meas, true, averaged, valid, coords


def window_averaged(window, coords, sc: Scenario, flow: CameraFrameFlow, n: int = 3):
    """The true velocity (m/s, ``(3, nz', ny', nx')``) averaged over each final window
    ``window`` (voxels, z y x) centred at ``coords`` (x, y, z mm): the mean over ``n^3``
    points at the centres of equal sub-boxes of the window."""
    x, y, z = coords
    shape = (3, len(z), len(y), len(x))
    size = np.asarray(window, float) * np.array(sc.grid.spacing)  # (z, y, x) mm
    offsets = (np.arange(n) + 0.5) / n - 0.5
    total = np.zeros(shape)
    for oz, oy, ox in np.ndindex(n, n, n):
        zz, yy, xx = np.meshgrid(z + offsets[oz] * size[0], y + offsets[oy] * size[1],
                                 x + offsets[ox] * size[2], indexing="ij")
        pts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
        total += (centred_displacement(pts, flow, DT) / 1e3 / DT).T.reshape(shape)
    return total / n**3


def lateral_depth_errors(meas, truths: dict, valid, sc: Scenario) -> dict:
    """RMS errors of the valid vectors, lateral (RMS over x and y) and depth, in voxels
    and as fractions of ``U∞``, against each truth of ``truths`` (m/s, by label)."""
    dz, dy, dx = sc.grid.spacing
    to_vox = np.array([dx, dy, dz])[:, None] * 1e-3 / DT  # m/s per voxel of displacement
    out = {}
    for label, true in truths.items():
        err = (meas - true)[:, valid]
        lat_v, dep_v = np.sqrt(np.mean(err[:2] ** 2)), np.sqrt(np.mean(err[2] ** 2))
        lat_x = np.sqrt(np.mean((err[:2] / to_vox[:2]) ** 2))
        out[label] = {"lateral_voxels": float(lat_x),
                      "depth_voxels": float(np.sqrt(np.mean((err[2] / to_vox[2]) ** 2))),
                      "lateral_u_inf": float(lat_v / U_INF), "depth_u_inf": float(dep_v / U_INF)}
    return out


def evaluate(run: StageRunner, sc: Scenario, flow: CameraFrameFlow, truths=None) -> dict:
    """Errors against the truth, as fractions of ``U∞``, and the reconstruction's
    recovery; ``truths``: :func:`field_truths` of the run's field, if already known."""
    if truths is None:
        truths = field_truths(run.out / "field.npz", sc, flow)
    meas, true, averaged, valid, coords = truths
    err = np.sqrt(np.sum((meas - true) ** 2, axis=0))
    pos_a, _ = read_particles(run.path("particles_a.csv"))
    inside = pos_a[sc.grid.contains(pos_a)]
    rec = {}
    for label, name in (("default_mlem", "vol_a.npz"), ("paper_mart", "vol_a_mart.npz")):
        rep = recovery(load_volume(run.path(name))[0], sc.grid, inside)
        rec[label] = {"recovered_fraction": rep.fraction, "ghost_fraction": rep.ghost_fraction,
                      "peaks": rep.found_peaks, "particles": rep.total}
    return {
        "size": sc.size, "layout": sc.camera.ml_layout, "u_inf_m_s": U_INF, "dt_s": DT,
        "vectors": int(valid.size),
        "valid_fraction": float(valid.mean()),
        "velocity_rms_error": float(np.sqrt(np.mean(err[valid] ** 2)) / U_INF),
        **mean_profile(truths, sc, flow),
        "component_rms_error": {c: float(np.sqrt(np.mean((meas[i] - true[i])[valid] ** 2))
                                         / U_INF) for i, c in enumerate("xyz")},
        "lateral_depth_error": lateral_depth_errors(
            meas, {"point": true, "window_averaged": averaged}, valid, sc),
        "recovery": rec,
    }


def mean_profile(truths, sc: Scenario, flow: CameraFrameFlow) -> dict:
    """The streamwise mean profile of a field's valid vectors (``truths``:
    :func:`field_truths`) beside the truth at the same vectors and the analytic profile:
    its RMS errors as fractions of ``U∞``, and the profiles the figures draw."""
    meas, true, _, valid, coords = truths
    z = coords[2]
    prof_meas = np.array([np.mean(meas[1, k][valid[k]]) for k in range(len(z))])
    prof_spread = np.array([np.std(meas[1, k][valid[k]]) for k in range(len(z))])
    prof_true = np.array([np.mean(true[1, k][valid[k]]) for k in range(len(z))])
    analytic = flow.mean_streamwise(z) / 1e3
    z_dense = np.linspace(sc.z_wall, float(z.min()), 60)  # from the wall up
    return {
        "mean_profile_rms_error": float(np.sqrt(np.mean((prof_meas - prof_true) ** 2)) / U_INF),
        "mean_profile_rms_error_vs_analytic":
            float(np.sqrt(np.mean((prof_meas - analytic) ** 2)) / U_INF),
        "profile_dense": {"wall_distance_mm": (sc.z_wall - z_dense).tolist(),
                          "analytic": (flow.mean_streamwise(z_dense) / 1e3).tolist()},
        "profile": {"z_mm": z.tolist(), "wall_distance_mm": (sc.z_wall - z).tolist(),
                    "measured": prof_meas.tolist(), "measured_std": prof_spread.tolist(),
                    "truth_at_vectors": prof_true.tolist(), "analytic": analytic.tolist()},
    }
