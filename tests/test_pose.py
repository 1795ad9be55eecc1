"""A camera's pose (``plenocl.camera.pose``, docs/design.md §2.2, issue 49): the
convention X_camera = R X_world + t with R = Rz Ry Rx, its camera-file section, the
stages that take world points through it, and the stages that refuse it for now."""

from __future__ import annotations

import numpy as np
import pytest

from plenocl import Grid, simulate_image
from plenocl.camera import Camera, Pose, pose_rotation
from plenocl.projection import Projector


def _small(pose: Pose | None = None) -> Camera:
    return Camera(50.0, 2.0, 1.0, 0.125, 0.5, (12, 10), 0.0074, (206, 172), pose=pose)


def test_rotations_are_right_handed_about_the_world_axes_x_first():
    x, y, z = np.eye(3)
    np.testing.assert_allclose(pose_rotation((90, 0, 0)) @ y, z, atol=1e-15)
    np.testing.assert_allclose(pose_rotation((0, 90, 0)) @ z, x, atol=1e-15)
    np.testing.assert_allclose(pose_rotation((0, 0, 90)) @ x, y, atol=1e-15)
    angles = (12.0, -31.0, 47.0)
    composed = (pose_rotation((0, 0, angles[2])) @ pose_rotation((0, angles[1], 0))
                @ pose_rotation((angles[0], 0, 0)))
    r = pose_rotation(angles)
    np.testing.assert_allclose(r, composed, atol=1e-15)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_a_pose_maps_world_points_into_the_camera_and_back():
    pose = Pose((10.0, -25.0, 5.0), (1.5, -2.0, 30.0))
    pts = np.random.default_rng(1).normal(0, 10, (50, 3))
    cam = pose.to_camera(pts)
    np.testing.assert_allclose(cam, pts @ pose.matrix.T + pose.translation_mm)
    np.testing.assert_allclose(pose.to_world(cam), pts, atol=1e-12)
    # distances are kept: a rigid motion
    np.testing.assert_allclose(np.linalg.norm(cam[1:] - cam[:-1], axis=1),
                               np.linalg.norm(pts[1:] - pts[:-1], axis=1))


def test_the_camera_file_round_trips_its_pose_and_leaves_an_unposed_camera_as_it_was(
        tmp_path):
    pose = Pose((0.0, 25.0, 0.0), (-55.0, 0.0, 12.0))
    path = tmp_path / "posed.toml"
    _small(pose).to_toml(path)
    back = Camera.from_toml(path)
    assert back.pose == pose and "[pose]" in path.read_text()
    assert "posed: rotation [0.0, 25.0, 0.0]" in back.describe()
    plain = _small()
    assert plain.pose is None and "pose" not in plain.to_dict()
    assert Camera.from_dict(plain.to_dict()).pose is None
    assert plain.to_dict() == Camera.from_dict(plain.to_dict()).to_dict()
    # the other constructors keep the pose
    assert _small(pose).with_layout("hexagonal").pose == pose
    assert _small(pose).on_lens_lattice().pose == pose


@pytest.mark.parametrize("section,message", [
    ({"rotation_deg": [0, 10, 0]}, "lacks translation_mm"),
    ({"rotation_deg": [0, 10], "translation_mm": [0, 0, 0]}, "three finite numbers"),
    ({"rotation_deg": [0, 10, "x"], "translation_mm": [0, 0, 0]}, "three numbers"),
    ({"rotation_deg": [0, float("nan"), 0], "translation_mm": [0, 0, 0]}, "finite"),
    ({"rotation_deg": [0, 0, 0], "translation_mm": [0, 0, 0], "scale": 2}, "unknown key"),
])
def test_a_bad_pose_section_is_refused_by_name(section, message):
    doc = _small().to_dict()
    doc["pose"] = section
    with pytest.raises(ValueError, match=message):
        Camera.from_dict(doc)


def test_a_pose_must_be_a_pose():
    with pytest.raises(TypeError, match="Pose"):
        _small(pose={"rotation_deg": [0, 0, 0]})


def test_image_points_take_world_points_through_the_pose():
    pose = Pose((3.0, -4.0, 20.0), (0.4, -0.3, 1.0))
    pts = np.array([[0.2, -0.1, 0.5], [-0.3, 0.25, -1.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(_small(pose).image_points(pts),
                               _small().image_points(pose.to_camera(pts)))


def test_a_posed_camera_images_world_particles_where_it_sees_them(queue):
    """The same rays, the same seed: the posed camera's image of world particles is the
    unposed camera's image of those particles in its frame, to the count."""
    pose = Pose((2.0, -3.0, 15.0), (0.1, -0.2, 0.8))
    local = np.array([[0.1, -0.2, 0.3], [-0.25, 0.15, -0.6], [0.0, 0.05, 1.2]])
    world = pose.to_world(local)
    kw = dict(rays_per_particle=300, seed=4, queue=queue)
    posed = simulate_image(_small(pose), world, 1e4, **kw)
    plain = simulate_image(_small(), local, 1e4, **kw)
    assert posed.sum() > 0
    np.testing.assert_allclose(posed, plain, atol=1e-3 * plain.max())
    with pytest.raises(ValueError, match="behind its main lens's front focal plane"):
        simulate_image(_small(pose), pose.to_world([[0.0, 0.0, -60.0]]), 1e4, **kw)


def test_a_pose_that_puts_the_particles_behind_the_camera_is_named_with_the_fix():
    """A camera turned half round about x looks away from the world's particles: the
    error names the pose, how many points, the depth they reach in the camera's frame
    and what to check; the same points through the unposed camera are imaged."""
    turned = Pose((180.0, 0.0, 0.0), (0.0, 0.0, -60.0))
    world = np.array([[0.1, 0.0, 1.0], [0.0, -0.2, -0.5], [0.2, 0.1, 0.0]])
    with pytest.raises(ValueError, match=r"\(rotation_deg \[180.0, 0.0, 0.0\], translation_mm "
                                         r"\[0.0, 0.0, -60.0\]\) puts 3 of 3 points .*"
                                         r"turned 180 degrees looks away") as err:
        _small(turned).image_points(world)
    assert "-61.000 mm or less" in str(err.value)
    assert np.all(np.isfinite(_small().image_points(world)))


def test_a_projector_takes_a_posed_camera_and_grid_for_camera_its_own_frame_only(queue):
    """A world grid is projected through the pose (tests/test_posed_projector.py);
    ``Grid.for_camera`` fits a grid in the camera's own frame, so a posed camera is
    refused there with the way to get one."""
    cam = _small(Pose((0.0, 20.0, 0.0), (0.0, 0.0, 0.0)))
    grid = Grid.for_camera(_small(), z=(-1.0, 1.0))
    assert Projector(cam, grid, queue).path == "posed"
    with pytest.raises(ValueError, match=r"Grid.for_camera works in the camera's own frame.*"
                                         r"camera.with_pose\(None\)"):
        Grid.for_camera(cam, z=(-1.0, 1.0))


def test_lines_of_sight_turn_with_the_pose():
    from plenocl.optics.sightline import line_of_sight

    pose = Pose((5.0, 30.0, -10.0), (2.0, -1.0, 4.0))
    world = np.array([[1.0, 2.0, 0.5], [-3.0, 0.5, -2.0]])
    posed = line_of_sight(_small(pose), world)
    np.testing.assert_allclose(posed @ pose.matrix.T,
                               line_of_sight(_small(), pose.to_camera(world)), atol=1e-15)
    # the line runs through the main lens's front principal point, placed in the world
    principal = pose.to_world([[0.0, 0.0, -_small().object_distance_mm]])[0]
    towards = world - principal
    np.testing.assert_allclose(posed, towards / np.linalg.norm(towards, axis=1)[:, None],
                               atol=1e-12)


def test_the_turn_and_shift_between_two_poses():
    a = Pose((0.0, 10.0, 0.0), (1.0, 2.0, 3.0))
    b = Pose((0.0, 12.5, 0.0), (1.0, 2.0, 3.5))
    assert a.turn_deg(b) == pytest.approx(2.5, abs=1e-9)
    assert b.turn_deg(a) == pytest.approx(2.5, abs=1e-9) and a.turn_deg(a) < 1e-6
    assert a.shift_mm(b) == pytest.approx(0.5)
    # about another axis too: the rotation's angle, whatever its axis
    assert Pose((3.0, 4.0, 0.0), (0, 0, 0)).turn_deg(Pose((0.0, 0.0, 0.0), (0, 0, 0))) == \
        pytest.approx(np.degrees(np.arccos((np.trace(pose_rotation((3.0, 4.0, 0.0))) - 1) / 2)))
