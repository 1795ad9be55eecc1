"""The boundary-layer demo seen by two plenoptic cameras (``plenocl demo boundary-layer
--cameras 2``; docs/design.md §2.3, §6.7; issue 49).

The small scenario's flow and particles (:mod:`plenocl.demo.boundary_layer`), now in a
world frame that two cameras look at from either side of its depth axis, ``apart``
degrees apart about y. Each camera is calibrated from its own simulated white image, its
pose from its images of a dot target at known positions (starting from the pose as built,
0.4 degree and 0.1 mm off), and the pair is processed by ``process_pair`` with both
cameras; the first camera alone, with its calibrated pose, on the same particles is the
baseline. ``summary.json`` holds both fields' errors against the truth averaged over each
window, the poses' errors and the particles recovered.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..calibration import calibrate
from ..camera import Camera, Pose
from ..io.atomic import write_json
from ..io.files import read_image, read_particles, write_tiff
from ..metrics import recovery
from ..opencl.device import get_queue
from ..pipeline.pair import process_pair
from ..pipeline.posecal import calibrate_pose
from ..pipeline.resume import StageRunner
from ..piv.direct import METHOD as CORRELATION_METHOD
from ..piv.refinement import METHOD as REFINEMENT_METHOD
from ..projection.projector import Projector
from ..reconstruction import METHOD as RECONSTRUCTION_METHOD
from ..vectorfield import save_field
from .boundary_layer import (
    DT,
    U_INF,
    CameraFrameFlow,
    Scenario,
    chain_settings,
    field_truths,
    lateral_depth_errors,
    mean_profile,
    scenario,
    sensor_options,
    stage_figures,
    stage_particles,
)

#: The pose as built against the truth: the dot target's calibration starts from it.
BUILT_ERROR = ((0.3, -0.2, 0.2), (0.08, -0.05, 0.06))


def true_poses(apart: float) -> list[Pose]:
    """The two cameras' poses: turned by minus and plus half of ``apart`` about y,
    looking at the world origin (the grid's centre)."""
    return [Pose((0.0, sign * apart / 2, 0.0), (0.0, 0.0, 0.0)) for sign in (-1, 1)]


def run_two_cameras(out_dir: str | Path, queue=None, seed: int = 0, apart: float = 25.0,
                    figures: bool = True, log: Callable[[str], None] = print) -> dict:
    """Run the two-camera chain; outputs and ``summary.json`` go to ``out_dir``
    (finished stages are skipped when the same run is started again), and with
    ``figures`` the single camera demo's figures of the two cameras' field
    (:data:`plenocl.demo.figures.FIGURES`)."""
    sc = scenario("small")
    flow = CameraFrameFlow(sc, seed)
    queue = get_queue(queue)  # one queue: the two cameras' projectors share it
    weights = chain_settings(sc).with_named_weights().reconstruction.lens_weights
    run = StageRunner(out_dir, {**sc.config(), "seed": seed, "apart_deg": apart,
                                "cameras": 2, "lens_weights": weights,
                                "methods": [RECONSTRUCTION_METHOD, CORRELATION_METHOD,
                                            REFINEMENT_METHOD]}, log)
    run.run("particles", ["particles_a.csv", "particles_b.csv"],
            lambda: stage_particles(run, sc, flow, seed))
    poses = true_poses(apart)
    for k, pose in enumerate(poses, start=1):
        run.run(f"camera_{k}", [f"white_{k}.tif", f"camera_{k}.toml"],
                lambda k=k, pose=pose: _stage_camera(run, sc, k, pose, seed, queue))
        run.run(f"images_{k}", [f"raw_{k}_a.tif", f"raw_{k}_b.tif"],
                lambda k=k, pose=pose: _stage_images(run, sc, k, pose, seed, queue))
    cams = [Camera.from_toml(run.path(f"camera_{k}.toml")) for k in (1, 2)]
    run.run("piv", ["field.npz", "field_camera_1.npz", "vol_a.npz"],
            lambda: _stage_piv(run, sc, cams, queue))
    summary, truths = _evaluate(run, sc, flow, cams, poses)
    if figures:
        stage_figures(run, sc, truths, mean_profile(truths, sc, flow))
    summary["seconds"] = run.timings
    write_json(run.path("summary.json"), summary, sort_keys=True)
    return summary


def _stage_camera(run: StageRunner, sc: Scenario, k: int, pose: Pose, seed: int,
                  queue) -> None:
    """Camera ``k``: its microlens centres from its white image, then its pose from its
    images of a dot target, from the pose as built."""
    from ..simulate import simulate_image, simulate_white_image

    kw = sensor_options(seed + 100 * k)
    white = simulate_white_image(sc.physical_camera, intensity=3e4, vignetting=0.3,
                                 queue=queue, **{a: v for a, v in kw.items() if a != "blur_px"})
    write_tiff(run.path(f"white_{k}.tif"), white)
    cam = calibrate(white, sc.camera)
    plates = dot_plates()
    physical = sc.physical_camera.with_pose(pose)
    images = [simulate_image(physical, dots, 3e4, 4000, queue=queue,
                             **sensor_options(seed + 100 * k + 10 + j))
              for j, dots in enumerate(plates)]
    guess = Pose(tuple(np.add(pose.rotation_deg, BUILT_ERROR[0])),
                 tuple(np.add(pose.translation_mm, BUILT_ERROR[1])))
    found = calibrate_pose(cam, images, plates, guess, queue=queue)
    run.log(f"  camera {k}: pose from the dot target, residual {found.residual_px:.2f} px "
            f"({found.dots} dots)")
    cam.with_pose(found.pose).to_toml(run.path(f"camera_{k}.toml"))


def dot_plates() -> list[np.ndarray]:
    """The dot target: 4 x 4 dots 1.2 mm apart at three depths (mm, world)."""
    xs = np.linspace(-1.8, 1.8, 4)
    x, y = np.meshgrid(xs, xs)
    return [np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
            for z in (-1.5, 0.0, 1.5)]


def _stage_images(run: StageRunner, sc: Scenario, k: int, pose: Pose, seed: int,
                  queue) -> None:
    from ..simulate import seeded_beyond_view, simulate_image

    physical = sc.physical_camera.with_pose(pose)
    for tag, offset in (("a", 1), ("b", 2)):
        pos, inten = read_particles(run.path(f"particles_{tag}.csv"))
        with seeded_beyond_view():  # the streamwise margin the flow carries into view
            img = simulate_image(physical, pos, inten, sc.rays, queue=queue,
                                 **sensor_options(seed + 10 * k + offset))
        write_tiff(run.path(f"raw_{k}_{tag}.tif"), img)


def _stage_piv(run: StageRunner, sc: Scenario, cams: list[Camera], queue) -> None:
    """Both cameras' pair, and the first camera's alone (the baseline)."""
    from ..volumefile import save_volume

    settings = chain_settings(sc)
    raws = {(k, t): read_image(run.path(f"raw_{k}_{t}.tif")) for k in (1, 2) for t in "ab"}
    projs = [Projector(c, sc.grid, queue) for c in cams]
    both = process_pair([raws[1, "a"], raws[2, "a"]], [raws[1, "b"], raws[2, "b"]], projs,
                        settings)
    alone = process_pair(raws[1, "a"], raws[1, "b"], projs[0], settings)
    for name, pair in (("field.npz", both), ("field_camera_1.npz", alone)):
        save_field(run.path(name), pair.piv, dt=DT, grid=sc.grid)
    save_field(run.path("field.vti"), both.piv, dt=DT, grid=sc.grid)
    save_volume(run.path("vol_a.npz"), both.vol_a, sc.grid)
    save_volume(run.path("vol_a_camera_1.npz"), alone.vol_a, sc.grid)


def _evaluate(run: StageRunner, sc: Scenario, flow: CameraFrameFlow, cams: list[Camera],
              poses: list[Pose]) -> tuple[dict, tuple]:
    """Both fields' errors against the window-averaged truth and their mean profiles' RMS
    errors, the poses' errors and the particles the first volumes recover; and the two
    cameras' field beside its truths (:func:`field_truths`)."""
    from ..volumefile import load_volume

    pos_a, _ = read_particles(run.path("particles_a.csv"))
    inside = pos_a[sc.grid.contains(pos_a)]
    out = {"apart_deg": poses[0].turn_deg(poses[1]), "u_inf_m_s": U_INF, "dt_s": DT,
           "fields": {}}
    kept = {}
    for label, field, vol in (("two_cameras", "field.npz", "vol_a.npz"),
                              ("camera_1_alone", "field_camera_1.npz", "vol_a_camera_1.npz")):
        truths = kept[label] = field_truths(run.out / field, sc, flow)
        meas, _, averaged, valid, _ = truths
        rep = recovery(load_volume(run.path(vol))[0], sc.grid, inside)
        out["fields"][label] = {
            **lateral_depth_errors(meas, {"window_averaged": averaged}, valid,
                                   sc)["window_averaged"],
            "mean_profile_rms_error": mean_profile(truths, sc, flow)["mean_profile_rms_error"],
            "valid_fraction": float(valid.mean()), "recovered_fraction": rep.fraction,
            "ghost_fraction": rep.ghost_fraction}
    out["pose_errors"] = [{"angle_deg": c.pose.turn_deg(p), "translation_mm": c.pose.shift_mm(p)}
                          for c, p in zip(cams, poses, strict=True)]
    return out, kept["two_cameras"]
