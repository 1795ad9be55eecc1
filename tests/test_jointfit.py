"""Particles fitted to several cameras' raw images at once (``plenocl.piv.jointfit``,
docs/design.md §6.7, issue 49): two cameras 25 degrees apart fix a particle's depth
where one camera's fit leaves it to its prior; a particle outside a camera's reach is
dropped, the others kept."""

from __future__ import annotations

import numpy as np

from plenocl import simulate_image
from plenocl.bench.accuracy_section import paper_optics
from plenocl.camera import Pose
from plenocl.piv.imagefit import ImageFit, ImageFitSettings
from plenocl.piv.jointfit import JointImageFit

CAM, GRID = paper_optics((32, 24))
VOXEL = np.array([GRID.spacing[2], GRID.spacing[1], GRID.spacing[0]])  # (x, y, z) mm
CAMERAS = [CAM.with_pose(Pose((0.0, t, 0.0), (0.0, 0.0, 0.0))) for t in (-12.5, 12.5)]


def _images(true: np.ndarray, seed: int) -> list[list[np.ndarray]]:
    return [[simulate_image(cam, true, 2e4, 4000, seed=seed + k, blur_px=0.8,
                            photon_noise=True, background=20.0, read_noise=3.0)]
            for k, cam in enumerate(CAMERAS)]


def test_two_cameras_fit_particles_closer_than_one():
    """Out of focus, started 0.3 voxel off laterally and 1.5 in depth: the two cameras'
    joint fit comes back within a quarter voxel in every axis, nearer in depth than one
    camera's own fit, with a smaller depth sigma."""
    rng = np.random.default_rng(2)
    true = np.column_stack([rng.uniform(-1.2, 1.2, 6), rng.uniform(-0.9, 0.9, 6),
                            [-8.0, -6.0, -4.0, 4.0, 6.0, 8.0]])
    start = true + np.array([0.3, -0.3, 1.5]) * VOXEL
    images = _images(true, 5)
    settings = ImageFitSettings(rays=400)
    joint = JointImageFit(CAMERAS, GRID, images, settings).fit(0, start)
    alone = ImageFit(CAMERAS[0], GRID, images[0], settings).fit(0, start)
    err = np.abs(joint.positions - true) / VOXEL
    assert joint.kept.all() and err.max() < 0.25, err
    alone_z = np.abs(alone.positions[:, 2] - true[:, 2]) / VOXEL[2]
    assert np.sqrt(np.mean(err[:, 2] ** 2)) < np.sqrt(np.mean(alone_z ** 2)), (err, alone_z)
    assert np.all(joint.sigma[:, 2] < alone.sigma[:, 2])
    np.testing.assert_allclose(joint.intensities, 2e4, rtol=0.15)


def test_a_particle_beyond_the_grid_is_dropped_and_the_rest_fitted():
    true = np.array([[0.2, 0.1, 5.0], [-0.4, 0.2, -6.0]])
    start = np.vstack([true + 0.2 * VOXEL, [[0.0, 0.0, GRID.z[1] + 10.0]]])
    fit = JointImageFit(CAMERAS, GRID, _images(true, 9), ImageFitSettings(rays=400))
    out = fit.fit(0, start)
    assert out.kept.tolist() == [True, True, False] and out.dropped == 1
    assert np.isnan(out.positions[2]).all()
    assert (np.abs(out.positions[:2] - true) / VOXEL).max() < 0.3
