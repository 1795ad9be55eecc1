"""Where the camera images a volume usefully: the depth range it resolves, its field of view
there, and the one check of a grid against them (docs/design.md §2.1).

A point at depth ``z`` is imaged at ``d'`` from the exit pupil; on the microlens array its
image is a blur disc ``D' |1 - 1/α|`` wide (``α = d'/d``, ``D'`` the exit pupil). The camera
resolves the depths where that disc satisfies both:

* **resolution**: each pixel's view of the point (its ray bundle, one pixel's footprint
  ``p_px d / f_ml`` on the exit pupil) spreads over at most :data:`VIEW_LENSES` microlenses,
  i.e. the disc spans at most ``VIEW_LENSES · N_u`` lenses (``N_u = D' f_ml / (d p_px)``,
  the pixels across a microlens image). At ``VIEW_LENSES = 1`` this is the exact
  refocusing range of a plenoptic camera (Ng 2005); beyond twice it reconstructions lose
  most particles;
* **light**: at least :data:`LIGHT_SHARE` of an on-axis point's light falls on the array.
  Beyond it the voxels send less than half their light to the sensor, which the
  reconstruction leaves out (``min_sensitivity = 0.5``): the volume would be empty.

Both bound ``|1 - 1/α|``; the range ends where the tighter one is reached (a near end never
beyond the main lens's focal length, ``z > f - s_o``, where no real image forms; a far end
possibly at infinity). Laterally a grid must overlap the array's field of view, the
array's extent carried into object space by the central rays (``x = -X'/α`` scaled by
``s_o'/s_i'``). Device-free; it imports only the camera model (a grid is any object with
``x``, ``y``, ``z``, ``rotation_deg`` and ``to_world``).
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera

__all__ = ["LIGHT_SHARE", "VIEW_LENSES", "check_grid", "field_of_view_mm",
           "in_field_of_view", "resolved_depth_range"]

#: Microlenses one pixel's view of a point may spread over at the ends of the resolved range.
VIEW_LENSES = 2.0
#: Share of an on-axis point's light that must reach the microlens array.
LIGHT_SHARE = 0.5
#: Strips across the array that the share of a blur disc on it is integrated over.
_STRIPS = 4096


def _array_box(camera: Camera) -> np.ndarray:
    """``[[x0, x1], [y0, y1]]`` array-plane mm covered by the microlenses (their centres'
    box widened by half a pitch)."""
    pos = camera.microlens_positions_mm().reshape(-1, 2)
    half = np.array([camera.ml_pitch_mm, camera.ml_row_pitch_mm]) / 2
    return np.column_stack([pos.min(0) - half, pos.max(0) + half])


def _disc_share(box: np.ndarray, diameter: float) -> float:
    """Share of a uniform disc of ``diameter`` centred on the axis inside ``box``: the
    chord lengths inside the box integrated across it (trapezoids, :data:`_STRIPS`)."""
    r = diameter / 2
    x0, x1 = max(box[0, 0], -r), min(box[0, 1], r)
    if x1 <= x0:
        return 0.0
    x = np.linspace(x0, x1, _STRIPS + 1)
    half = np.sqrt(np.maximum(r * r - x * x, 0.0))
    chord = np.clip(np.minimum(box[1, 1], half) - np.maximum(box[1, 0], -half), 0.0, None)
    area = float(((chord[1:] + chord[:-1]) / 2).sum() * (x1 - x0) / _STRIPS)
    return area / (math.pi * r * r)


def _light_limit_mm(box: np.ndarray, pitch: float) -> float:
    """Largest blur-disc diameter (mm) of which :data:`LIGHT_SHARE` still falls on the
    array ``box`` (the disc centred on the origin: the optical axis, or a region of
    interest's centre seen on the array)."""
    lo, hi = 0.0, 4 * float(np.abs(box).max()) + pitch
    for _ in range(50):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _disc_share(box, mid) >= LIGHT_SHARE else (lo, mid)
    return lo


def _blur_limit(camera: Camera, box: np.ndarray) -> float:
    """Largest ``|1 - 1/α|`` inside the resolved range: the tighter of the resolution
    limit (``VIEW_LENSES · p_ml`` per pixel footprint on the pupil) and the light limit
    (``box``: :func:`_array_box`)."""
    resolution = VIEW_LENSES * camera.ml_pitch_mm / camera.pixel_pupil_footprint_mm
    # a region of interest's discs centre on what its centre sees, not on the axis
    seen = camera.sensor_centre_on_array_mm()
    return min(resolution, _light_limit_mm(box - seen[:, None], camera.ml_pitch_mm)
               / camera.exit_pupil_diameter_mm)


def _depth_of_alpha(camera: Camera, alpha: float) -> float:
    """Object depth ``z`` imaged at ``d' = α d`` (``inf`` when it lies at or beyond the
    image of infinity)."""
    s_ip = alpha * camera.exit_pupil_distance_mm - camera.focal_length_mm * (
        camera.pupil_magnification - 1.0)
    f = camera.focal_length_mm
    if s_ip <= f:
        return math.inf
    return f * s_ip / (s_ip - f) - camera.object_distance_mm


def resolved_depth_range(camera: Camera) -> tuple[float, float]:
    """The depths ``(z_near, z_far)`` mm this camera resolves (the module's criterion).

    ``z_near`` is at least the focal-length limit ``f - s_o`` (excluded: no real image
    there); ``z_far`` may be ``inf``.
    """
    return _resolved(camera, _array_box(camera))


def _resolved(camera: Camera, box: np.ndarray) -> tuple[float, float]:
    """:func:`resolved_depth_range` of the array ``box`` (:func:`_array_box`)."""
    c = _blur_limit(camera, box)
    near = camera.focal_length_mm - camera.object_distance_mm
    if c < 1:
        near = _depth_of_alpha(camera, 1 / (1 - c))
    return near, _depth_of_alpha(camera, 1 / (1 + c))


def field_of_view_mm(camera: Camera, z: float) -> np.ndarray:
    """``[[x0, x1], [y0, y1]]`` object-space mm the array images at depth ``z`` (central
    rays; the main lens inverts the image)."""
    return _field(camera, z, _array_box(camera))


def in_field_of_view(camera: Camera, points) -> np.ndarray:
    """Bool ``(N,)``: whether each object point ``(x, y, z)`` mm (the camera's frame) lies
    within :func:`field_of_view_mm` at its own depth; the array's box found once for all
    points (a point at a time took 5 ms on the 16 MP camera)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    field = _field(camera, pts[:, 2], _array_box(camera))  # (N, 2, 2)
    return np.all((field[..., 0] <= pts[:, :2]) & (pts[:, :2] <= field[..., 1]), axis=1)


def _field(camera: Camera, z, box: np.ndarray) -> np.ndarray:
    """:func:`field_of_view_mm` of the array ``box`` (:func:`_array_box`); ``z`` a depth,
    or depths ``(N,)`` for fields ``(N, 2, 2)``."""
    z = np.asarray(z, dtype=np.float64)
    scale = camera.alpha(z) * (camera.object_distance_mm + z) / camera.image_distance_at(z)
    return np.sort(-box * scale[..., None, None], axis=-1)  # object mm per array mm


def check_grid(camera: Camera, grid) -> None:
    """Refuse a grid the camera cannot image usefully, naming the camera's range.

    Raises
    ------
    ValueError
        When the grid's depth extent reaches beyond :func:`resolved_depth_range` (or to the
        main lens's focal length, where no real image forms), or when no part of it lies
        in the field of view (:func:`field_of_view_mm`) at any of its depths. A posed
        camera's (world) grid is checked as its bounding box in the camera's frame
        (:func:`_check_posed`).
    """
    if camera.pose is not None:
        _check_posed(camera, grid)
        return
    box = _array_box(camera)
    near, far = _resolved(camera, box)
    limit = camera.focal_length_mm - camera.object_distance_mm
    z0, z1 = grid.z
    span = f"this camera resolves z in [{near:.2f}, {far:.2f}] mm"
    if z0 <= limit:
        raise ValueError(
            f"the grid's depth range z = ({z0:g}, {z1:g}) mm reaches z <= f - s_o = "
            f"{limit:.3f} mm, where the main lens forms no real image; {span}: move the "
            "volume into that range")
    if z0 < near or z1 > far:
        raise ValueError(
            f"the grid's depth range z = ({z0:g}, {z1:g}) mm reaches beyond the depths the "
            f"camera resolves: {span} (beyond, a point's image spreads over more than "
            f"{VIEW_LENSES:g} microlenses per pixel's view, or less than {LIGHT_SHARE:.0%} of "
            "its light reaches the array; docs/design.md §2.1). Move the volume into that "
            "range (plenocl grid --z), or focus the camera on it ([main_lens] magnification)")
    _check_lateral(camera, grid, box)


class _CameraBox:
    """An axis-aligned box in the camera's frame, as :func:`check_grid` reads a grid."""

    rotation_deg = 0.0

    def __init__(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.x, self.y, self.z = ((float(a), float(b)) for a, b in zip(lo, hi, strict=True))

    @staticmethod
    def to_world(vx, vy):
        return np.asarray(vx), np.asarray(vy)


def _check_posed(camera: Camera, grid) -> None:
    """:func:`check_grid` of a world grid seen by a posed camera: its corners in front of
    the camera (:meth:`plenocl.camera.Pose.check_in_front`), and their bounding box in
    the camera's frame within the depths it resolves and its field of view."""
    pose = camera.pose
    pts = pose.to_camera(grid.corners())
    pose.check_in_front(pts[:, 2], camera.focal_length_mm - camera.object_distance_mm)
    box = _CameraBox(pts.min(axis=0), pts.max(axis=0))
    try:
        check_grid(camera.with_pose(None), box)
    except ValueError as exc:
        raise ValueError(
            f"seen through the camera's pose (rotation_deg {list(pose.rotation_deg)}, "
            f"translation_mm {list(pose.translation_mm)}; docs/design.md §2.2) the world "
            f"grid spans x = ({box.x[0]:.3f}, {box.x[1]:.3f}), y = ({box.y[0]:.3f}, "
            f"{box.y[1]:.3f}), z = ({box.z[0]:.3f}, {box.z[1]:.3f}) mm in the camera's "
            f"frame, and there {exc}") from None


def _check_lateral(camera: Camera, grid, box: np.ndarray) -> None:
    """Refuse a grid no part of which lies in the field of view at any of its depths."""
    gx, gy = np.meshgrid(grid.x, grid.y)
    wx, wy = grid.to_world(gx.ravel(), gy.ravel())  # the grid's four corners
    depths = np.linspace(grid.z[0], grid.z[1], 33)
    fovs = [_field(camera, z, box) for z in depths]
    for fov in fovs:
        if (wx.max() >= fov[0, 0] and wx.min() <= fov[0, 1]
                and wy.max() >= fov[1, 0] and wy.min() <= fov[1, 1]):
            return
    a, b = fovs[0], fovs[-1]
    raise ValueError(
        f"the grid (x = {grid.x}, y = {grid.y} mm) lies entirely outside the camera's field "
        f"of view: at z = {grid.z[0]:g} mm it sees x in [{a[0, 0]:.2f}, {a[0, 1]:.2f}], "
        f"y in [{a[1, 0]:.2f}, {a[1, 1]:.2f}] mm, at z = {grid.z[1]:g} mm x in "
        f"[{b[0, 0]:.2f}, {b[0, 1]:.2f}], y in [{b[1, 0]:.2f}, {b[1, 1]:.2f}] mm; move the "
        "grid there (Grid.for_camera, plenocl grid, fit it)")
