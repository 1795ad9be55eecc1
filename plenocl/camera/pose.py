"""Where a camera stands in the world: its pose (docs/design.md §2.2, issue 49).

A world point ``X`` (mm) maps into the camera's own frame as ``R X + t``, with
``R = Rz Ry Rx`` the product of right-handed rotations about the world's axes by the
pose's ``rotation_deg`` ``(rx, ry, rz)`` (``Rx`` applied first) and ``t`` its
``translation_mm``. The camera's own frame is the one every stage works in today: the
optical axis along ``z``, the nominal focal plane at ``z = 0``, the main lens's front
principal point at ``(0, 0, -s_o)``. A camera without a pose stands at the world frame
(``R = I``, ``t = 0``), and its results are those of a camera before poses existed.

Plain NumPy, as the rest of :mod:`plenocl.camera`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .lattice import rotation_matrix

__all__ = ["POSE_KEYS", "Pose", "pose_rotation", "require_world_frame"]

#: The keys of a camera file's ``[pose]`` section.
POSE_KEYS = ("rotation_deg", "translation_mm")


def pose_rotation(rotation_deg) -> np.ndarray:
    """``Rz Ry Rx`` ``(3, 3)`` for right-handed rotations ``(rx, ry, rz)`` (degrees) about
    the world's x, y and z axes, applied in that order: each the counter-clockwise plane
    rotation (:func:`plenocl.camera.lattice.rotation_matrix`) of the next two axes in
    cyclic order, (y, z), (z, x), (x, y)."""
    r = np.eye(3)
    for axis, degrees in enumerate(rotation_deg):
        plane = [(axis + 1) % 3, (axis + 2) % 3]
        turn = np.eye(3)
        turn[np.ix_(plane, plane)] = rotation_matrix(float(degrees))
        r = turn @ r
    return r


def _triple(name: str, value) -> tuple[float, float, float]:
    """Three finite numbers, or a ValueError naming ``name``."""
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"[pose] {name} must be three numbers (x, y, z), got {value!r}"
                         ) from None
    if len(out) != 3 or not all(map(math.isfinite, out)):
        raise ValueError(f"[pose] {name} must be three finite numbers (x, y, z), got "
                         f"{value!r}")
    return out


@dataclass(frozen=True)
class Pose:
    """A camera's pose: ``X_camera = R X_world + t`` (module documentation).

    Parameters
    ----------
    rotation_deg
        ``(rx, ry, rz)``: right-handed rotations about the world's x, y and z axes, in
        degrees, applied in that order (``R = Rz Ry Rx``).
    translation_mm
        ``t``, the world origin's position in the camera's frame (mm).
    """

    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "rotation_deg", _triple("rotation_deg", self.rotation_deg))
        object.__setattr__(self, "translation_mm",
                           _triple("translation_mm", self.translation_mm))

    @property
    def matrix(self) -> np.ndarray:
        """``R`` ``(3, 3)``."""
        return pose_rotation(self.rotation_deg)

    def to_camera(self, points_xyz) -> np.ndarray:
        """World points ``(N, 3)`` (mm) in the camera's frame: ``R X + t``."""
        pts = np.asarray(points_xyz, float).reshape(-1, 3)
        return pts @ self.matrix.T + np.asarray(self.translation_mm)

    def to_world(self, points_xyz) -> np.ndarray:
        """Points ``(N, 3)`` of the camera's frame (mm) in the world: ``R^T (X - t)``."""
        pts = np.asarray(points_xyz, float).reshape(-1, 3)
        return (pts - np.asarray(self.translation_mm)) @ self.matrix

    def turn_deg(self, other: Pose) -> float:
        """The angle (degrees) of the rotation that carries this pose's onto ``other``'s."""
        cos = (np.trace(other.matrix @ self.matrix.T) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def shift_mm(self, other: Pose) -> float:
        """The distance (mm) between this pose's translation and ``other``'s."""
        return float(np.linalg.norm(np.subtract(other.translation_mm, self.translation_mm)))

    def check_in_front(self, camera_z, nearest: float) -> None:
        """Refuse points whose depth in the camera's frame ``camera_z`` (mm) is at or
        below ``nearest`` (the camera's ``f - s_o``: at or behind the main lens's front
        focal plane, where it forms no image): the pose puts them behind the camera."""
        z = np.asarray(camera_z, float)
        behind = ~(z > nearest)
        if behind.any():
            raise ValueError(
                f"the camera's pose (rotation_deg {list(self.rotation_deg)}, translation_mm "
                f"{list(self.translation_mm)}) puts {int(behind.sum())} of {z.size} points at "
                f"a depth of {float(np.nanmin(z)):.3f} mm or less in the camera's frame, at or "
                f"behind its main lens's front focal plane (z = {nearest:.3f} mm), where it "
                "forms no image: the camera looks along its frame's +z, and X_camera = R "
                "X_world + t (docs/design.md §2.2); check the pose's rotation (a camera "
                "turned 180 degrees looks away) and the sign of its translation")

    def to_dict(self) -> dict:
        """The camera file's ``[pose]`` section."""
        return {"rotation_deg": list(self.rotation_deg),
                "translation_mm": list(self.translation_mm)}

    @classmethod
    def from_dict(cls, doc: dict, source: str = "camera") -> Pose:
        """The pose of a camera file's ``[pose]`` section; both keys are needed."""
        missing = [key for key in POSE_KEYS if key not in doc]
        if missing:
            raise ValueError(f"{source}: [pose] lacks {', '.join(missing)} (both "
                             "rotation_deg = [rx, ry, rz] and translation_mm = [tx, ty, tz]; "
                             "docs/design.md §2.2); leave [pose] out for a camera at the "
                             "world frame")
        return cls(doc["rotation_deg"], doc["translation_mm"])


def require_world_frame(camera, what: str) -> None:
    """Refuse a posed camera where ``what`` works in the camera's own frame only."""
    if camera.pose is not None:
        raise ValueError(
            f"{what} works in the camera's own frame and does not take a posed camera (the "
            "camera file's [pose]): give it the camera without its pose "
            "(camera.with_pose(None)) and carry the result into the world with "
            "Pose.to_world, or give the world grid yourself (projectors, reconstruct and "
            "process_pair take a posed camera with a world grid; docs/design.md §2.2)")


def check_distinct_views(cameras) -> None:
    """Several cameras in one reconstruction see the volume differently: two with the
    same pose (``None``, no pose, is the world frame) and the same main lens (focal
    length, f-number, magnification) would give one view twice, which measures no depth
    and weighs that view double; refused, naming them and the fix. (The same pose with
    another focus, behind a beam splitter say, is another view.)"""
    def view(camera) -> tuple:
        pose = Pose() if camera.pose is None else camera.pose
        return (*pose.rotation_deg, *pose.translation_mm, camera.focal_length_mm,
                camera.f_number, camera.magnification)

    views = [np.asarray(view(c), float) for c in cameras]
    for j, first in enumerate(views, start=1):
        for k, other in enumerate(views[j:], start=j + 1):
            if np.allclose(first, other, rtol=1e-12, atol=1e-9):
                raise ValueError(
                    f"cameras {j} and {k} have the same pose (rotation {tuple(first[:3])} "
                    f"deg, translation {tuple(first[3:6])} mm) and main lens: one view "
                    "twice. Several cameras must see the volume from different places: "
                    "give each camera its own pose ([pose] in its camera file, "
                    "Camera.with_pose, or plenocl.calibrate_pose from a dot target), or "
                    "list each camera file once")
