"""Lens weights that integrate the voxel's extent (``Projector(lens_weights="extent")``,
issue 47): against the NumPy twin, adjoint, conserving, the paper's weights for a voxel
at least a lens wide, and narrower footprints for a voxel narrower than a lens."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import tolerances as tol
from helpers import assert_adjoint, assert_close_to_peak

from plenocl import Grid, simulate_image
from plenocl.projection import Projector
from plenocl.projection.model import WeightingModel
from plenocl.reconstruction import ReconstructionSettings, reconstruct
from plenocl.reference.weights import voxel_weights

#: Voxels 0.40-0.47 of a lens wide (in lens indices) at the three depths.
FINE = Grid((3, 21, 27), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-4.0, 4.0))
#: Voxels 1.2-1.4 lenses wide.
COARSE = Grid((5, 7, 9), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-5.0, 5.0))
FINE_VOXELS = [(1, 10, 13), (0, 3, 20), (2, 17, 5), (1, 0, 26), (0, 20, 0)]


def _dense(idx, w, n):
    out = np.zeros(n)
    out[idx] = w
    return out


def _widths(camera, grid) -> np.ndarray:
    """Each depth's voxel width in lens indices, ``(nz, 2)``: the row sums of ``|G|``."""
    coef = WeightingModel(camera, grid, warn=False).coef
    return np.abs(coef[:, 0:4]).reshape(-1, 2, 2).sum(axis=2)


@pytest.fixture(scope="module")
def fine(small_camera, queue):
    return {w: Projector(small_camera, FINE, queue, lens_weights=w)
            for w in ("paper", "extent")}


def test_the_grids_are_what_the_tests_need(small_camera):
    assert (_widths(small_camera, FINE) < 0.5).all()
    assert (_widths(small_camera, COARSE) > 1.0).all()


def test_extent_weights_match_the_reference(small_camera, fine):
    n = small_camera.pixels[0] * small_camera.pixels[1]
    for vox in FINE_VOXELS:
        ref = _dense(*voxel_weights(small_camera, FINE, *vox, lens_weights="extent"), n)
        kern = _dense(*fine["extent"].voxel_weights(*vox), n)
        onehot = np.zeros(FINE.shape, np.float32)
        onehot[vox] = 1.0
        for got in (kern, fine["extent"].forward(onehot).ravel()):
            assert_close_to_peak(got, ref, tol.WEIGHTS, vox)
            np.testing.assert_allclose(got.sum(), ref.sum(), rtol=tol.FOOTPRINT_TOTAL)


def test_extent_weights_are_adjoint(fine):
    assert_adjoint(fine["extent"])


def test_a_sub_lens_voxel_keeps_its_light_on_fewer_pixels(small_camera, fine):
    """The two lenses' shares still sum to one, so a voxel whose light all reaches the
    array keeps a total of one; its light sits on fewer pixels, never on one the paper's
    weights leave dark."""
    lit = {"paper": 0, "extent": 0}
    for vox in FINE_VOXELS:
        (pi, pw), (ei, ew) = (fine[w].voxel_weights(*vox) for w in ("paper", "extent"))
        if pw.sum() > 1 - tol.CONSERVATION:  # a voxel whose light all reaches the array
            np.testing.assert_allclose(ew.sum(), 1.0, rtol=tol.CONSERVATION)
        assert np.isin(ei, pi).all()  # never a pixel the paper's weights leave dark
        assert ew.max() >= pw.max() * (1 - tol.CONSERVATION)
        lit["paper"] += len(pi)
        lit["extent"] += len(ei)
    assert lit["extent"] < 0.9 * lit["paper"]


@pytest.mark.parametrize("method", ["factorised", "direct"])
def test_a_voxel_wider_than_a_lens_keeps_the_papers_weights(small_camera, queue, method):
    paper = Projector(small_camera, COARSE, queue, method=method)
    extent = Projector(small_camera, COARSE, queue, method=method, lens_weights="extent")
    vol = np.random.default_rng(2).random(COARSE.shape).astype(np.float32)
    img = np.random.default_rng(3).random(paper.image_shape).astype(np.float32)
    if method == "factorised":  # the same arithmetic, bit for bit
        np.testing.assert_array_equal(extent.forward(vol), paper.forward(vol))
        np.testing.assert_array_equal(extent.back(img), paper.back(img))
    else:  # the direct forward scatters with atomics, in no fixed order
        np.testing.assert_allclose(extent.forward(vol), paper.forward(vol),
                                   rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)
        np.testing.assert_allclose(extent.back(img), paper.back(img),
                                   rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)


def test_every_path_gives_the_same_extent_weights(small_camera, queue, fine):
    """The direct kernels and the GPU-style layout against the separable default."""
    rng = np.random.default_rng(4)
    vol = rng.random(FINE.shape).astype(np.float32)
    img = rng.random(fine["extent"].image_shape).astype(np.float32)
    for other in (Projector(small_camera, FINE, queue, method="direct", lens_weights="extent"),
                  Projector(small_camera, FINE, queue, vector_width=1, segment=1,
                            lens_weights="extent")):
        np.testing.assert_allclose(other.forward(vol), fine["extent"].forward(vol),
                                   rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)
        np.testing.assert_allclose(other.back(img), fine["extent"].back(img),
                                   rtol=tol.RECOMPUTED, atol=tol.RECOMPUTED_FLOOR)


def test_refined_and_sampled_projectors_keep_the_lens_weights(fine):
    assert fine["extent"].refined(2).lens_weights == "extent"
    assert fine["extent"].sampled(2.0).lens_weights == "extent"


def test_unknown_lens_weights_are_refused(small_camera, queue):
    with pytest.raises(ValueError, match="lens_weights must be one of"):
        Projector(small_camera, FINE, queue, lens_weights="box")


def test_the_settings_and_the_projector_name_the_same_lens_weights():
    from plenocl.projection.projector import LENS_WEIGHTS
    from plenocl.reconstruction.settings import LENS_WEIGHTS as NAMED

    assert NAMED == LENS_WEIGHTS
    with pytest.raises(ValueError, match="lens_weights must be one of"):
        ReconstructionSettings(lens_weights="box")


def test_the_default_is_the_extent_weights_and_settings_name_it(small_camera, queue):
    """A projector left to its default has the extent weights; a pair's settings left to
    the projector's name them (what a stored record digests), and keep a named choice."""
    from plenocl.pipeline import PairSettings
    from plenocl.projection.projector import DEFAULT_LENS_WEIGHTS

    assert Projector(small_camera, FINE, queue).lens_weights == DEFAULT_LENS_WEIGHTS == "extent"
    assert PairSettings().reconstruction.lens_weights is None
    assert PairSettings().with_named_weights().reconstruction.lens_weights == "extent"
    paper = PairSettings(reconstruction=ReconstructionSettings(lens_weights="paper"))
    assert paper.with_named_weights() is paper


def test_weighted_projectors_are_built_once(fine):
    paper = fine["paper"]
    assert paper.weighted("paper") is paper
    assert paper.weighted("extent") is paper.weighted("extent")
    assert paper.weighted("extent").lens_weights == "extent"


def test_the_settings_choose_the_lens_weights(small_camera, queue, fine):
    """``reconstruct(..., lens_weights="extent")`` on the paper's projector is the
    reconstruction on the extent projector, and differs from the paper's."""
    rng = np.random.default_rng(5)
    pos = np.column_stack([rng.uniform(-0.5, 0.5, 6), rng.uniform(-0.4, 0.4, 6),
                           rng.uniform(-3.0, 3.0, 6)])
    image = simulate_image(small_camera, pos, 1e4, 2000, seed=5, queue=queue)
    settings = ReconstructionSettings(supersample=1, iterations=5)
    named = reconstruct(image, fine["paper"], settings=replace(settings, lens_weights="extent"))
    built = reconstruct(image, fine["extent"], settings=settings)
    paper = reconstruct(image, fine["paper"], settings=settings)
    np.testing.assert_array_equal(named, built)
    assert np.abs(named - paper).max() > 1e-3 * paper.max()
