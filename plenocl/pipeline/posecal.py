"""A camera's pose from images of a dot target at known world positions (docs/design.md
§2.3, issue 49 item 4).

Each dot is a point of light; one plenoptic camera locates it in its own frame from its
raw image, well across its line of sight and less well along it. Starting from a guessed
pose (the setup as built, within a few tenths of a millimetre and about a degree), every
known dot is carried into the camera's frame, fitted to the raw image from there
(:class:`plenocl.piv.imagefit.ImageFit`: the camera's exact rays, each dot's position and
its posterior standard deviation), and the pose is the rigid motion that carries the
world dots onto the fitted ones, each residual divided by its standard deviation
(Gauss-Newton on the rotation vector and translation, SciPy's ``least_squares``). The fit
starts from the guess's prediction and its prior pulls towards it, so the two steps
alternate until the pose stops moving: at the fixed point the prediction is the fit. The
residuals are reported as image points on the sensor (pixels): where the calibrated pose
puts each dot against where its image puts it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..camera import Camera, Pose
from ..grid import Grid
from ..optics.depthrange import field_of_view_mm
from ..peaks import find_particles
from ..piv.imagefit import ImageFit, ImageFitSettings
from ..piv.jointfit import JointImageFit
from ..projection import Projector
from ..reconstruction import reconstruct

#: Alternations of the dots' fit and the pose's at most, and the pose change (degrees,
#: mm) below which they stop.
POSE_ROUNDS = 6
POSE_TOLERANCE = (1e-4, 1e-5)
#: An unsettled pose is said (a warning) when its last change exceeds this (degrees,
#: mm), and a grown residual when it exceeds the guess's by this factor and this many
#: pixels: a good guess's last rounds move by rounding, and its residual by a few
#: hundredths of a pixel either way.
UNSETTLED = (1e-2, 1e-3)
GROWN = (1.25, 0.1)
#: How far (mm) beyond the dots the fit's grid reaches (its margin and voxel size only).
GRID_MARGIN_MM = 1.0


@dataclass(frozen=True)
class PoseCalibration:
    """A calibrated pose and how well it explains the target's images.

    Attributes
    ----------
    pose
        The pose found (:class:`plenocl.camera.Pose`).
    residual_px
        RMS distance (sensor pixels) between each dot's image point under ``pose`` and
        under its fitted position, over the dots kept.
    start_residual_px
        The same under the guessed pose, with the first round's fits (the disparity
        the calibration started from).
    dots
        The dots used (the fit dropped the others: outside the view, not finite).
    rounds
        Alternations run.
    settled
        Whether the pose stopped moving (:data:`POSE_TOLERANCE`) within
        :data:`POSE_ROUNDS` (``False``: a warning said so).
    """

    pose: Pose
    residual_px: float
    dots: int
    rounds: int
    start_residual_px: float = float("nan")
    settled: bool = True


def calibrate_pose(camera: Camera, images, targets, guess: Pose,
                   settings: ImageFitSettings | None = None, queue=None) -> PoseCalibration:
    """The pose of ``camera`` from its images of a dot target.

    Parameters
    ----------
    camera
        The calibrated camera (its pose, if any, is ignored: ``guess`` starts it).
    images
        Its raw images, one per target position.
    targets
        Per image, the dots' world positions ``(N_k, 3)`` mm.
    guess
        The pose as built: within about a degree and a few tenths of a millimetre.
    settings, queue
        The dots' fit (:class:`plenocl.piv.imagefit.ImageFitSettings`; its device).

    Returns
    -------
    PoseCalibration
    """
    own = camera.with_pose(None)
    points = [np.asarray(t, float).reshape(-1, 3) for t in targets]
    if len(points) != len(images) or not points or not sum(map(len, points)) >= 3:
        raise ValueError("calibrate_pose needs one array of dot positions per image and at "
                         "least 3 dots in all")
    pose, rounds, start, settled = guess, 0, float("nan"), False
    while rounds < POSE_ROUNDS and not settled:
        rounds += 1
        world, fitted, sigma = _fitted_dots(own, images, points, pose, settings, queue)
        if rounds == 1:
            start = _residual_px(own, pose, world, fitted)
        new = _solve_pose(world, fitted, sigma, pose)
        turn, shift = pose.turn_deg(new), pose.shift_mm(new)
        pose = new
        settled = turn < POSE_TOLERANCE[0] and shift < POSE_TOLERANCE[1]
    residual = _residual_px(own, pose, world, fitted)
    found = PoseCalibration(pose, residual, len(world), rounds, start, settled)
    _warn_if_doubtful(own, found, world, (turn, shift))
    return found


def _warn_if_doubtful(own: Camera, found: PoseCalibration, world: np.ndarray,
                      last: tuple[float, float]) -> None:
    """Say when the pose cannot be trusted: every dot within the camera's depth
    resolution of its focal plane (their depths barely measured, so the pose's tilt is
    not held: a plate at the focal plane gave 18 degrees off), the alternation not
    settled (:data:`UNSETTLED`), or the residual grown from the guess's (:data:`GROWN`)."""
    depth = np.abs(found.pose.to_camera(world)[:, 2])
    reach = own.depth_resolution_mm
    why = []
    if depth.max() < reach:
        why.append(f"every dot lies within the camera's depth resolution ({reach:.2f} mm) of "
                   f"its focal plane (at most {depth.max():.2f} mm), where it measures depth "
                   "poorly: image the target at depths beyond it too (two or more plate "
                   "positions, e.g. 2-3 resolutions either side)")
    if not found.settled and (last[0] > UNSETTLED[0] or last[1] > UNSETTLED[1]):
        why.append(f"the pose did not settle in {found.rounds} rounds (its last change "
                   f"{last[0]:.3g} deg, {last[1]:.3g} mm)")
    if found.residual_px > GROWN[0] * found.start_residual_px + GROWN[1]:
        why.append(f"the residual grew from the guess's {found.start_residual_px:.3g} px to "
                   f"{found.residual_px:.3g} px (check the dots' order against the images "
                   "and the guess)")
    if why:
        warnings.warn("calibrate_pose: the pose found may be wrong: " + "; ".join(why),
                      stacklevel=3)


def _fitted_dots(own: Camera, images, points, pose: Pose, settings, queue):
    """Every dot's world position, its position fitted in the camera's frame from the
    pose's prediction, and the fit's standard deviations, over the dots the fit kept."""
    world, fitted, sigma = [], [], []
    for image, dots in zip(images, points, strict=True):
        start = pose.to_camera(dots)
        seen = _in_view(own, start)
        if not seen.any():
            continue
        fit = ImageFit(own, _grid_around(own, start[seen]), [image], settings, queue=queue)
        out = fit.fit(0, start[seen])
        kept = out.kept & (out.intensities > 0)  # a dot with no light found: not there
        world.append(dots[seen][kept])
        fitted.append(out.positions[kept])
        sigma.append(out.sigma[kept])
    if not world:
        world = fitted = sigma = [np.zeros((0, 3))]
    world, fitted, sigma = (np.concatenate(a) for a in (world, fitted, sigma))
    if len(world) < 3:
        raise ValueError(f"only {len(world)} of the target's dots could be fitted: check "
                         "that the guessed pose puts them in the camera's view")
    return world, fitted, np.maximum(sigma, 1e-6)


def _in_view(camera: Camera, pts: np.ndarray) -> np.ndarray:
    """Which camera-frame points lie in the camera's field of view at their depth."""
    out = np.zeros(len(pts), bool)
    for k, (x, y, z) in enumerate(pts):
        (x0, x1), (y0, y1) = field_of_view_mm(camera, float(z))
        out[k] = x0 <= x <= x1 and y0 <= y <= y1
    return out


def _grid_around(camera: Camera, pts: np.ndarray) -> Grid:
    """A grid of the camera's voxels holding ``pts`` and a margin (the fit's margin and
    prior scale)."""
    voxel = camera.ml_pitch_mm / camera.magnification
    dvox = camera.depth_resolution_mm / 2
    lo, hi = pts.min(axis=0) - GRID_MARGIN_MM, pts.max(axis=0) + GRID_MARGIN_MM
    shape = [max(1, int(np.ceil((hi[k] - lo[k]) / step))) for k, step in
             enumerate((voxel, voxel, dvox))]
    hi = lo + np.array(shape) * np.array([voxel, voxel, dvox])
    return Grid(tuple(shape[::-1]), (lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2]))


def _as_pose(params: np.ndarray) -> Pose:
    """The pose of a rotation vector and translation ``(6,)``."""
    rx, ry, rz = Rotation.from_rotvec(params[:3]).as_euler("xyz", degrees=True)
    return Pose((rx, ry, rz), tuple(params[3:]))


def _solve_pose(world: np.ndarray, fitted: np.ndarray, sigma: np.ndarray, start: Pose
                ) -> Pose:
    """The rigid motion carrying ``world`` onto ``fitted`` (camera frame), each
    component's residual divided by its standard deviation, from ``start``."""
    rotvec = Rotation.from_matrix(start.matrix).as_rotvec()

    def residuals(params):
        moved = world @ Rotation.from_rotvec(params[:3]).as_matrix().T + params[3:]
        return ((moved - fitted) / sigma).ravel()

    found = least_squares(residuals, np.concatenate([rotvec, start.translation_mm]),
                          method="lm")
    return _as_pose(found.x)


def _residual_px(own: Camera, pose: Pose, world: np.ndarray, fitted: np.ndarray) -> float:
    """RMS sensor distance (pixels) between the dots' image points under ``pose`` and
    under their fitted positions."""
    predicted = own.image_points(pose.to_camera(world))[:, :2]
    found = own.image_points(fitted)[:, :2]
    return float(np.sqrt(np.mean(np.sum((predicted - found) ** 2, axis=1)))
                 / own.pixel_pitch_mm)


#: A particle of the reconstruction takes part in self-calibration when the joint fit
#: finds at least this fraction of the median particle's intensity (ghosts are dimmer).
SELF_MIN_INTENSITY = 0.3
#: Each round moves a camera this many times the way to the pose its particles give.
SELF_STEP = 1.8
#: The disparity map's regions: the sensor cut into this many parts per axis (their
#: mean disparity vectors are the systematic disparity; Wieneke 2008).
DISPARITY_REGIONS = 2


@dataclass(frozen=True)
class SelfCalibration:
    """Several cameras' poses refined from their particle images.

    Attributes
    ----------
    cameras
        The cameras with their refined poses (the first one's as given: it holds the
        world frame).
    disparity_px
        Per round (the first before any change), per camera, the systematic disparity
        (sensor pixels): the RMS over the sensor's regions (:data:`DISPARITY_REGIONS`
        per axis) of the mean vector from where the camera's own image puts the
        particles to where the particles fitted to every camera's images lie in it.
    scatter_px
        The same rounds' RMS disparity of single particles (the fits' noise included).
    particles
        The particles the last round used.
    """

    cameras: list[Camera]
    disparity_px: list[list[float]]
    scatter_px: list[list[float]]
    particles: int


def self_calibrate(cameras, images, grid: Grid, rounds: int = 8,
                   settings: ImageFitSettings | None = None, queue=None) -> SelfCalibration:
    """Refine the poses of several cameras from their images of the particles themselves
    (volume self-calibration after Wieneke 2008; docs/design.md §2.3).

    Each exposure's volume is reconstructed from every camera's image; its particles
    (those the fit to every camera's image at once finds at least
    :data:`SELF_MIN_INTENSITY` of the median intensity: ghosts are dimmer) are located in
    the world by that joint fit, and each camera after the first takes the pose that
    carries all exposures' particles onto its own images (:func:`calibrate_pose` with the
    particles as its target); the particles are fitted again with the new poses,
    ``rounds`` times. The first camera holds the world frame. What the particles cannot
    tell (a motion of a camera their positions absorb) is left as it is: the cameras end
    consistent with each other, their disparities at the fits' noise, which more
    exposures (more particles per region) lower.

    Parameters
    ----------
    cameras
        The posed, calibrated cameras (at least two).
    images
        Per camera, its raw images of the same exposures (a list, one image per
        exposure, in the same order for every camera; or one image).
    grid
        The world grid to reconstruct on.
    rounds
        Rounds of refitting the poses and the particles.
    settings, queue
        The particles' fit and the device.
    """
    per_camera = [list(i) if isinstance(i, (list, tuple)) else [i] for i in images]
    if len(cameras) < 2 or len(per_camera) != len(cameras):
        raise ValueError("self-calibration needs two or more cameras and their images, "
                         "one list per camera")
    if len({len(i) for i in per_camera}) != 1:
        raise ValueError("self-calibration needs every camera's images of the same "
                         "exposures: lists of one length")
    cams = list(cameras)
    exposures = list(zip(*per_camera, strict=True))  # per exposure, every camera's image
    projectors = [Projector(c, grid, queue) for c in cams]
    worlds = [grid.from_index(find_particles(reconstruct(list(e), projectors))[0])
              for e in exposures]
    systematic, scatter = [], []
    for round_ in range(rounds + 1):
        worlds = [_joint_particles(cams, e, grid, w, settings, queue, select=round_ == 0)
                  for e, w in zip(exposures, worlds, strict=True)]
        maps = [disparity(c, imgs, worlds, settings, queue) for c, imgs in
                zip(cams, per_camera, strict=True)]
        systematic.append([m[0] for m in maps])
        scatter.append([m[1] for m in maps])
        if round_ == rounds:
            break
        cams = [cams[0]] + [c.with_pose(_extrapolated(c.pose or Pose(), calibrate_pose(
            c, imgs, worlds, c.pose or Pose(), settings, queue).pose, SELF_STEP))
                            for c, imgs in zip(cams[1:], per_camera[1:], strict=True)]
    return SelfCalibration(cams, systematic, scatter, sum(map(len, worlds)))


def _extrapolated(old: Pose, new: Pose, factor: float) -> Pose:
    """``old`` moved ``factor`` times the way to ``new`` (rotation vector and
    translation): the particles' joint positions take part of a camera's error each
    round, so the plain step falls short."""
    turn = Rotation.from_matrix(new.matrix @ old.matrix.T).as_rotvec() * factor
    rotvec = (Rotation.from_rotvec(turn) * Rotation.from_matrix(old.matrix)).as_rotvec()
    shift = np.asarray(old.translation_mm) + factor * np.subtract(new.translation_mm,
                                                                  old.translation_mm)
    return _as_pose(np.concatenate([rotvec, shift]))


def _joint_particles(cams, images, grid: Grid, world: np.ndarray, settings, queue,
                     select: bool) -> np.ndarray:
    """The particles fitted to every camera's image from ``world`` (mm); with
    ``select``, only those at least :data:`SELF_MIN_INTENSITY` of the median bright."""
    fit = JointImageFit(cams, grid, [[img] for img in images], settings, queue=queue)
    found = fit.fit(0, world)
    keep = found.kept
    if select and keep.any():
        keep &= found.intensities >= SELF_MIN_INTENSITY * np.median(found.intensities[keep])
    if keep.sum() < 3:
        raise ValueError(f"self-calibration found {int(keep.sum())} particles in every "
                         "camera's view: too few; check the poses and the grid")
    return found.positions[keep]


def disparity(camera: Camera, images, worlds, settings: ImageFitSettings | None = None,
              queue=None) -> tuple[float, float]:
    """The systematic and the single-particle RMS disparity (sensor pixels) of a posed
    camera over its ``images``: from where each image puts particles near that
    exposure's world positions ``worlds`` (each fitted from its prediction) to where
    the pose puts them (see :class:`SelfCalibration`)."""
    own, pose = camera.with_pose(None), camera.pose or Pose()
    placed, fitted, _ = _fitted_dots(own, images, worlds, pose, settings, queue)
    predicted = own.image_points(pose.to_camera(placed))[:, :2]
    vectors = (predicted - own.image_points(fitted)[:, :2]) / own.pixel_pitch_mm
    cols, rows = own.pixels
    pixel = own.mm_to_px(predicted)
    region = (np.clip((pixel[:, 0] / cols * DISPARITY_REGIONS).astype(int), 0,
                      DISPARITY_REGIONS - 1) * DISPARITY_REGIONS
              + np.clip((pixel[:, 1] / rows * DISPARITY_REGIONS).astype(int), 0,
                        DISPARITY_REGIONS - 1))
    means = [vectors[region == k].mean(axis=0) for k in np.unique(region)]
    return (float(np.sqrt(np.mean(np.sum(np.square(means), axis=1)))),
            float(np.sqrt(np.mean(np.sum(vectors ** 2, axis=1)))))
