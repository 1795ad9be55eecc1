"""A two-element objective traced element by element (issue 29, docs/design.md §2): the
independent truth a thick-lens camera is checked against (``tests/test_thick_lens.py``,
``benchmarks/thick_lens.py``).

The objective: two ideal thin lenses (60 and 120 mm, 40 mm apart) with the aperture stop
between them (30 mm behind the first). Its cardinal points and pupils come from
ray-transfer matrices, and rays are traced element by element through a uniformly
sampled point of the physical stop: nothing of plenocl's pupil model makes its images.
:func:`thick_camera` is the camera a user writes for it (focal length, f-number, pupil
magnification, principal-plane separation), :func:`thin_camera` a thin lens of the same
image-side cone.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..camera import Camera
from ..grid import Grid

F1, F2, GAP, STOP_AT = 60.0, 120.0, 40.0, 30.0  # mm: lenses, their gap, stop behind lens 1
MAGNIFICATION = 1.0
WORKING_F_NUMBER = 4.0  # = f_ml / p_ml of the array below
#: The volume the objective's particles are reconstructed on.
GRID = Grid((32, 24, 24), x=(-1.5, 1.5), y=(-1.5, 1.5), z=(-2.0, 2.0))


@dataclasses.dataclass(frozen=True)
class Objective:
    """The two-element objective's paraxial data, from its ray-transfer matrix (lens 1 at
    axial position 0, positions grow towards the sensor)."""

    focal_length: float
    front_principal: float
    rear_principal: float
    entrance_magnification: float  # entrance pupil diameter / stop diameter
    exit_magnification: float  # exit pupil diameter / stop diameter
    exit_pupil: float  # axial position of the exit pupil

    @classmethod
    def of(cls) -> Objective:
        def lens(f):
            return np.array([[1.0, 0.0], [-1.0 / f, 1.0]])

        a, _, c, d = (lens(F2) @ np.array([[1.0, GAP], [0.0, 1.0]]) @ lens(F1)).ravel()
        behind = GAP - STOP_AT  # the stop seen through lens 2 (Gaussian imaging)
        image = behind * F2 / (behind - F2)
        return cls(-1.0 / c, (d - 1.0) / c, GAP + (1.0 - a) / c,
                   abs(F1 / (F1 - STOP_AT)), abs(image / behind), GAP + image)

    @property
    def pupil_magnification(self) -> float:
        """Exit over entrance pupil diameter."""
        return self.exit_magnification / self.entrance_magnification


OBJECTIVE = Objective.of()


def thick_camera() -> Camera:
    """The camera as a user describes it: the objective's focal length, f-number (its
    entrance pupil), pupil magnification and principal-plane separation."""
    o = OBJECTIVE
    f_number = WORKING_F_NUMBER / (1 + MAGNIFICATION / o.pupil_magnification)
    return Camera(o.focal_length, f_number, MAGNIFICATION, 0.125, 0.5, (30, 30), 0.0074,
                  (510, 510), pupil_magnification=o.pupil_magnification,
                  principal_plane_separation_mm=o.rear_principal - o.front_principal)


def thin_camera() -> Camera:
    """A thin lens of the same focal length, magnification and image-side cone."""
    cam = thick_camera()
    return Camera(cam.focal_length_mm, WORKING_F_NUMBER / (1 + MAGNIFICATION), MAGNIFICATION,
                  0.125, 0.5, (30, 30), 0.0074, (510, 510))


def array_position(cam: Camera) -> float:
    """Axial position of the microlens array: ``s_i`` behind the rear principal plane."""
    return OBJECTIVE.rear_principal + cam.image_distance_mm


def trace_objective(cam: Camera, positions, rays: int, seed: int, blur_px: float
                    ) -> np.ndarray:
    """Raw image of point particles (object mm, +z away from the camera) traced through
    the two lenses, the stop, the (square, 100 % fill) microlens each ray enters and onto
    the sensor; one count per particle in all."""
    o, rng = OBJECTIVE, np.random.default_rng(seed)
    stop_radius = cam.aperture_diameter_mm / o.entrance_magnification / 2
    image = np.zeros((cam.pixels[1], cam.pixels[0]))
    for x0, y0, z in np.asarray(positions, float):
        distance = cam.object_distance_mm - o.front_principal + z  # object to lens 1
        r, th = stop_radius * np.sqrt(rng.random(rays)), 2 * np.pi * rng.random(rays)
        at_mla, slope = zip(*(_through_lenses(h0, hs, distance, array_position(cam))
                              for h0, hs in ((x0, r * np.cos(th)), (y0, r * np.sin(th)))))
        _deposit(cam, image, np.stack(at_mla, -1), np.stack(slope, -1), rng, blur_px, rays)
    return image


def _through_lenses(h0: float, h_stop: np.ndarray, distance: float, mla: float):
    """One transverse axis: the ray from height ``h0``, ``distance`` before lens 1, that
    crosses the stop at ``h_stop``; its height on the array and slope behind lens 2."""
    h1 = (h_stop + STOP_AT * h0 / distance) / (1 + STOP_AT / distance - STOP_AT / F1)
    slope = (h1 - h0) / distance - h1 / F1
    h2 = h1 + GAP * slope
    slope = slope - h2 / F2
    return h2 + (mla - GAP) * slope, slope


def _deposit(cam: Camera, image, at_mla, slope, rng, blur_px: float, rays: int) -> None:
    """The rays through the (square, 100 % fill) ideal microlens each enters, onto the
    sensor's pixels with a Gaussian blur."""
    cols, rows = cam.ml_count
    k = np.floor(at_mla / cam.ml_pitch_mm + np.array([cols, rows]) / 2).astype(int)
    ok = ((k >= 0) & (k < [cols, rows])).all(axis=1)
    lens = (k[ok] - (np.array([cols, rows]) - 1) / 2) * cam.ml_pitch_mm
    sensor = lens + cam.ml_focal_length_mm * slope[ok]  # an ideal microlens at `lens`
    px = cam.mm_to_px(sensor) + rng.normal(0.0, blur_px, sensor.shape)
    c, r = np.rint(px).astype(int).T
    inside = (c >= 0) & (c < cam.pixels[0]) & (r >= 0) & (r < cam.pixels[1])
    np.add.at(image, (r[inside], c[inside]), 1.0 / rays)
