"""Lines of sight: the direction along which the camera places a point worst
(docs/design.md §7.4).

A plenoptic camera reads a point's depth from the parallax across the lenses it lights,
several times less precisely than its lateral position. What it leaves uncertain is where
the point lies along its *line of sight*: the chief ray through the centre of the main
lens's entrance pupil, ``(0, 0, -(s_o + f (1/m_p - 1)))`` (a thin lens: its centre,
``-s_o``; :attr:`plenocl.Camera.entrance_pupil_distance_mm`), along which every point
keeps the same central view on the array (:meth:`plenocl.Camera.image_points`). (A thick
lens's front principal point would lean the line 9.0° instead of 6.5° 20 mm off the axis
at the paper's optics with ``m_p = 0.5``.) On the optical axis that line is the grid's z
axis; off it, it leans by ``atan(r / (s_o + f (1/m_p - 1) + z))``: 11° at the paper's
optics 25 mm off the axis, where one voxel (0.13 mm) of depth error along it also moves
the point 0.14 voxel (0.18 mm) sideways. A stage that treats the uncertain direction as z
(a prior, a step bound, a search ellipsoid) is right on the axis only; these frames turn
it with the line.
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera

__all__ = ["line_of_sight", "sight_frames", "sight_information"]


def line_of_sight(camera: Camera, points_xyz) -> np.ndarray:
    """Unit vectors ``(N, 3)`` ``(x, y, z)`` along the lines of sight through object
    points ``(N, 3)`` mm (away from the camera: ``z`` component positive in the camera's
    frame). The points and the vectors are in the world's frame: a posed camera
    (:attr:`plenocl.Camera.pose`) takes the points into its frame and turns the vectors
    back."""
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    pose = camera.pose
    local = pts if pose is None else pose.to_camera(pts)
    ray = local + np.array([0.0, 0.0, camera.entrance_pupil_distance_mm])
    ray = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    return ray if pose is None else ray @ pose.matrix   # R^T v, row by row


def sight_frames(directions: np.ndarray) -> np.ndarray:
    """Rotations ``(N, 3, 3)`` whose third column is each unit ``direction`` ``(N, 3)``
    (``z > 0``): the least rotation taking the z axis onto it (Rodrigues' formula), so
    that on the axis it is the identity and its first two columns stay near x and y.
    ``R @ local`` turns a vector given in the (lateral, lateral, along) frame into the
    grid's ``(x, y, z)``."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    vx, vy, c = -d[:, 1], d[:, 0], d[:, 2]  # v = z x d, c = z . d
    cross = np.zeros((len(d), 3, 3))
    cross[:, 0, 2], cross[:, 1, 2] = vy, -vx
    cross[:, 2, 0], cross[:, 2, 1] = -vy, vx
    return np.eye(3) + cross + (cross @ cross) / (1.0 + c)[:, None, None]


def sight_information(frames: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Information matrices ``(N, 3, 3)`` (inverse covariances) of Gaussians whose
    standard deviations are ``sigma`` ``(3,)`` ``(lateral, lateral, along)`` in each
    frame of :func:`sight_frames`."""
    weights = 1.0 / np.asarray(sigma, dtype=np.float64) ** 2
    return np.einsum("nik,k,njk->nij", frames, weights, frames)
