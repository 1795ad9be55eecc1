"""A thick main lens (issue 29; docs/design.md §2): a camera described by its pupil
magnification and principal-plane separation against an independent ray tracer of a real
two-element objective.

The objective (``plenocl.bench.objective``): two ideal thin lenses (60 and 120 mm, 40 mm
apart) with the aperture stop between them (30 mm behind the first); its cardinal points
and pupils from ray-transfer matrices, its rays traced element by element through a
uniformly sampled point of the physical stop: nothing of plenocl's pupil model makes its
images.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenocl import Camera, LightField, Projector, simulate_image
from plenocl.bench.objective import (
    GRID,
    MAGNIFICATION,
    OBJECTIVE,
    WORKING_F_NUMBER,
    array_position,
    thick_camera,
    thin_camera,
    trace_objective,
)
from plenocl.calibration import calibrate
from plenocl.metrics import match_particles
from plenocl.optics.raybundle import RayBundle
from plenocl.peaks import find_particles
from plenocl.reconstruction import reconstruct
from plenocl.simulate import simulate_white_image


def test_the_pupil_model_places_the_objectives_exit_pupil_and_focal_plane():
    """From the two numbers a lens's data gives (m_p, HH'), the camera puts the exit
    pupil, its size and the focal plane where the real objective has them."""
    cam, o = thick_camera(), OBJECTIVE
    assert cam.focal_length_mm == pytest.approx(51.428571, rel=1e-6)
    assert cam.pupil_magnification == pytest.approx(6 / 11)
    assert cam.exit_pupil_distance_mm == pytest.approx(array_position(cam) - o.exit_pupil,
                                                       rel=1e-12)
    stop = cam.aperture_diameter_mm / o.entrance_magnification
    assert cam.exit_pupil_diameter_mm == pytest.approx(stop * o.exit_magnification, rel=1e-12)
    front = o.front_principal - cam.object_distance_mm
    assert cam.focal_plane_distance_mm == pytest.approx(array_position(cam) - front, rel=1e-12)
    assert cam.working_f_number == pytest.approx(WORKING_F_NUMBER)
    assert thin_camera().exit_pupil_distance_mm == thin_camera().image_distance_mm


def test_a_thick_lens_camera_file_round_trips_and_refuses_bad_values(tmp_path):
    cam = thick_camera()
    cam.to_toml(tmp_path / "thick.toml")
    back = Camera.from_toml(tmp_path / "thick.toml")
    assert back.pupil_magnification == cam.pupil_magnification
    assert back.principal_plane_separation_mm == cam.principal_plane_separation_mm
    assert "pupil_magnification" not in thin_camera().to_dict()["main_lens"]
    with pytest.raises(ValueError, match="pupil_magnification must be a positive"):
        dataclasses.replace(cam, pupil_magnification=0.0)
    with pytest.raises(ValueError, match="principal_plane_separation_mm must be a finite"):
        dataclasses.replace(cam, principal_plane_separation_mm=float("nan"))


def test_the_simulator_traces_the_objectives_rays(queue):
    """plenocl's simulator of the thick camera and the element-by-element tracer make the
    same raw image, within the rays' own scatter (two seeds of the simulator); the thin
    lens of the same cone does not."""
    rng, rays = np.random.default_rng(5), 400_000
    pos = np.column_stack([rng.uniform(-1.2, 1.2, (8, 2)), np.linspace(-1.8, 1.8, 8)])
    traced = rays * trace_objective(thick_camera(), pos, rays, 1, 0.7)

    def simulated(cam, seed):
        return simulate_image(cam, pos, np.full(8, float(rays)), rays, seed=seed, blur_px=0.7,
                              queue=queue)

    def l1(a, b):  # the share of the light in a different place
        return np.abs(a - b).sum() / a.sum()

    model = simulated(thick_camera(), 2)
    scatter = l1(model, simulated(thick_camera(), 3))  # 0.037
    assert l1(model, traced) < 1.1 * scatter  # 0.036
    assert l1(simulated(thin_camera(), 2), traced) > 1.3 * scatter  # 0.056


@pytest.mark.parametrize("z", [-1.6, 1.2])
def test_the_image_fits_ray_bundle_draws_the_objectives_image(z):
    """The image fit's forward model (deterministic rays over the exit pupil) draws the
    particle the objective images, to the tracer's Monte-Carlo noise."""
    cam, pos = thick_camera(), np.array([[0.31, -0.22, z]])
    ref = trace_objective(cam, pos, 200_000, 6, 0.8).ravel()
    bundle = RayBundle.of(cam, rays=3000, blur_px=0.8)
    points = cam.image_points(pos)
    patches = bundle.patches(points)
    elements, rows = bundle.render(points, np.ones(1), patches)
    _, pixel = patches.pixels(cam.pixels[0], elements)
    image = np.zeros(ref.size)
    np.add.at(image, pixel, rows[0])
    assert image.sum() == pytest.approx(ref.sum(), rel=2e-3)
    assert np.linalg.norm(image - ref) / np.linalg.norm(ref) < 0.08


def test_a_thick_lens_camera_calibrates_to_its_exit_pupils_centres(queue):
    """The microlens images centre on the exit pupil's projection, ``x_k (1 + f_ml/d)``:
    a white image stopped down to f/16 calibrates to those centres, 0.2-0.4 px from
    where the thin lens of the same cone puts them at the array's edge."""
    cam = thick_camera()
    white = simulate_white_image(cam, stop_f_number=16.0, photon_noise=True, seed=3,
                                 queue=queue)
    centres = calibrate(white, cam).microlens_centers
    err = np.linalg.norm(centres - cam.ideal_microlens_centers(), axis=-1)
    assert np.sqrt(np.nanmean(err**2)) < 0.03 and np.isfinite(err).mean() > 0.97
    thin = np.linalg.norm(thin_camera().ideal_microlens_centers()
                          - cam.ideal_microlens_centers(), axis=-1)
    assert thin.max() > 0.2


@pytest.mark.parametrize("z", [-1.5, 1.5])
def test_the_objectives_light_field_refocuses_where_the_pupils_put_it(queue, z):
    """Refocusing the objective's raw image (the aperture coordinates on the exit pupil,
    ``α = d'/d``) brings a particle into focus at its own depth, at ``X'/α`` on the
    array plane."""
    cam = thick_camera().with_centers(thick_camera().ideal_microlens_centers())
    point = np.array([0.2, -0.15, z])
    lf = LightField(1e5 * trace_objective(cam, point[None], 40_000, 4, 0.5), cam, queue=queue)
    depths = np.arange(-2.5, 2.51, 0.5)
    stack = lf.focal_stack(depths, supersample=2)
    assert depths[stack.reshape(len(depths), -1).max(1).argmax()] == z
    img = lf.refocus(z_mm=z, supersample=2)
    w = np.clip(img - 0.2 * img.max(), 0, None)
    found = (w[..., None] * lf.output_positions_mm(supersample=2)).sum((0, 1)) / w.sum()
    expected = cam.image_points(point[None])[0, :2] / cam.alpha(z)
    assert found == pytest.approx(expected, abs=0.35 * cam.ml_pitch_mm)


def _matched(image, camera, queue, positions) -> dict[int, np.ndarray]:
    """Each recovered particle's error (voxels, ``x, y, z``) by its index in
    ``positions``."""
    found, _ = find_particles(reconstruct(image, Projector(camera, GRID, queue)), 0.1)
    true_idx = GRID.to_index(positions)
    return {t: found[f] - true_idx[t] for t, f in match_particles(found, true_idx, 1.5, 4.0)}


def _rms(errors: dict[int, np.ndarray], on: set[int]) -> tuple[float, float]:
    """RMS lateral and depth error (voxels) over the particles ``on``."""
    d = np.array([errors[t] for t in sorted(on)])
    return float(np.sqrt(np.mean(d[:, :2] ** 2))), float(np.sqrt(np.mean(d[:, 2] ** 2)))


def test_a_thick_lens_reconstructs_particles_as_well_as_a_thin_one(queue):
    """Particles traced through the objective reconstruct on the thick camera within the
    thin lens's own error (its simulator's image on its own camera), compared on the
    particles both recover; the objective's nominal f-number on a thin lens (the pupils
    ignored), calibrated centres and all, misplaces them in depth."""
    rng = np.random.default_rng(11)
    pos = np.column_stack([rng.uniform(-1.2, 1.2, (12, 2)), rng.uniform(-1.7, 1.7, 12)])
    traced = rng.poisson(2e4 * trace_objective(thick_camera(), pos, 20_000, 3, 1.0))
    thin_image = simulate_image(thin_camera(), pos, np.full(12, 2e4), 20_000, seed=3,
                                blur_px=1.0, photon_noise=True, queue=queue)
    thick = _matched(traced, thick_camera(), queue, pos)  # 12 of 12
    thin = _matched(thin_image, thin_camera(), queue, pos)  # 11 of 12
    cam = thick_camera()
    with pytest.warns(UserWarning, match="overlap"):
        nominal = Camera(cam.focal_length_mm, cam.f_number, MAGNIFICATION, 0.125, 0.5,
                         (30, 30), 0.0074, (510, 510)
                         ).with_centers(cam.ideal_microlens_centers())
    pupils_ignored = _matched(traced, nominal, queue, pos)
    both = thick.keys() & thin.keys()
    (thick_lat, thick_depth), (thin_lat, thin_depth) = _rms(thick, both), _rms(thin, both)
    print(f"on {len(both)} particles: thick {thick_lat:.3f} / {thick_depth:.3f}, thin "
          f"{thin_lat:.3f} / {thin_depth:.3f}")
    assert len(thick) >= len(thin) - 1 and len(both) >= 10
    assert thick_lat <= thin_lat + 0.03 and thick_depth <= 1.1 * thin_depth
    ignored = sorted(both & pupils_ignored.keys())  # the nominal f-number scales depth:
    z = pos[ignored, 2]                              # its error grows with the depth
    slopes = [np.polyfit(z, [errors[t][2] for t in ignored], 1)[0]
              for errors in (thick, pupils_ignored)]
    print(f"depth error per mm of depth: thick {slopes[0]:.2f}, pupils ignored {slopes[1]:.2f}")
    assert abs(slopes[1]) > 0.2 and abs(slopes[1]) > 2 * abs(slopes[0])
