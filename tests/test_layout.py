"""The lens layout object (``Camera.layout``, plenocl/camera/lattice.py): what every stage
asks about the array's layout, checked against the camera's own geometry."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from plenocl.camera import AxialView, Camera, HexagonalLayout, RectangularLayout, lens_layout
from plenocl.camera.lattice import axial_basis, view_lean

LAYOUTS = [("rectangular", None), ("hexagonal", 0.5), ("hexagonal", -0.5)]


def camera(name: str, shift: float | None, rotation: float = 0.0) -> Camera:
    """The paper's optics on 13 x 11 lenses (a hexagonal array: the rows its height holds)."""
    base = Camera(50.0, 2.42, 0.66, 0.125, 0.5, (13, 11), 0.0074, (240, 210),
                  ml_rotation_deg=rotation)
    return base.with_layout(name, shift)


@pytest.mark.parametrize("name,shift", LAYOUTS)
def test_axial_indices_round_trip_and_place_every_lens(name, shift):
    cam = camera(name, shift)
    layout = cam.layout
    cols, rows = layout.count
    ky, kx = np.mgrid[0:rows, 0:cols]
    k = np.stack([kx, ky], -1)
    qr = layout.to_axial(k)
    np.testing.assert_array_equal(layout.from_axial(qr), k)
    # in axial indices the array is affine: q e1 + r e2, in pitches along the row
    basis = axial_basis(layout.odd_row_shift, 1.0)
    np.testing.assert_allclose(qr @ basis, layout.lattice_coords(), atol=1e-12)
    # and the lattice coordinates are the lenses' positions on the array plane
    pos = cam.microlens_positions_mm()
    steps = (pos - pos[0, 0]) / [cam.ml_pitch_mm, cam.ml_row_pitch_mm]
    np.testing.assert_allclose(steps, layout.lattice_coords() - layout.lattice_coords()[0, 0],
                               atol=1e-9)


@pytest.mark.parametrize("name,shift", LAYOUTS)
def test_neighbours_and_row_spacing_follow_the_lens_positions(name, shift):
    cam = camera(name, shift)
    pos = cam.microlens_positions_mm().reshape(-1, 2)
    inner = cam.microlens_positions_mm()[5, 6]
    dist = np.hypot(*(pos - inner).T) / cam.ml_pitch_mm
    assert np.sum(np.abs(dist - 1) < 1e-9) == cam.layout.neighbours
    rows = cam.microlens_positions_mm()[:, 0, 1]
    np.testing.assert_allclose(np.diff(rows), cam.ml_pitch_mm * cam.layout.row_ratio)
    assert cam.layout.staggered == (name == "hexagonal")
    assert cam.layout.hexagonal == (name == "hexagonal")


@pytest.mark.parametrize("name,shift", LAYOUTS)
@pytest.mark.parametrize("rotation", [0.0, 0.4, -1.3])
def test_rotation_from_the_mean_steps_is_the_arrays(name, shift, rotation):
    cam = camera(name, shift, rotation)
    c = cam.ideal_microlens_centers()
    row_step = np.mean(np.diff(c, axis=1), axis=(0, 1))
    col_step = np.mean(np.diff(c, axis=0), axis=(0, 1))
    assert cam.layout.rotation_deg(row_step, col_step) == pytest.approx(rotation, abs=1e-9)


@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_the_axial_view_numbers_the_same_lenses(shift):
    cam = camera("hexagonal", shift).with_centers(
        camera("hexagonal", shift).ideal_microlens_centers()
        + np.random.default_rng(1).normal(0, 0.3, (12, 13, 2)))
    view = cam.on_lens_lattice()
    assert isinstance(view.layout, AxialView) and view.layout.is_view
    assert view.on_lens_lattice() is view
    assert view.layout.array_count == cam.layout.count
    cols, rows = cam.layout.count
    ky, kx = np.mgrid[0:rows, 0:cols]
    at = view.layout.from_axial(cam.layout.to_axial(np.stack([kx, ky], -1)))
    np.testing.assert_array_equal(view.microlens_centers[at[..., 1], at[..., 0]],
                                  cam.microlens_centers)
    # every other place of the view's parallelogram holds no lens
    assert np.isnan(view.microlens_centers).all(-1).sum() == view.ml_count[0] * rows - cols * rows
    # the view's first column is its index q - lean r = q_min (it steps by (+1/2, √3/2)
    # from row to row whatever the numbering's shift: one rhombus for one array)
    q = cam.layout.to_axial(np.stack([kx, ky], -1))[..., 0] - view_lean(shift) * ky
    assert view.layout.q_min == q.min()
    assert np.isfinite(view.microlens_centers[:, 0]).all(-1).any()


def test_the_view_is_not_a_camera_file_and_not_an_array():
    cam = camera("hexagonal", 0.5)
    with pytest.raises(ValueError, match="axial view"):
        cam.on_lens_lattice().to_dict()
    with pytest.raises(ValueError, match="the light field"):
        cam.on_lens_lattice().layout.require_array("the light field takes the array")
    cam.layout.require_array("never raised for the array itself")
    assert cam.layout.file_keys() == {"layout": "hexagonal", "odd_row_shift": 0.5}
    assert camera("rectangular", None).layout.file_keys() == {}


def test_with_layout_fills_the_same_sensor():
    rect = camera("rectangular", None)
    hexa = rect.with_layout("hexagonal")
    assert isinstance(rect.layout, RectangularLayout)
    assert isinstance(hexa.layout, HexagonalLayout) and hexa.odd_row_shift == 0.5
    assert hexa.ml_count == (13, math.floor(11 * 2 / math.sqrt(3)))
    assert hexa.pixels == rect.pixels and not hexa.calibrated
    # as many rows as the array's height holds, no more
    height = rect.ml_count[1] * rect.ml_pitch_mm
    assert hexa.ml_count[1] * hexa.ml_row_pitch_mm <= height
    assert (hexa.ml_count[1] + 1) * hexa.ml_row_pitch_mm > height
    back = hexa.with_layout("rectangular")  # the rows the hexagonal array's height holds
    assert back.ml_count == (13, math.floor(hexa.ml_count[1] * math.sqrt(3) / 2))
    assert rect.with_layout("rectangular").ml_count == rect.ml_count


def test_lens_layout_refuses_what_no_array_has():
    with pytest.raises(ValueError, match="layout must be one of"):
        lens_layout("hex", (3, 3))
    with pytest.raises(ValueError, match="layout must be one of"):
        lens_layout("axial", (3, 3), view=False)
    with pytest.raises(ValueError, match="odd_row_shift must be one of"):
        lens_layout("rectangular", (3, 3), 0.5)
    with pytest.raises(ValueError, match="odd_row_shift must be one of"):
        lens_layout("hexagonal", (3, 3), 0.25)
    assert lens_layout("axial", (5, 3), 0.5).array_count == (4, 3)


def test_no_stage_reads_the_layouts_name():
    """Stages ask ``Camera.layout``; only the camera package compares ``ml_layout``."""
    root = Path(__file__).resolve().parents[1] / "plenocl"
    readers = []
    for path in root.rglob("*.py"):
        if path.parent.name == "camera":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                names = [n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute)]
                if "ml_layout" in names:
                    readers.append(f"{path.relative_to(root)}:{node.lineno}")
    assert not readers, f"compare Camera.layout, not the layout's name: {readers}"
