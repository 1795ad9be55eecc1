"""The unfocused plenoptic camera (docs/design.md §2): optics, microlens layout, TOML files.

Units are millimetres. Sensor coordinates have their origin on the optical axis, which
crosses the whole sensor's centre: pixel ``(col, row)`` of a ``W x H`` sensor has its centre
at ``((col + 0.5) - W/2) * p_px``, ``((row + 0.5) - H/2) * p_px``; a region of interest's
pixels are counted from its origin on the whole sensor (:meth:`Camera.cropped`). The
main lens inverts the image.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..io.tomlfile import read_toml, write_toml
from ..options import refuse_unknown
from .lattice import LensLayout, lens_layout
from .pose import POSE_KEYS, Pose
from .region import region_fields

#: Microlens images that fill their pitch less than this (fraction) trigger a warning.
UNDERFILL_WARN = 0.80
#: Microlens images wider than their pitch by more than this fraction trigger a warning.
OVERLAP_WARN = 0.02


def _positive(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"camera {name} must be a positive finite number, got {value!r}"
                         ) from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"camera {name} must be a positive finite number, got {value!r}")
    return value


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"camera {name} must be a finite number (0 for a thin lens)")
    return value


def _origin(value) -> tuple[int, int]:
    try:
        col, row = (int(v) for v in value)
        ok = all(float(v) == int(v) for v in value) and col >= 0 and row >= 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"sensor crop_origin must be two integers >= 0 [column, row] (the "
                         f"region of interest's first pixel in the full frame), got {value!r}")
    return col, row


def _count_pair(name: str, value) -> tuple[int, int]:
    try:
        pair = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        pair = ()
    if len(pair) != 2 or min(pair) <= 0 or any(int(v) != v for v in value):
        raise ValueError(f"camera {name} must be two positive integers [columns, rows], "
                         f"got {value!r}")
    return pair


@dataclass(frozen=True, eq=False)
class Camera:
    """An unfocused plenoptic camera: main lens, microlens array, sensor.

    Parameters
    ----------
    focal_length_mm, f_number, magnification
        Main lens focal length, f-number (entrance pupil ``D = f/N``) and ``|M|`` at the
        nominal focal plane.
    ml_pitch_mm, ml_focal_length_mm, ml_count
        Microlens pitch, focal length and ``(columns, rows)``.
    pixel_pitch_mm, pixels
        Sensor pixel pitch and ``(columns, rows)``.
    ml_rotation_deg, ml_offset_mm
        Physical layout of the array on its plane (rotation about the optical axis,
        lateral shift). The simulator uses them; calibration measures their effect.
    ml_layout, ml_odd_row_shift
        ``"rectangular"`` (default) or ``"hexagonal"``: rows ``pitch·√3/2`` apart, the odd
        rows (1, 3, ...) shifted along the row by ``ml_odd_row_shift`` pitches (+0.5, the
        default, or -0.5) against the even ones (docs/design.md §2).
    microlens_centers
        Microlens image centres ``(rows, cols, 2)`` as ``(col, row)`` pixels; the ideal
        centres of the layout when not given. ``NaN`` marks a lens calibration missed.
    crop_origin, full_pixels
        A region of interest (:meth:`cropped`): its first pixel ``(column, row)`` on the
        whole sensor, and the whole sensor's ``(columns, rows)``; ``pixels`` are then the
        region's. The optical axis crosses the whole sensor's centre, so positions seen
        through an off-centre region are the whole frame's. Without ``full_pixels`` (a
        camera file written before 2026-12) the axis is taken at the region's centre.
    pupil_magnification, principal_plane_separation_mm
        A thick main lens (docs/design.md §2): the exit pupil's diameter over the
        entrance pupil's, ``m_p``, and the distance from the front principal plane to
        the rear one (positive when the rear lies nearer the sensor). The defaults,
        1 and 0, are the thin lens.
    pose
        Where the camera stands in the world (:class:`plenocl.camera.pose.Pose`: a world
        point ``X`` is ``R X + t`` in the camera's frame; docs/design.md §2.2). ``None``
        (the default): the camera's frame is the world's.
    """

    focal_length_mm: float
    f_number: float
    magnification: float
    ml_pitch_mm: float
    ml_focal_length_mm: float
    ml_count: tuple[int, int]
    pixel_pitch_mm: float
    pixels: tuple[int, int]
    ml_rotation_deg: float = 0.0
    ml_offset_mm: tuple[float, float] = (0.0, 0.0)
    microlens_centers: np.ndarray | None = field(default=None, repr=False)
    calibrated: bool = False
    crop_origin: tuple[int, int] | None = None
    full_pixels: tuple[int, int] | None = None
    pupil_magnification: float = 1.0
    principal_plane_separation_mm: float = 0.0
    ml_layout: str = "rectangular"
    ml_odd_row_shift: float | None = None
    layout: LensLayout = field(init=False, repr=False)
    pose: Pose | None = None

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "f_number", "magnification", "ml_pitch_mm",
                     "ml_focal_length_mm", "pixel_pitch_mm", "pupil_magnification"):
            object.__setattr__(self, name, _positive(name, getattr(self, name)))
        object.__setattr__(self, "ml_count", _count_pair("microlens count", self.ml_count))
        object.__setattr__(self, "pixels", _count_pair("sensor pixels", self.pixels))
        rot, off = float(self.ml_rotation_deg), tuple(float(v) for v in self.ml_offset_mm)
        if not (math.isfinite(rot) and all(map(math.isfinite, off)) and len(off) == 2):
            raise ValueError("microlens rotation and offset must be finite numbers")
        object.__setattr__(self, "ml_rotation_deg", rot)
        object.__setattr__(self, "ml_offset_mm", off)
        object.__setattr__(self, "layout", lens_layout(self.ml_layout, self.ml_count,
                                                       self.ml_odd_row_shift))
        object.__setattr__(self, "principal_plane_separation_mm", _finite(
            "principal_plane_separation_mm", self.principal_plane_separation_mm))
        self._check_region()
        if self.pose is not None and not isinstance(self.pose, Pose):
            raise TypeError(f"pose must be a plenocl.camera.Pose or None, got "
                            f"{type(self.pose).__name__}")
        self._check_sensor_covers_array()
        self._check_fill()
        object.__setattr__(self, "microlens_centers", self._validated_centers())

    # ---- validation -------------------------------------------------------------
    def _check_region(self) -> None:
        """``crop_origin`` as two whole pixels, and ``full_pixels`` (only with it) holding
        the region."""
        if self.crop_origin is not None:
            object.__setattr__(self, "crop_origin", _origin(self.crop_origin))
        if self.full_pixels is None:
            return
        full = _count_pair("whole sensor's pixels (full_pixels)", self.full_pixels)
        object.__setattr__(self, "full_pixels", full)
        origin = self.crop_origin
        if origin is None or any(o + n > f for o, n, f in zip(origin, self.pixels, full)):
            raise ValueError(
                f"[sensor] full_pixels {list(full)} is the whole sensor a region of interest "
                f"is cut from: it needs crop_origin, and the region ({self.pixels[0]} x "
                f"{self.pixels[1]} px from {list(origin or ())}) must lie inside it")

    @property
    def odd_row_shift(self) -> float:
        """How far (pitches, along the row) the odd rows of lenses sit from the even ones:
        0 for a rectangular array, ``ml_odd_row_shift`` (default +0.5) for a hexagonal one."""
        return self.layout.odd_row_shift

    def _check_sensor_covers_array(self) -> None:
        # the array's lenses are those whose image centre lies on the sensor (design.md
        # §2): the outermost centres (of the even rows), a pitch inside the array's
        # edges, fit on the sensor (a hexagonal array's axial view: the array's own)
        mla = np.array(self.layout.array_count) * [self.ml_pitch_mm, self.ml_row_pitch_mm]
        sensor = np.array(self.pixels) * self.pixel_pitch_mm
        if np.any(mla - [self.ml_pitch_mm, self.ml_row_pitch_mm] > sensor * (1 + 1e-9)):
            raise ValueError(
                f"the microlens array ({mla[0]:.3f} x {mla[1]:.3f} mm) is larger than the "
                f"sensor ({sensor[0]:.3f} x {sensor[1]:.3f} mm) by more than a lens: count "
                "only the lenses whose image centre lies on the sensor ([microlens_array] "
                "count), and check the microlens pitch against the sensor's pixel pitch "
                "and pixel count"
            )
        if self.pixels_per_microlens < 2:
            raise ValueError(
                f"only {self.pixels_per_microlens:.2f} pixels per microlens: a plenoptic "
                "camera needs several pixels behind each microlens to sample the aperture"
            )

    def _check_fill(self) -> None:
        fill = self.microlens_image_fill
        if fill > 1 + OVERLAP_WARN:
            warnings.warn(
                f"microlens images overlap by {100 * (fill - 1):.1f}% of the pitch: the main "
                f"lens at f/{self.f_number:g} is faster than the microlenses "
                f"(working f-number {self.working_f_number:.2f} vs "
                f"{self.ml_focal_length_mm / self.ml_pitch_mm:.2f}); stop it down",
                stacklevel=3,
            )
        elif fill < UNDERFILL_WARN:
            warnings.warn(
                f"microlens images fill only {100 * fill:.1f}% of the pitch "
                f"({100 * (1 - fill):.1f}% underfill): the main lens f-number does not match "
                "the microlenses and angular resolution is wasted",
                stacklevel=3,
            )

    def _validated_centers(self) -> np.ndarray:
        cols, rows = self.ml_count
        if self.microlens_centers is None:
            centers = self.ideal_microlens_centers()
        else:
            centers = np.array(self.microlens_centers, dtype=np.float64)
            if centers.shape != (rows, cols, 2):
                raise ValueError(
                    f"microlens_centers must have shape (rows, cols, 2) = {(rows, cols, 2)}, "
                    f"got {centers.shape}"
                )
            if np.isinf(centers).any():
                raise ValueError("microlens_centers contain Inf; use NaN for missing lenses")
        centers.flags.writeable = False
        return centers

    # ---- optics -----------------------------------------------------------------
    @property
    def aperture_diameter_mm(self) -> float:
        """Main-lens entrance pupil diameter ``D = f/N`` (a thin lens: its aperture)."""
        return self.focal_length_mm / self.f_number

    @property
    def object_distance_mm(self) -> float:
        """Nominal object distance ``s_o = f (1 + 1/M)`` (from the front principal plane)."""
        return self.focal_length_mm * (1 + 1 / self.magnification)

    @property
    def image_distance_mm(self) -> float:
        """Rear principal plane to microlens array, ``s_i = f (1 + M)``."""
        return self.focal_length_mm * (1 + self.magnification)

    @property
    def exit_pupil_diameter_mm(self) -> float:
        """Exit pupil diameter ``D' = m_p D``: the cone of every image-space ray."""
        return self.exit_pupil_diameter_at(self.f_number)

    def exit_pupil_diameter_at(self, f_number: float) -> float:
        """Exit pupil diameter with the lens stopped to ``f_number``, ``m_p f / N``."""
        return self.pupil_magnification * self.focal_length_mm / f_number

    @property
    def entrance_pupil_distance_mm(self) -> float:
        """Distance of the entrance pupil's centre from the nominal focal plane,
        ``s_o + f (1/m_p - 1)`` (a thin lens: ``s_o``): the centre of the camera's
        perspective, through which a point's chief ray (its lateral image position, the
        central view's place on the array) runs."""
        return self.object_distance_mm + self.focal_length_mm * (
            1.0 / self.pupil_magnification - 1.0)

    @property
    def exit_pupil_distance_mm(self) -> float:
        """Exit pupil to microlens array, ``d = f (M + m_p)`` (the pupil lies ``f (1 -
        m_p)`` behind the rear principal plane; a thin lens: ``s_i``). Every image-space
        ray geometry measures from here: the aperture coordinates ``(u, v)`` lie on it."""
        return self.focal_length_mm * (self.magnification + self.pupil_magnification)

    @property
    def focal_plane_distance_mm(self) -> float:
        """Nominal focal plane to microlens array along the axis, ``s_o + HH' + s_i``."""
        return (self.object_distance_mm + self.principal_plane_separation_mm
                + self.image_distance_mm)

    @property
    def working_f_number(self) -> float:
        """Image-side f-number ``d / D' = N (1 + M/m_p)``; matches ``f_ml / p_ml`` in a
        well-built camera."""
        return self.exit_pupil_distance_mm / self.exit_pupil_diameter_mm

    @property
    def lens_image_scale(self) -> float:
        """The imaging relation of the microlens images: a lens at array-plane position
        ``x_k`` (from the optical axis) images the exit pupil centred at ``c_k = x_k (1 +
        f_ml/d)`` on the sensor. The one place plenocl computes it
        (:mod:`plenocl.optics.imaging` builds on it)."""
        return 1 + self.ml_focal_length_mm / self.exit_pupil_distance_mm

    @property
    def microlens_image_pitch_mm(self) -> float:
        """Spacing of microlens images on the sensor, ``p_ml (1 + f_ml / d)``."""
        return self.ml_pitch_mm * self.lens_image_scale

    @property
    def microlens_image_fill(self) -> float:
        """Diameter of a microlens image of the aperture over the image pitch."""
        diameter = self.ml_focal_length_mm / self.working_f_number
        return diameter / self.microlens_image_pitch_mm

    @property
    def pixels_per_microlens(self) -> float:
        """Pixels across one microlens image."""
        return self.microlens_image_pitch_mm / self.pixel_pitch_mm

    @property
    def depth_resolution_mm(self) -> float:
        """How far from the focal plane (either side, object space) a point's defocus blur
        on the array grows to one microlens pitch, ``p_ml N_w / M²``: the camera's depth
        resolution. Within it of the plane a particle lights a single microlens and its
        depth is ambiguous."""
        return self.ml_pitch_mm * self.working_f_number / self.magnification**2

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        """Sensor ``(width, height)``."""
        return (self.pixels[0] * self.pixel_pitch_mm, self.pixels[1] * self.pixel_pitch_mm)

    def image_distance_at(self, z_mm) -> np.ndarray:
        """Image distance ``s_i'`` (from the rear principal plane) of object depth ``z``
        (+z away from the camera)."""
        s_o = self.object_distance_mm + np.asarray(z_mm, dtype=np.float64)
        if not np.all(np.isfinite(s_o)):
            raise ValueError(f"depth z must be a finite number of mm, got {z_mm!r}")
        if np.any(s_o <= self.focal_length_mm):
            raise ValueError(
                f"depth z must satisfy z > {self.focal_length_mm - self.object_distance_mm:.3f}"
                f" mm (an object at or inside the focal length of the main lens forms no "
                "real image); move the volume away from the camera"
            )
        return self.focal_length_mm * s_o / (s_o - self.focal_length_mm)

    def pupil_distance_at(self, z_mm) -> np.ndarray:
        """Distance ``d'`` of the image of depth ``z`` from the exit pupil, ``s_i' - s_i +
        d`` (a thin lens: ``s_i'``): where a ray from aperture point ``(u, v)`` to the image
        point meets the array, ``x = u + (X' - u) d / d'``."""
        return self._from_pupil(self.image_distance_at(z_mm))

    def _from_pupil(self, s_ip):
        """``d' = s_i' - s_i + d = s_i' + f (m_p - 1)``: the image distance from the exit
        pupil (a thin lens: ``s_i'`` itself, to the last bit)."""
        if self.pupil_magnification == 1.0:
            return s_ip
        return s_ip + self.focal_length_mm * (self.pupil_magnification - 1.0)

    def alpha(self, z_mm) -> np.ndarray:
        """Refocus parameter ``α = d'/d`` of depth ``z`` (a thin lens: ``s_i'/s_i``)."""
        return self.pupil_distance_at(z_mm) / self.exit_pupil_distance_mm

    def image_points(self, points_xyz) -> np.ndarray:
        """Image-space ``(X', Y', d')`` of object points ``(N, 3)``: the lateral image
        position ``-(s_i'/s_o') (X, Y)`` and the image's distance from the exit pupil
        (:meth:`pupil_distance_at`; a thin lens: ``s_i'``). The points are in the world's
        frame: a posed camera takes them into its own first (:attr:`pose`)."""
        pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        if self.pose is not None:
            pts = self.pose.to_camera(pts)
            self.pose.check_in_front(pts[:, 2], self.focal_length_mm - self.object_distance_mm)
        s_ip = self.image_distance_at(pts[:, 2])
        scale = -s_ip / (self.object_distance_mm + pts[:, 2])
        return np.column_stack([pts[:, 0] * scale, pts[:, 1] * scale, self._from_pupil(s_ip)])

    @property
    def pixel_pupil_footprint_mm(self) -> float:
        """One sensor pixel's footprint on the exit pupil, ``p_px d / f_ml``: the step of
        the aperture coordinate between neighbouring pixels behind a microlens."""
        return self.pixel_pitch_mm * self.exit_pupil_distance_mm / self.ml_focal_length_mm

    def aperture_u_of_offset(self, offset_mm):
        """Exit-pupil coordinate seen by a pixel ``offset_mm`` from its microlens image
        centre, ``-offset d / f_ml``."""
        return -np.asarray(offset_mm) * self.exit_pupil_distance_mm / self.ml_focal_length_mm

    # ---- microlens layout --------------------------------------------------------
    def _rotation(self) -> tuple[float, float]:
        t = math.radians(self.ml_rotation_deg)
        return math.cos(t), math.sin(t)

    @property
    def ml_row_pitch_mm(self) -> float:
        """Distance between neighbouring rows of lenses: the pitch, or ``pitch·√3/2`` for a
        hexagonal array."""
        return self.ml_pitch_mm * self.layout.row_ratio

    def on_lens_lattice(self) -> Camera:
        """This camera with its lenses numbered on an affine lattice: itself for a
        rectangular array; for a hexagonal one its axial view (docs/design.md §5), the
        lenses at axial indices ``(q - q_min, r)``, ``NaN`` where the parallelogram holds
        no lens of the array, so that the weighting function and projector, written for
        (possibly sheared) affine lattices, take it as it is. Only for them: the view is
        not simulated, written or calibrated."""
        return self.layout.lattice_view(self)

    def lens_lattice_coords(self) -> np.ndarray:
        """``(rows, cols, 2)`` position of every lens in the array's own frame, in pitches
        along the rows and rows down: ``(kx + shift·(ky odd), ky)`` (``shift``:
        :attr:`odd_row_shift`, 0 for a rectangular array)."""
        return self.layout.lattice_coords()

    def microlens_positions_mm(self) -> np.ndarray:
        """Microlens centres on the array plane, ``(rows, cols, 2)`` as ``(x, y)`` mm."""
        cols, rows = self.ml_count
        k = self.lens_lattice_coords()
        aa = (k[..., 0] - (cols - 1) / 2) * self.ml_pitch_mm
        bb = (k[..., 1] - (rows - 1) / 2) * self.ml_row_pitch_mm
        c, s = self._rotation()
        x = c * aa - s * bb + self.ml_offset_mm[0]
        y = s * aa + c * bb + self.ml_offset_mm[1]
        return np.stack([x, y], axis=-1)

    def ideal_microlens_centers(self) -> np.ndarray:
        """Microlens image centres ``c_k = x_k (1 + f_ml/d)`` as ``(col, row)`` pixels."""
        ck = self.microlens_positions_mm() * self.lens_image_scale
        return self.mm_to_px(ck)

    @property
    def sensor_edge_px(self) -> np.ndarray:
        """``(col, row)`` of the optical axis counted from the sensor's first pixel's
        outer edge (``W/2, H/2`` for a whole sensor; a region's from its own edge):
        ``mm_to_px(xy) = xy / p_px + sensor_edge_px - 0.5``."""
        if self.full_pixels is None:
            return np.array(self.pixels, dtype=np.float64) / 2
        return (np.array(self.full_pixels, dtype=np.float64) / 2
                - np.array(self.crop_origin, dtype=np.float64))

    def mm_to_px(self, xy_mm) -> np.ndarray:
        """Sensor ``(x, y)`` mm (from the optical axis) to ``(col, row)`` pixel
        coordinates (pixel centres at .0)."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        return xy / self.pixel_pitch_mm + self.sensor_edge_px - 0.5

    def px_to_mm(self, colrow) -> np.ndarray:
        """``(col, row)`` pixel coordinates to sensor ``(x, y)`` mm (from the axis)."""
        cr = np.asarray(colrow, dtype=np.float64)
        return (cr + 0.5 - self.sensor_edge_px) * self.pixel_pitch_mm

    def sensor_centre_on_array_mm(self) -> np.ndarray:
        """Array-plane ``(x, y)`` mm of the lens whose image centre is the sensor's (a
        region's) centre: ``(0, 0)`` for a whole sensor (the depth range's blur discs
        centre there, :mod:`plenocl.optics.depthrange`)."""
        middle = (np.array(self.pixels, dtype=np.float64) - 1) / 2
        return self.px_to_mm(middle) / self.lens_image_scale

    def field_centre_mm(self) -> np.ndarray:
        """Object-space ``(x, y)`` mm at the nominal focal plane that the sensor's (a
        region's) centre sees: ``(0, 0)`` for a whole sensor; :meth:`Grid.for_camera
        <plenocl.Grid.for_camera>` centres its grid there."""
        return -self.sensor_centre_on_array_mm() / self.magnification

    def with_layout(self, name: str, odd_row_shift: float | None = None) -> Camera:
        """This camera with a ``name`` array (:data:`LAYOUTS`) of the same pitch on the same
        sensor, uncalibrated: as many lenses per row, and as many rows as the array's
        height holds (a hexagonal array's rows lie ``pitch·√3/2`` apart; docs/design.md
        §2)."""
        layout = lens_layout(name, self.ml_count, odd_row_shift, view=False)
        cols, rows = self.ml_count
        count = (cols, layout.rows_within(rows * self.layout.row_ratio))
        return replace(self, ml_layout=name, ml_count=count, ml_odd_row_shift=odd_row_shift,
                       microlens_centers=None, calibrated=False)

    def with_pose(self, pose: Pose | None) -> Camera:
        """A copy standing at ``pose`` (``None``: the world frame, the camera's own)."""
        return replace(self, pose=pose)

    def with_centers(self, centers: np.ndarray) -> Camera:
        """A copy with calibrated microlens image centres."""
        return replace(self, microlens_centers=np.asarray(centers, float), calibrated=True)

    # ---- region of interest --------------------------------------------------------
    def cropped(self, origin: tuple[int, int], size: tuple[int, int]) -> Camera:
        """The camera seen through a region of interest of its frames: ``size`` =
        ``(columns, rows)`` pixels from ``origin`` = ``(column, row)``.

        Give the camera of the whole sensor (``[microlens_array] count``: the whole
        array's lenses). The region keeps the lenses whose image centre lies in it, where
        they stand on the whole array, and the optical axis where it crosses the whole
        sensor (``[sensor] crop_origin`` and ``full_pixels``), so positions seen through
        an off-centre region are the whole frame's; full frames read later are cut
        alike (:meth:`fit_image`). A calibrated camera's region keeps its lenses'
        measured centres, less ``origin`` (``NaN`` stays ``NaN``; the lenses are chosen
        on the nominal layout, as uncalibrated). A region's camera may be cropped
        again: ``origin`` then counts in its pixels, and the result is the whole
        sensor's region that far further on (docs/design.md §2, §3).
        """
        origin, size = _origin(origin), _count_pair("region of interest's size", size)
        return replace(self, **region_fields(self, origin, size))

    def fit_image(self, image, name: str = "image") -> np.ndarray:
        """``image`` as this camera's sensor sees it: as it is when its shape is the
        sensor's, else a whole frame (at least ``full_pixels``) cut to the recorded
        region of interest (``crop_origin``); any other frame (one that does not hold the
        region, or a region of the sensor itself) is an error naming the fix."""
        img = np.asarray(image)
        want = (self.pixels[1], self.pixels[0])
        if img.shape == want:
            return img
        if self.crop_origin is not None and img.ndim == 2:
            col, row = self.crop_origin
            # a frame of the whole sensor or larger (a camera writing a column more);
            # a frame between the region and the whole sensor (another region) is refused
            least = (row + want[0], col + want[1]) if self.full_pixels is None else \
                (self.full_pixels[1], self.full_pixels[0])
            if img.shape[0] >= least[0] and img.shape[1] >= least[1]:
                return img[row:row + want[0], col:col + want[1]]
        raise ValueError(
            f"{name} is {img.shape[-1]} x {img.shape[0]} px (columns x rows), which does not "
            f"match the camera's sensor of {want[1]} x {want[0]}"
            + (f" from ({self.crop_origin[0]}, {self.crop_origin[1]})" if self.crop_origin
               else "")
            + (f" of the whole {self.full_pixels[0]} x {self.full_pixels[1]} sensor"
               if self.full_pixels else "")
            + ": give the region of interest of the frames (--crop COLUMN ROW "
            "WIDTH HEIGHT, or camera.cropped(origin, size)), or correct [sensor] pixels")

    def describe(self) -> str:
        """A short human-readable summary of the derived optics."""
        thick = "" if self.is_thin_lens else (
            f", exit pupil {self.exit_pupil_diameter_mm:.2f} mm wide "
            f"{self.exit_pupil_distance_mm:.2f} mm before the array (working "
            f"f/{self.working_f_number:.2f}), focal plane {self.focal_plane_distance_mm:.2f} "
            "mm from the array")
        return (
            f"f={self.focal_length_mm:g} mm f/{self.f_number:g} |M|={self.magnification:g}: "
            f"s_o={self.object_distance_mm:.2f} mm, s_i={self.image_distance_mm:.2f} mm, "
            f"D={self.aperture_diameter_mm:.2f} mm{thick}; "
            f"{self.ml_count[0]}x{self.ml_count[1]} "
            f"microlenses, {self.pixels_per_microlens:.2f} px each, image fill "
            f"{100 * self.microlens_image_fill:.1f}%"
            + ("" if self.pose is None else
               f"; posed: rotation {list(self.pose.rotation_deg)} deg, translation "
               f"{list(self.pose.translation_mm)} mm")
        )

    @property
    def is_thin_lens(self) -> bool:
        """Whether the main lens is the thin one (``m_p = 1``, no principal-plane gap)."""
        return self.pupil_magnification == 1.0 and self.principal_plane_separation_mm == 0.0

    # ---- files ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The camera as TOML-ready nested dictionaries (docs/design.md §2 keys; a thick
        lens's two keys only when they differ from the thin lens)."""
        lens = {"focal_length_mm": self.focal_length_mm, "f_number": self.f_number,
                "magnification": self.magnification}
        if not self.is_thin_lens:
            lens["pupil_magnification"] = self.pupil_magnification
            lens["principal_plane_separation_mm"] = self.principal_plane_separation_mm
        doc = {
            "main_lens": lens,
            "microlens_array": {**self.layout.file_keys(), "pitch_mm": self.ml_pitch_mm,
                                "focal_length_mm": self.ml_focal_length_mm,
                                "count": list(self.ml_count),
                                "rotation_deg": self.ml_rotation_deg,
                                "offset_mm": list(self.ml_offset_mm)},
            "sensor": {"pixel_pitch_mm": self.pixel_pitch_mm, "pixels": list(self.pixels)},
        }
        if self.crop_origin is not None:
            doc["sensor"]["crop_origin"] = list(self.crop_origin)
        if self.full_pixels is not None:
            doc["sensor"]["full_pixels"] = list(self.full_pixels)
        if self.calibrated:
            c = self.microlens_centers
            doc["calibration"] = {"centers_col": c[..., 0].tolist(),
                                  "centers_row": c[..., 1].tolist()}
        if self.pose is not None:
            doc["pose"] = self.pose.to_dict()
        return doc

    @classmethod
    def from_dict(cls, doc: dict, source: str = "camera") -> Camera:
        """Build a camera from the nested dictionaries of a camera file; an unknown
        section or key (a misspelt optional one included) is an error naming it."""
        _check_keys(doc, source)
        try:
            lens, mla, sensor = doc["main_lens"], doc["microlens_array"], doc["sensor"]
            kwargs = dict(
                focal_length_mm=lens["focal_length_mm"], f_number=lens["f_number"],
                magnification=lens["magnification"], ml_pitch_mm=mla["pitch_mm"],
                pupil_magnification=lens.get("pupil_magnification", 1.0),
                principal_plane_separation_mm=lens.get("principal_plane_separation_mm", 0.0),
                ml_focal_length_mm=mla["focal_length_mm"], ml_count=mla["count"],
                ml_rotation_deg=mla.get("rotation_deg", 0.0),
                ml_offset_mm=mla.get("offset_mm", (0.0, 0.0)),
                ml_layout=mla.get("layout", "rectangular"),
                ml_odd_row_shift=mla.get("odd_row_shift"),
                pixel_pitch_mm=sensor["pixel_pitch_mm"], pixels=sensor["pixels"],
                crop_origin=sensor.get("crop_origin"), full_pixels=sensor.get("full_pixels"),
            )
        except KeyError as exc:
            raise ValueError(f"{source} lacks the key {exc.args[0]!r} (see docs/design.md §2 "
                             "for the camera file's sections and keys)") from None
        cal = doc.get("calibration")
        if cal:
            kwargs["microlens_centers"] = np.stack(
                [np.array(cal["centers_col"], float), np.array(cal["centers_row"], float)], -1)
            kwargs["calibrated"] = True
        if "pose" in doc:
            kwargs["pose"] = Pose.from_dict(doc["pose"], source)
        camera = cls(**kwargs)
        if camera.crop_origin is not None and camera.full_pixels is None:
            warnings.warn(
                f"{source} records a region of interest ([sensor] crop_origin) but not the "
                "whole sensor's size, so plenocl takes the optical axis at the region's "
                "centre: positions (grids, particles, the vectors' coordinates) are off by "
                "the region's offset from the sensor's centre over the magnification. Add "
                "[sensor] full_pixels = [columns, rows] of the whole sensor (docs/design.md "
                "§2)", stacklevel=2)
        return camera

    @classmethod
    def from_toml(cls, path: str | Path) -> Camera:
        """Read a camera file."""
        return cls.from_dict(read_toml(path), source=str(path))

    def to_toml(self, path: str | Path) -> None:
        """Write a camera file (atomically); calibrated centres are included."""
        write_toml(path, self.to_dict())

    # ---- presets ----------------------------------------------------------------
    @classmethod
    def paper_16mp(cls) -> Camera:
        """The paper's experiment: Imperx B4820 (4904 x 3280, 7.4 µm), 289 x 193 lenses."""
        return cls(50.0, 2.42, 0.66, 0.125, 0.5, (289, 193), 0.0074, (4904, 3280))

    @classmethod
    def synthetic_850(cls) -> Camera:
        """The paper's synthetic camera: 850 x 850 px behind 50 x 50 lenses, M = 1, f/2."""
        return cls(50.0, 2.0, 1.0, 0.125, 0.5, (50, 50), 0.0074, (850, 850))


PRESETS = {"paper": Camera.paper_16mp, "synthetic": Camera.synthetic_850}

#: The sections of a camera file and the keys each may hold (docs/design.md §2).
CAMERA_KEYS = {
    "main_lens": ("focal_length_mm", "f_number", "magnification", "pupil_magnification",
                  "principal_plane_separation_mm"),
    "microlens_array": ("pitch_mm", "focal_length_mm", "count", "rotation_deg", "offset_mm",
                        "layout", "odd_row_shift"),
    "sensor": ("pixel_pitch_mm", "pixels", "crop_origin", "full_pixels"),
    "calibration": ("centers_col", "centers_row"),
    "pose": POSE_KEYS,
}


def _check_keys(doc: dict, source: str) -> None:
    """Refuse unknown sections and keys by name, as the experiment file does: a misspelt
    optional key (``rotaton_deg``) would otherwise be ignored and the geometry wrong."""
    refuse_unknown(doc, CAMERA_KEYS, lambda bad: f"{source}: unknown section(s) {bad}; a "
                   f"camera file has {list(CAMERA_KEYS)} (docs/design.md §2)")
    for section, keys in CAMERA_KEYS.items():
        given = doc.get(section, {})
        if not isinstance(given, dict):
            raise ValueError(f"{source}: [{section}] must be a section of keys")
        refuse_unknown(given, keys, lambda bad, section=section, keys=keys:
                       f"{source}: unknown key(s) {bad} in [{section}]; it takes "
                       f"{list(keys)} (docs/design.md §2)")
    mla = doc.get("microlens_array", {})
    try:  # the axial view is the projector's, never a file's
        lens_layout(mla.get("layout", "rectangular"), (1, 1), view=False)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def load_camera(spec: str | Path | None) -> Camera:
    """A camera from a TOML file, or a preset name (``synthetic``, ``paper``; default
    ``synthetic``)."""
    if spec is None or spec in PRESETS:
        return PRESETS[spec or "synthetic"]()
    if not Path(spec).is_file():
        raise FileNotFoundError(f"no camera file {spec!s} and no preset of that name; give a "
                                f"camera TOML file or one of the presets {sorted(PRESETS)}")
    return Camera.from_toml(spec)

