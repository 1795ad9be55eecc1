"""Stress tests (issue 8, item 3): property-based checks with hypothesis, explicit extremes,
float32-vs-float64 error, determinism, and a table of invalid inputs across the public API
(documented in ``docs/errors.md``).

Sized for CI on two CPU cores with PoCL: cameras of 3-8 lenses per side behind 8-30 px
each, grids of at most 6 x 7 x 7 voxels, a handful of examples per property.
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings

import numpy as np
import pyopencl.array as cla
import pytest
import tolerances as tol
from helpers import ROTATED, lens_camera
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from plenocl import (
    Camera,
    Grid,
    LightField,
    PIVResult,
    Projector,
    calibrate,
    flows,
    random_particles,
    reconstruct,
    save_field,
    simulate_image,
    simulate_white_image,
)
from plenocl.calibration import import_centers
from plenocl.camera import Pose
from plenocl.io import read_field, read_image, read_particles
from plenocl.optics.depthrange import resolved_depth_range
from plenocl.pipeline import TrackSettings, track
from plenocl.pipeline.frames import load_frame
from plenocl.piv import PIVSettings, piv3d
from plenocl.piv.imagefit import ImageFit, ImageFitSettings
from plenocl.plot import PlotOptions, plot_file
from plenocl.reconstruction import (
    FLOAT32_LIMIT,
    METHODS,
    SMOOTH_DEFAULTS,
    UnusableImageError,
    preprocess,
    view_blocks,
)
from plenocl.reference.weights import ApertureGrid, voxel_weights, weight_matrix
from plenocl.simulate import lens_displacements_mm
from plenocl.volumefile import load_volume


def _settings(n: int) -> settings:
    """Few examples, no deadline (OpenCL builds), no example database in the checkout."""
    return settings(max_examples=n, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow,
                                           HealthCheck.function_scoped_fixture])


#: The fixed tiny case: 4 x 4 lenses of ~17 px (M = 1, f/2, matched), a 3 x 4 x 4 grid.
TINY = dict(focal_length_mm=50.0, f_number=2.0, magnification=1.0, ml_pitch_mm=0.125,
            ml_focal_length_mm=0.5, ml_count=(4, 4), pixel_pitch_mm=0.0074, pixels=(70, 70))
TINY_GRID = Grid((3, 4, 4), x=(-0.2, 0.2), y=(-0.2, 0.2), z=(-1.0, 1.0))


@pytest.fixture(scope="module")
def tiny(queue):
    """Camera, projector and a consistent test image of the fixed tiny case."""
    cam = Camera(**TINY)
    proj = Projector(cam, TINY_GRID, queue)
    vol = np.random.default_rng(0).random(TINY_GRID.shape).astype(np.float32)
    return cam, proj, proj.forward(vol)


# ---- 1. random cameras and grids: projector properties ------------------------------------
@st.composite
def camera_and_grid(draw, layouts=("ideal", "ideal", "rotated", "perturbed")):
    """A valid camera whose f-number matches its microlenses (fill 82-100 %: no warning),
    and a grid centred on the axis whose central voxel's light stays on the array.

    Layouts: ideal centres (separable kernels), a rotated array, or calibrated centres off
    the ideal grid by up to ±0.3 px with one lens missing (NaN; general kernels).
    The central voxel ``(nz//2, ny//2, nx//2)`` sits on the axis at a depth whose blur
    circle on the array has radius ``b`` lenses, ``b <= (min(count) - 1)/2 - 0.5``: every
    aperture sample then falls between two lenses that exist, and the sensor has at least
    2 px of margin around the array, so none of its light is lost (weights sum to 1). The
    grid's faces lie within the depths the camera resolves (a projector refuses others).
    """
    f = draw(st.floats(20.0, 100.0))
    mag = draw(st.floats(0.3, 2.0))
    p_ml = draw(st.floats(0.08, 0.2))
    f_ml = draw(st.floats(0.3, 1.5))
    fill = draw(st.floats(0.82, 1.0))
    ppl = draw(st.floats(8.0, 30.0))
    cols, rows = draw(st.integers(3, 8)), draw(st.integers(3, 8))
    margin = draw(st.tuples(st.integers(4, 7), st.integers(4, 7)))
    layout = draw(st.sampled_from(list(layouts)))
    rotation = 0.0
    if layout == "rotated":
        rotation = draw(st.sampled_from([-1.0, 1.0])) * draw(st.floats(0.3, 1.5))
    s_i = f * (1 + mag)
    aperture = fill * p_ml * (s_i + f_ml) / f_ml  # microlens image fill = fill
    image_pitch = p_ml * (1 + f_ml / s_i)
    p_px = image_pitch / ppl
    pixels = tuple(math.ceil(n * ppl) + m for n, m in zip((cols, rows), margin))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a fill or validation slip in this strategy fails here
        cam = Camera(f, f / aperture, mag, p_ml, f_ml, (cols, rows), p_px, pixels,
                     ml_rotation_deg=rotation)
    seed = draw(st.integers(0, 2**32 - 1))
    if layout == "perturbed":
        rng = np.random.default_rng(seed)
        centres = cam.microlens_centers + rng.uniform(-0.3, 0.3, cam.microlens_centers.shape)
        centres[rng.integers(rows), rng.integers(cols)] = np.nan
        cam = cam.with_centers(centres)
    # central voxel depth from its blur radius b (lenses) on the array: D/2 |1 - 1/α| = b p_ml
    b = draw(st.floats(0.0, (min(cols, rows) - 1) / 2 - 0.5))
    sign = draw(st.sampled_from([-1.0, 1.0]))
    alpha = 1.0 / (1.0 - sign * 2 * b * p_ml / cam.aperture_diameter_mm)
    s_ip = alpha * cam.image_distance_mm
    z_c = f * s_ip / (s_ip - f) - cam.object_distance_mm
    nz = draw(st.integers(3, 6))
    ny, nx = draw(st.sampled_from([3, 5, 7])), draw(st.sampled_from([3, 5, 7]))
    limit = f - cam.object_distance_mm  # z <= limit forms no real image
    dz = draw(st.floats(0.1, 3.0)) * cam.depth_resolution_mm
    dz = min(dz, 0.5 * (z_c - limit) / (nz // 2 + 0.5))  # keep the near face well beyond
    near, far = resolved_depth_range(cam)  # and both faces within the depths it resolves
    dz = min(dz, 0.99 * (z_c - near) / (nz // 2 + 0.5), 0.99 * (far - z_c) / (nz - nz // 2 - 0.5))
    z0 = z_c - (nz // 2 + 0.5) * dz
    half = [draw(st.floats(0.05, 1.2)) * n * p_ml / (2 * mag) for n in (cols, rows)]
    grid = Grid((nz, ny, nx), x=(-half[0], half[0]), y=(-half[1], half[1]), z=(z0, z0 + nz * dz))
    return cam, grid, layout, seed


@_settings(30)
@given(case=camera_and_grid(layouts=("rotated",)))
def test_resampled_projector_properties_on_random_cameras(case, queue):
    """Random grids across rotated arrays' lens rows, projected through the lens-row
    frame: non-negative, adjoint, and each voxel's weights sum to at most 1 and equal
    Aᵀ 1 there (the resampling conserves light)."""
    cam, grid, _, seed = case
    proj = Projector(cam, grid, queue)
    assert proj.path == "resampled"
    rng = np.random.default_rng(seed)
    vol = (rng.random(grid.shape) * (rng.random(grid.shape) < 0.7)).astype(np.float32)
    img = rng.random(proj.image_shape).astype(np.float32)
    fwd, bck = proj.forward(vol), proj.back(img)
    assert fwd.min() >= 0 and bck.min() >= 0
    lhs = float(np.dot(fwd.ravel().astype(np.float64), img.ravel()))
    rhs = float(np.dot(vol.ravel().astype(np.float64), bck.ravel()))
    assert abs(lhs - rhs) <= tol.ADJOINT * lhs, (lhs, rhs)
    centre = (grid.shape[0] // 2, grid.shape[1] // 2, grid.shape[2] // 2)
    idx, wts = proj.footprint_entries(np.array([centre, (0, 0, 0)]))
    sums = np.where(idx >= 0, wts, 0).astype(np.float64).sum(axis=1)
    acc = proj.frame.n_samples * 2.0**-24
    assert sums.max() <= 1 + acc + tol.CONSERVATION
    sens = proj.back(np.ones(proj.image_shape, np.float32)).astype(np.float64)
    np.testing.assert_allclose(sens[tuple(np.array([centre, (0, 0, 0)]).T)], sums,
                               rtol=0, atol=acc + 1e-6)


def _scratch_for_chunks(proj: Projector, factor: float) -> int:
    """A scratch size that forces several aperture-column and depth chunks."""
    lo, hi = proj.aperture.column_ranges()
    cols, rows = proj.camera.ml_count
    need = max(int((hi - lo + 1).max()) * 4 * rows * proj.nkxp, 4 * proj.shape[1] * proj.nkxp)
    return int(need * factor)


@_settings(60)
@given(case=camera_and_grid(), chunk_factor=st.floats(1.0, 3.0))
def test_projector_properties_on_random_cameras(case, chunk_factor, queue):
    cam, grid, layout, seed = case
    # every aperture column holds a sample (the factorised kernels rely on it)
    assert ApertureGrid.for_camera(cam).inside()[0].any()
    proj = Projector(cam, grid, queue, general="exact")
    if layout != "perturbed":  # perturbed centres may fit an axis-aligned layout by chance
        assert proj.path == ("separable" if layout == "ideal" else "general")
    rng = np.random.default_rng(seed)
    vol = (rng.random(grid.shape) * (rng.random(grid.shape) < 0.7)).astype(np.float32)
    img = rng.random(proj.image_shape).astype(np.float32)

    fwd, bck = proj.forward(vol), proj.back(img)
    assert fwd.shape == proj.image_shape and bck.shape == grid.shape
    for name, out in (("forward", fwd), ("back", bck)):
        assert out.dtype == np.float32, name
        assert np.isfinite(out).all(), f"{name} produced NaN/Inf"
        assert out.min() >= 0, f"{name} of non-negative input went negative: {out.min()}"

    # adjointness <A x, y> = <x, Aᵀ y>; both sides are sums of non-negative terms
    lhs = float(np.dot(fwd.ravel().astype(np.float64), img.ravel()))
    rhs = float(np.dot(vol.ravel().astype(np.float64), bck.ravel()))
    assert lhs > 0, "the grid is centred on the axis: its light must reach the sensor"
    assert abs(lhs - rhs) <= tol.ADJOINT * lhs, f"<Ax,y>={lhs!r} <x,Aᵀy>={rhs!r}"

    # every voxel's weights sum to at most 1 (footprint kernel, summed in float64) ...
    centre = (grid.shape[0] // 2, grid.shape[1] // 2, grid.shape[2] // 2)
    flat = rng.choice(grid.size, size=min(grid.size, 12), replace=False)
    voxels = np.array([centre, *np.array(np.unravel_index(flat, grid.shape)).T])
    idx, wts = proj.footprint_entries(voxels)
    sums = np.where(idx >= 0, wts, 0).astype(np.float64).sum(axis=1)
    assert sums.max() <= 1 + tol.CONSERVATION and sums.min() >= 0, (sums.min(), sums.max())
    # ... and Aᵀ 1 gives the same sums, within float32 accumulation over the aperture
    # samples: the general back kernel adds them one by one into a float per voxel, so
    # its error grows as n_samples * 2^-24 (measured up to 1.2e-5 with ~900 samples)
    acc = proj.n_samples * 2.0**-24
    sens = proj.back(np.ones(proj.image_shape, np.float32)).astype(np.float64)
    assert sens.max() <= 1 + acc and sens.min() >= 0, (sens.min(), sens.max(), acc)
    np.testing.assert_allclose(sens[tuple(voxels.T)], sums, rtol=0, atol=acc)

    # the central voxel: same sum as the float64 reference; 1 with the ideal layout
    _, ref = voxel_weights(cam, grid, *centre)
    _, kern = proj.voxel_weights(*centre)
    assert float(kern.astype(np.float64).sum()) == pytest.approx(ref.sum(), abs=tol.CONSERVATION)
    if layout == "ideal":
        assert ref.sum() == pytest.approx(1.0, abs=1e-9), "strategy: footprint not inside"
        assert float(kern.astype(np.float64).sum()) == pytest.approx(1.0, abs=tol.CONSERVATION)

    # the same operator when the work is split into small chunks, and by the direct kernels
    # (other summation orders: equal within the float32 accumulation bound above)
    tol_f = dict(rtol=tol.RECOMPUTED, atol=max(acc, 1e-5) * float(fwd.max()))
    tol_b = dict(rtol=tol.RECOMPUTED, atol=max(acc, 1e-5) * float(bck.max()))
    chunked = Projector(cam, grid, queue, general="exact",
                        scratch_bytes=_scratch_for_chunks(proj, chunk_factor))
    assert len(chunked.plan.columns) > 1 or chunked.plan.zchunk < grid.shape[0]
    np.testing.assert_allclose(chunked.forward(vol), fwd, **tol_f)
    np.testing.assert_allclose(chunked.back(img), bck, **tol_b)
    direct = Projector(cam, grid, queue, method="direct")
    np.testing.assert_allclose(direct.forward(vol), fwd, **tol_f)
    np.testing.assert_allclose(direct.back(img), bck, **tol_b)

    # active-slice skipping is exact: skipped slices count as zero (forward) / come out 0
    active = rng.random(grid.shape[0]) < 0.5
    masked = np.where(active[:, None, None], vol, np.float32(0))
    np.testing.assert_allclose(
        proj.forward_device(proj.volume_to_device(masked), active=active).get(),
        proj.forward(masked), rtol=tol.ROUNDING, atol=1e-7 * float(fwd.max()))
    part = proj.volume_to_host(proj.back_device(cla.to_device(queue, img), active=active))
    assert not part[~active].any()
    np.testing.assert_allclose(part[active], bck[active], rtol=tol.ROUNDING)

    # dark-microlens skipping is exact, bit for bit: the forward projection at the lit
    # pixels, and the back projection of an image that is dark elsewhere
    sparse = np.where(rng.random(img.shape) < 0.01, img, np.float32(0))
    lenses = proj.lens_set(proj.lit_lenses(sparse))
    lit = sparse > 0
    on_lit = proj.forward_device(proj.volume_to_device(vol), lenses=lenses).get()
    np.testing.assert_array_equal(on_lit[lit], fwd[lit])
    np.testing.assert_array_equal(
        proj.volume_to_host(proj.back_device(cla.to_device(queue, sparse), lenses=lenses)),
        proj.back(sparse))


@_settings(30)
@given(case=camera_and_grid(), count=st.integers(0, 20), rays=st.integers(1, 3000),
       blur=st.sampled_from([0.0, 0.5, 2.0]), exponent=st.floats(-3, 9))
def test_simulated_images_are_finite_and_conserve_light(case, count, rays, blur, exponent,
                                                        queue):
    """Noise-free images of random particles inside a random grid: finite, non-negative,
    and never more light than the particles send through the aperture (rays that miss
    the array or the sensor are lost)."""
    cam, grid, layout, seed = case
    rng = np.random.default_rng(seed)
    lo = np.array([grid.x[0], grid.y[0], grid.z[0]])
    hi = np.array([grid.x[1], grid.y[1], grid.z[1]])
    pos = lo + (hi - lo) * rng.random((count, 3))
    inten = 10.0**exponent * rng.random(count)
    img = simulate_image(cam, pos, inten, rays, seed=seed, blur_px=blur, queue=queue)
    assert img.shape == (cam.pixels[1], cam.pixels[0]) and img.dtype == np.float32
    assert np.isfinite(img).all() and img.min() >= 0
    total = float(inten.sum())
    assert float(img.astype(np.float64).sum()) <= total * (1 + tol.CONSERVATION) + 1e-30, \
        (img.sum(), total)
    if layout != "rotated" and blur == 0:
        # a particle at the central voxel: its blur circle lies on the array (see the
        # strategy), every ray lands, and the image carries all of its intensity
        centre = [[0.0, 0.0, float(grid.axis_centers("z")[grid.shape[0] // 2])]]
        one = simulate_image(cam, centre, 10.0**exponent, rays, seed=seed, queue=queue)
        assert float(one.astype(np.float64).sum()) == pytest.approx(10.0**exponent,
                                                                    rel=tol.CONSERVATION)


def test_projector_with_empty_outer_aperture_column(queue):
    """A textbook matched design: 16 px per microlens (p_ml = 16 p_px) and working
    f-number s_i/D = f_ml/p_ml, so r/step = 1.25 * 16 / 2 = 10 up to rounding."""
    f, mag, f_ml, p_px = 35.0, 0.5, 0.5, 0.0045
    p_ml = 16 * p_px
    cam = Camera(f, f * f_ml / (f * (1 + mag) * p_ml), mag, p_ml, f_ml, (4, 4), p_px, (72, 72))
    grid = Grid((3, 3, 3), x=(-0.15, 0.15), y=(-0.15, 0.15), z=(-1.0, 1.0))
    aperture = ApertureGrid.for_camera(cam)
    lo, hi = aperture.column_ranges()
    a = weight_matrix(cam, grid)
    proj = Projector(cam, grid, queue)
    vol = np.ones(grid.shape, np.float32)
    sens = proj.back(np.ones(proj.image_shape, np.float32))
    err = np.abs(proj.forward(vol).ravel() - a @ vol.ravel()).max() / (a @ vol.ravel()).max()
    measured = (f"column ranges cover {int((hi - lo + 1).sum())} samples of "
                f"{len(aperture.samples()[0])}; max Aᵀ1 = {sens.max():.6g}; forward error "
                f"{err:.3g} of the peak")
    assert int((hi - lo + 1).sum()) == len(aperture.samples()[0]), measured
    assert sens.max() <= 1 + tol.CONSERVATION and err <= tol.WEIGHTS, measured


# ---- 2. reconstruct never returns NaN, Inf or negative voxels -------------------------------
KINDS = ("zeros", "single", "uniform", "sparse", "decades", "constant")
DTYPES = ("uint8", "uint16", "float16", "float32", "float64")


def _make_image(shape, kind: str, dtype: str, exponent: float, seed: int) -> np.ndarray:
    """A non-negative test image of ``kind`` in ``dtype``.

    Floats are scaled to ``10**exponent`` (float16 within its normal range), integers to
    their full scale; ``decades`` spreads pixel values over 30 orders of magnitude.
    """
    rng = np.random.default_rng(seed)
    base = np.zeros(shape)
    if kind == "single":
        base[rng.integers(shape[0]), rng.integers(shape[1])] = 1.0
    elif kind == "uniform":
        base = rng.random(shape)
    elif kind == "sparse":
        base = rng.random(shape) * (rng.random(shape) < 0.03)
    elif kind == "decades":
        base = 10.0 ** rng.uniform(-30, 0, shape) * (rng.random(shape) < 0.5)
    elif kind == "constant":
        base[:] = 1.0
    if dtype in ("uint8", "uint16"):
        return np.rint(base * np.iinfo(dtype).max).astype(dtype)
    if dtype == "float16":
        return (base * 10.0 ** np.clip(exponent, -4, 4)).astype(np.float16)
    return (base * 10.0**exponent).astype(dtype)


def _sum_bound(image, sens) -> float:
    """Upper bound on ``Σ_j s_j E_j`` for MLEM and SMART (``s_j = Σ_i w_ij``).

    MLEM: ``Σ_j s_j E_j' = Σ_i I_i P_i' / P_i <= Σ_i I_i`` after every update with μ = 1;
    with μ < 1, ``x^μ <= 1 + μ (x - 1)`` keeps it below ``max(Σ_j s_j E_j, Σ_i I_i)``.
    SMART's update is a weighted geometric mean of the same ratios, which is at most
    their arithmetic mean. The uniform start carries ``Σ_i I_i``; MLOS starts at a
    geometric mean of pixel values, at most ``max I``, so at most ``max I · Σ_j s_j``.
    Masking and the sensitivity floor only zero voxels. Slack 1e-3 for float32 sums.
    """
    img = np.asarray(image, np.float64)
    return 1.001 * max(img.sum(), img.max() * float(sens.sum()))


@pytest.fixture(scope="module")
def tiny_perturbed(tiny, queue):
    """The tiny case with calibrated centres (±0.3 px, one lens missing): general kernels."""
    cam = tiny[0]
    rng = np.random.default_rng(8)
    centres = cam.microlens_centers + rng.uniform(-0.3, 0.3, cam.microlens_centers.shape)
    centres[1, 2] = np.nan
    return Projector(cam.with_centers(centres), TINY_GRID, queue)


@_settings(60)
@given(kind=st.sampled_from(KINDS), dtype=st.sampled_from(DTYPES),
       exponent=st.floats(-30, 30), seed=st.integers(0, 2**32 - 1),
       start=st.sampled_from(["uniform", "mlos"]),
       mask_fraction=st.sampled_from([None, 0.0, 0.5]), relax=st.floats(0.05, 1.0),
       iterations=st.integers(0, 4), threshold=st.sampled_from([0.0, 0.1, 0.5]),
       mart_blocks=st.integers(1, 3), skip_empty=st.booleans(), perturbed=st.booleans())
@example(kind="constant", dtype="float32", exponent=30.0, seed=0, start="uniform",
         mask_fraction=None, relax=1.0, iterations=1, threshold=0.0, mart_blocks=1,
         skip_empty=False, perturbed=False)  # float32(1e30) = 1.0000000150e30: accepted
def test_reconstruct_is_finite_and_non_negative(tiny, tiny_perturbed, kind, dtype, exponent,
                                                seed, start, mask_fraction, relax, iterations,
                                                threshold, mart_blocks, skip_empty, perturbed):
    """Zero, single-pixel, flat, sparse and 30-decade images in uint8/uint16/float16/32/64,
    every method and option mix: the volume is finite, non-negative and (MLEM, SMART)
    carries no more light than :func:`_sum_bound` allows; an image that cannot give a
    volume (one value, saturated, no pixel above the threshold) is refused, and only such a
    one; a ``mask_fraction`` that zeroes every voxel of the first guess is said."""
    proj = tiny_perturbed if perturbed else tiny[1]
    image = _make_image(proj.image_shape, kind, dtype, exponent, seed)
    peak = float(np.asarray(image, np.float64).max())
    sens = proj.back(np.ones(proj.image_shape, np.float32)).astype(np.float64)
    for method in METHODS:  # each with its own smoothing (SMOOTH_DEFAULTS)
        _, scale, thr = preprocess(image, proj.camera, "median", threshold * peak,
                                   smooth_px=SMOOTH_DEFAULTS[method])
        unusable = np.mean(image == image.max()) > 0.5 or scale == 0 or thr >= 1  # one
        # value, saturated (SATURATED_FRACTION), no light above the background or threshold
        try:
            vol = reconstruct(image, proj, method, iterations, relax, start=start,
                              threshold=threshold * peak, mask_fraction=mask_fraction,
                              skip_empty=skip_empty, mart_blocks=mart_blocks, supersample=1)
        except UnusableImageError:
            assert unusable, f"{method}: a usable image refused"
            continue
        except ValueError as exc:  # a mask_fraction that left no voxel: said, not zeros
            assert mask_fraction is not None and "zeroed every voxel" in str(exc), exc
            continue
        assert not unusable, f"{method}: an image without light reconstructed"
        assert vol.shape == proj.shape and vol.dtype == np.float32
        assert np.isfinite(vol).all(), f"{method}: NaN/Inf voxels"
        assert vol.min() >= 0, f"{method}: negative voxel {vol.min()}"
        if method != "mart":
            total = float((sens * vol).sum())
            assert total <= _sum_bound(image, sens), (method, total)


@pytest.mark.parametrize("method, mart_blocks", [("mlem", 2), ("smart", 2), ("mart", 1)])
def test_thousand_iterations_stay_bounded(queue, method, mart_blocks):
    """1000 iterations on an inconsistent image (noise plus a few pixels 10^4 brighter).

    Bound: ``max E <= Σ_j s_j E_j / min_sensitivity <= 1.001 Σ_i I_i / min_sensitivity``
    (every voxel left non-zero has ``s_j > min_sensitivity``; the sum is bounded as in
    :func:`_sum_bound`). It is proved for MLEM and SMART; for MART's block updates the
    same bound is an observed property, asserted all the same. Measured max E / bound:
    0.18 (MLEM), 5e-4 (SMART, MART). MART runs with one block to keep CI time short.
    """
    cam = lens_camera(3, 3, pixels=(31, 31), pixel_pitch_mm=0.0125)
    proj = Projector(cam, Grid((2, 3, 3), x=(-0.15, 0.15), y=(-0.15, 0.15), z=(-1.0, 1.0)),
                     queue)
    rng = np.random.default_rng(5)
    image = rng.random(proj.image_shape)
    image[rng.integers(31, size=3), rng.integers(31, size=3)] = 1e4
    # the inconsistent image as it is (no background removed: it is not a camera frame)
    vol, info = reconstruct(image, proj, method, 1000, 1.0 if method != "mart" else 0.7,
                            mart_blocks=mart_blocks, background=None, return_info=True,
                            supersample=1)
    assert info.iterations == 1000
    assert np.isfinite(vol).all() and vol.min() >= 0 and vol.max() > 0
    assert np.isfinite(info.residuals).all()
    bound = 1.001 * image.sum() / 0.5
    assert vol.max() <= bound, f"{method}: max {vol.max():.6g} > bound {bound:.6g}"
    sens = proj.back(np.ones(proj.image_shape, np.float32)).astype(np.float64)
    assert (sens * vol).sum() <= 1.001 * image.sum()


@pytest.mark.parametrize("peak", [3e38, 1e39])
def test_reconstruct_finite_for_huge_images(tiny, peak):
    """Finite input must give a finite volume, or a clear rejection of the range."""
    _, proj, img = tiny
    image = img.astype(np.float64) / img.max() * peak
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            vol = reconstruct(image, proj, iterations=2, supersample=1)
        except ValueError as exc:  # a fix may reject such images instead
            assert "range" in str(exc) or "float32" in str(exc), str(exc)
            return
    assert np.isfinite(vol).all(), f"{np.isinf(vol).sum()} Inf voxels of {vol.size}"


# ---- 3. float32 accumulation against float64 --------------------------------------------
F32_BOUND = 1e-5  # ~170 float32 ulps (2^-24) relative to the peak


@pytest.fixture(scope="module", params=["separable", "general"])
def dense_case(request, small_camera, queue):
    """The conftest camera (12 x 10 lenses of ~17 px, 349 aperture samples) and a 100-voxel
    grid, with the dense float64 reference matrix: ideal centres (separable kernels) or
    the array rotated by 2 degrees (general kernels)."""
    cam = small_camera
    if request.param == "general":
        cam = lens_camera(**ROTATED)
    grid = Grid((4, 5, 5), x=(-0.3, 0.3), y=(-0.25, 0.25), z=(-3.0, 3.0))
    proj = Projector(cam, grid, queue, general="exact")
    assert proj.path == request.param
    return proj, weight_matrix(cam, grid)


@pytest.mark.parametrize("kind", ["uniform", "sparse", "decades"])
def test_float32_forward_and_back_match_float64(dense_case, kind, record_property):
    """Relative error (max abs error over the peak) of the float32 device projections
    against ``A x`` and ``Aᵀ y`` in float64. Measured 2e-7 to 9e-7; bound 1e-5 (~170 float32
    ulps). It grows with the aperture samples (general back: up to ~1.2e-5 at ~900)."""
    proj, a = dense_case
    rng = np.random.default_rng(11)
    shape = proj.shape
    vol = {"uniform": rng.random(shape), "sparse": rng.random(shape) * (rng.random(shape) < 0.2),
           "decades": 10.0 ** rng.uniform(-3, 3, shape)}[kind].astype(np.float32)
    ref = a @ vol.ravel().astype(np.float64)
    got = proj.forward(vol).ravel().astype(np.float64)
    err_fwd = np.abs(got - ref).max() / np.abs(ref).max()
    img = rng.random(proj.image_shape).astype(np.float32)
    ref_b = a.T @ img.ravel().astype(np.float64)
    err_back = np.abs(proj.back(img).ravel() - ref_b).max() / np.abs(ref_b).max()
    record_property("float32_forward_rel_err", float(err_fwd))
    record_property("float32_back_rel_err", float(err_back))
    print(f"float32 vs float64 ({proj.path}, {kind}): forward {err_fwd:.3g}, back {err_back:.3g}")
    assert err_fwd <= F32_BOUND, f"forward relative error {err_fwd:.3g} > {F32_BOUND}"
    assert err_back <= F32_BOUND, f"back relative error {err_back:.3g} > {F32_BOUND}"


# ---- 4. determinism ---------------------------------------------------------------------
def _same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_determinism(tiny, queue):
    cam, proj, img = tiny
    rng = np.random.default_rng(3)
    vol = rng.random(proj.shape).astype(np.float32)
    again = Projector(cam, TINY_GRID, queue)  # fresh buffers, same device
    assert _same_bits(proj.forward(vol), proj.forward(vol))
    assert _same_bits(proj.forward(vol), again.forward(vol))
    assert _same_bits(proj.back(img), proj.back(img))
    assert _same_bits(proj.back(img), again.back(img))
    kw = dict(start="mlos", mask_fraction=0.5, supersample=1, background=None)  # a projection
    for method in METHODS:
        one = reconstruct(img, proj, method, 5, **kw)
        assert one.any() and _same_bits(one, reconstruct(img, proj, method, 5, **kw)), method
        assert _same_bits(one, reconstruct(img, again, method, 5, **kw)), method
    pos = rng.uniform(-0.2, 0.2, (5, 3))
    sims = [simulate_image(cam, pos, 1000.0, 3000, seed=9, blur_px=0.5, photon_noise=True,
                           bit_depth=12, queue=queue) for _ in range(2)]
    assert _same_bits(*sims) and sims[0].any()
    whites = [simulate_white_image(cam, rays_per_lens=500, seed=4, queue=queue)
              for _ in range(2)]
    assert _same_bits(*whites) and whites[0].any()


# ---- 5. invalid inputs across the public API ----------------------------------------------
@pytest.fixture(scope="module")
def ctx(tiny, queue, tmp_path_factory):
    """Everything the invalid-input cases need: the tiny camera/projector/image, volumes
    for PIV, and bad files."""
    cam, proj, img = tiny
    d = tmp_path_factory.mktemp("bad_inputs")
    (d / "two_columns.csv").write_text("x_mm,y_mm\n1,2\n3,4\n")
    (d / "no_header.csv").write_text("0.1,0.2,0.3\n0.4,0.5,0.6\n")
    (d / "pixels.csv").write_text("x_px,y_px,z_px\n10,20,3\n")
    (d / "empty.tif").write_bytes(b"")
    (d / "cut.npz").write_bytes(b"PK\x03\x04 cut short")
    (d / "grid_typo.toml").write_text("[grid]\nshape = [3, 4, 4]\nx_mm = [-0.2, 0.2]\n"
                                      "y_mm = [-0.2, 0.2]\nz_mm = [-1, 1]\nrotaton_deg = 5\n")
    (d / "five_columns.csv").write_text("a,b,c,d,e\n1,2,3,4,5\n")
    (d / "header_only.csv").write_text("x_mm,y_mm,z_mm\n")
    (d / "text.csv").write_text("x_mm,y_mm,z_mm\na,b,c\n")
    np.save(d / "colour.npy", np.dstack([np.zeros((5, 5)), np.ones((5, 5)), np.zeros((5, 5))]))
    np.save(d / "stack.npy", np.zeros((5, 5, 5)))
    np.save(d / "line.npy", np.zeros(5))
    (d / "camera_missing_key.toml").write_text("[main_lens]\nfocal_length_mm = 50.0\n")
    (d / "camera_bad.toml").write_text("[main_lens\nfocal_length_mm = 50.0\n")
    (d / "centres_from_one.csv").write_text("lens_col,lens_row,x_px,y_px\n4,4,60.0,60.0\n")
    (d / "centres_off_region.csv").write_text("lens_col,lens_row,x_px,y_px\n0,0,60.0,5.0\n")
    vol = np.random.default_rng(2).random((16, 16, 16)).astype(np.float32)
    return {"cam": cam, "proj": proj, "img": img, "dir": d, "vol": vol, "queue": queue}


def _cam(**kw):
    return lambda c: Camera(**{**TINY, **kw})


def _grid(**kw):
    args = {"shape": (3, 4, 4), "x": (-1, 1), "y": (-1, 1), "z": (-1, 1), **kw}
    return lambda c: Grid(**args)


def _sim(positions=((0.0, 0.0, 0.0),), intensities=1000.0, **kw):
    return lambda c: simulate_image(c["cam"], np.asarray(positions, float), intensities,
                                    **{"rays_per_particle": 100, **kw}, queue=c["queue"])


def _white(**kw):
    return lambda c: simulate_white_image(c["cam"], **{"rays_per_lens": 100, **kw},
                                          queue=c["queue"])


def _proj(z=(-1.0, 1.0), x=(-0.2, 0.2), **kw):
    return lambda c: Projector(c["cam"], Grid((3, 4, 4), x, (-0.2, 0.2), z), c["queue"], **kw)


def _rec(image=None, **kw):
    def call(c):
        img = c["img"] if image is None else image(c["img"])
        return reconstruct(img, c["proj"], **{"iterations": 1, **kw})
    return call


def _piv(a=lambda v: v, b=lambda v: v, **kw):
    return lambda c: piv3d(a(c["vol"]), b(c["vol"]), **kw)


def _foreign_lens_set(c):
    """A lens set made for a 3 x 3-lens camera, passed to the 4 x 4-lens projector."""
    from plenocl.projection.lenses import lens_set
    foreign = lens_set(c["queue"], np.ones(9, bool), (3, 3), 2)
    c["proj"].forward_device(c["proj"].volume_to_device(c["vol"][:3, :4, :4]), lenses=foreign)


def _cal(image):
    return lambda c: calibrate(image(c), c["cam"])


def _cal_wrong_count(c):
    """The tiny camera's white image (4 x 4 lenses) with a camera file saying 2 x 2."""
    white = simulate_white_image(c["cam"], queue=c["queue"])
    calibrate(white, Camera(**{**TINY, "ml_count": (2, 2)}))


def _cal_wrong_stagger(c):
    """A hexagonal array's white image (odd rows half a pitch right) with a camera file
    saying half a pitch left."""
    hexagonal = {**TINY, "ml_layout": "hexagonal", "ml_count": (8, 8), "pixels": (137, 118)}
    white = simulate_white_image(Camera(**hexagonal), queue=c["queue"])
    calibrate(white, Camera(**hexagonal, ml_odd_row_shift=-0.5))


def _with_nan(a):
    a = a.astype(np.float64)
    a.flat[5] = np.nan
    return a


def _particle_image(c):
    pos = np.array([[0.05, 0.0, 0.3], [-0.1, 0.1, -0.5]])
    return simulate_image(c["cam"], pos, 1e4, 2000, queue=c["queue"])


def _tiny_field() -> PIVResult:
    """A 1 x 1 x 2 vector field."""
    one = np.ones((1, 1, 2))
    return PIVResult(x=np.array([8.0, 16.0]), y=np.array([8.0]), z=np.array([8.0]), u=one,
                     v=one, w=one, valid=one > 0, peak_ratio=one, outlier=one < 0,
                     masked=one < 0, window=(16, 16, 16))


def _saturated(image):
    """Three quarters of the pixels at the brightest value."""
    out = np.array(image, np.float64)
    out.ravel()[: 3 * out.size // 4] = out.max()
    return out


def _dense(image):
    """Every pixel lit (a dense image, no dark frame subtracted): the median is no dark
    level and 4 x the MAD lies above the brightest pixel."""
    return np.random.default_rng(3).uniform(100, 200, np.shape(image))


def _frame(make, name):
    """:func:`plenocl.pipeline.frames.load_frame` of the tiny camera's image made by
    ``make`` and saved as ``name``."""
    def call(c):
        np.save(c["dir"] / name, make(c["img"]))
        load_frame(c["dir"] / name, c["cam"])
    return call


def _file(reader, name):
    return lambda c: reader(c["dir"] / name)


NAN = float("nan")
# (id, call(ctx), exception type(s), key phrase of the message)
INVALID = [
    # Camera
    ("camera-focal-zero", _cam(focal_length_mm=0), ValueError,
     "focal_length_mm must be a positive finite number"),
    ("camera-f-number-negative", _cam(f_number=-2.0), ValueError,
     "f_number must be a positive finite number"),
    ("camera-magnification-nan", _cam(magnification=NAN), ValueError,
     "magnification must be a positive finite number"),
    ("camera-pixel-pitch-inf", _cam(pixel_pitch_mm=math.inf), ValueError,
     "pixel_pitch_mm must be a positive finite number"),
    ("camera-ml-count-one-value", _cam(ml_count=(4,)), ValueError,
     "microlens count must be two positive integers"),
    ("camera-ml-count-zero", _cam(ml_count=(0, 4)), ValueError,
     "microlens count must be two positive integers"),
    ("camera-ml-count-fraction", _cam(ml_count=(4.5, 4)), ValueError,
     "microlens count must be two positive integers"),
    ("camera-pixels-three-values", _cam(pixels=(70, 70, 70)), ValueError,
     "sensor pixels must be two positive integers"),
    ("camera-array-larger-than-sensor", _cam(ml_count=(100, 4)), ValueError,
     "larger than the sensor"),
    ("camera-too-few-pixels-per-lens", _cam(pixel_pitch_mm=0.1), ValueError,
     "pixels per microlens"),
    ("camera-region-beyond-sensor", lambda c: c["cam"].cropped((40, 0), (40, 70)),
     ValueError, "reaches beyond the 70 x 70 px sensor"),
    ("camera-region-without-lens", lambda c: c["cam"].cropped((0, 0), (6, 6)), ValueError,
     "holds no microlens image centre"),
    ("camera-full-pixels-without-origin", _cam(full_pixels=(100, 100)), ValueError,
     "full_pixels .* needs crop_origin"),
    ("camera-full-pixels-smaller-than-region", _cam(crop_origin=(40, 0), full_pixels=(100, 70)),
     ValueError, "must lie inside it"),
    ("camera-old-region-cropped-again",
     lambda c: Camera(**TINY, crop_origin=(8, 8)).cropped((0, 0), (60, 60)), ValueError,
     "add \\[sensor\\] full_pixels"),
    ("camera-rotation-nan", _cam(ml_rotation_deg=NAN), ValueError,
     "rotation and offset must be finite"),
    ("camera-layout", _cam(ml_layout="hex"), ValueError, "microlens layout must be one of"),
    ("camera-odd-row-shift", _cam(ml_layout="hexagonal", ml_odd_row_shift=0.25), ValueError,
     r"odd_row_shift must be one of \(0.5, -0.5\)"),
    ("camera-pupil-magnification", _cam(pupil_magnification=0.0), ValueError,
     "pupil_magnification must be a positive finite number"),
    ("camera-pose-nan", lambda c: Pose((0.0, NAN, 0.0), (0.0, 0.0, 0.0)), ValueError,
     r"\[pose\] rotation_deg must be three finite numbers"),
    ("camera-principal-planes-nan", _cam(principal_plane_separation_mm=NAN), ValueError,
     "principal_plane_separation_mm must be a finite number"),
    ("camera-centers-shape", _cam(microlens_centers=np.zeros((3, 3, 2))), ValueError,
     r"microlens_centers must have shape \(rows, cols, 2\)"),
    ("camera-centers-inf", _cam(microlens_centers=np.full((4, 4, 2), np.inf)), ValueError,
     "contain Inf; use NaN for missing lenses"),
    ("camera-file-missing-key", _file(Camera.from_toml, "camera_missing_key.toml"),
     ValueError, "lacks the key 'microlens_array'"),
    ("camera-file-not-toml", _file(Camera.from_toml, "camera_bad.toml"), ValueError,
     "is not valid TOML"),
    ("camera-ml-count-scalar", _cam(ml_count=4), (ValueError, TypeError),
     "microlens count"),
    ("camera-focal-not-a-number", _cam(focal_length_mm="fifty"), (ValueError, TypeError),
     "focal_length_mm"),
    # Grid
    ("grid-shape-zero", _grid(shape=(0, 4, 4)), ValueError,
     "grid shape must be three positive integers"),
    ("grid-shape-two-values", _grid(shape=(3, 4)), ValueError,
     "grid shape must be three positive integers"),
    ("grid-shape-fraction", _grid(shape=(3, 4, 4.5)), ValueError,
     "grid shape must be three positive integers"),
    ("grid-extent-reversed", _grid(x=(1, -1)), ValueError,
     "grid extent x must be two finite numbers"),
    ("grid-extent-empty", _grid(y=(1, 1)), ValueError, "grid extent y must be two finite"),
    ("grid-extent-nan", _grid(z=(-1, NAN)), ValueError, "grid extent z must be two finite"),
    ("grid-extent-three-values", _grid(x=(-1, 0, 1)), ValueError, "grid extent x"),
    ("grid-rotation-nan", _grid(rotation_deg=NAN), ValueError,
     "grid rotation_deg must be a finite angle"),
    ("grid-rotation-beyond-45", _grid(rotation_deg=60.0), ValueError, "within ±45 degrees"),
    # simulate_image / simulate_white_image
    ("simulate-positions-not-n-by-3", _sim(positions=((0.0, 0.0),)), ValueError,
     r"positions must be an \(N, 3\) array"),
    ("simulate-positions-nan", _sim(positions=((NAN, 0.0, 0.0),)), ValueError,
     "must be finite"),
    ("simulate-intensity-negative", _sim(intensities=-1.0), ValueError,
     "intensities must be >= 0"),
    ("random-particles-count", lambda c: random_particles(((0, 1),) * 3, count=2.5),
     ValueError, "count must be a whole number >= 0"),
    ("random-particles-intensity-range", lambda c: random_particles(
        ((0, 1),) * 3, count=3, intensity=(5e4, 1e4)), ValueError,
     r"intensity \(low, high\) must be finite, 0 <= low <= high"),
    ("flow-two-components", lambda c: flows.Uniform((1.0, 0.0)), ValueError,
     r"velocity must be three finite numbers \(x, y, z\)"),
    ("simulate-depth-impossible", _sim(positions=((0.0, 0.0, -60.0),)), ValueError,
     "forms no real image"),
    ("simulate-depth-at-focal-length", _sim(positions=((0.0, 0.0, -50.0),)), ValueError,
     "forms no real image"),
    ("simulate-pose-looks-away", lambda c: simulate_image(
        dataclasses.replace(c["cam"], pose=Pose((180.0, 0.0, 0.0), (0.0, 0.0, -60.0))),
        np.zeros((1, 3)), 1000.0, rays_per_particle=100, queue=c["queue"]), ValueError,
     r"camera's pose .* puts 1 of 1 points .* behind its main lens's front focal plane"),
    ("simulate-rays-zero", _sim(rays_per_particle=0), ValueError,
     "rays must be a positive integer"),
    ("simulate-rays-fraction", _sim(rays_per_particle=1.5), ValueError,
     "rays must be a positive integer"),
    ("simulate-bit-depth-zero", _sim(bit_depth=0), ValueError,
     "bit_depth must be a whole number from 1 to 16"),
    ("simulate-background-negative", _sim(background=-1.0), ValueError,
     "background must be >= 0"),
    ("simulate-intensities-wrong-length", _sim(intensities=[1.0, 2.0]), ValueError,
     "intensit"),
    ("simulate-blur-nan", _sim(blur_px=NAN), ValueError, "blur"),
    ("simulate-seed-negative", _sim(seed=-1), ValueError, "seed"),
    ("white-stop-faster-than-lens", _white(stop_f_number=1.0), ValueError,
     "stop_f_number must be >= the lens f-number"),
    ("white-rays-zero", _white(rays_per_lens=0), ValueError, "rays must be a positive integer"),
    ("white-vignetting-one", _white(vignetting=1.0), ValueError, r"vignetting must be in \[0, 1\)"),
    ("white-missing-shape", _white(missing=np.zeros((3, 3), bool)), ValueError,
     "missing must be a boolean mask of shape"),
    ("white-intensity-negative", _white(intensity=-5.0), ValueError, "intensity"),
    ("white-lens-shift-shape", _white(lens_shift_mm=np.zeros((3, 3, 2))), ValueError,
     r"lens_shift_mm must be a finite \(4, 4, 2\) array"),
    ("white-lens-shift-too-large", _white(lens_shift_mm=np.full((4, 4, 2), 0.04)), ValueError,
     "more than a quarter of the"),
    ("lens-displacements-jitter", lambda c: lens_displacements_mm(c["cam"], jitter_px=-0.2),
     ValueError, r"jitter_px must be >= 0"),
    # Projector
    ("grid-for-camera-posed", lambda c: Grid.for_camera(
        dataclasses.replace(c["cam"], pose=Pose((0.0, 20.0, 0.0), (0.0, 0.0, 0.0))),
        (-1.0, 1.0)), ValueError, r"works in the camera's own frame and does not take a "
     r"posed camera"),
    ("projector-posed-grid-aside", lambda c: Projector(
        dataclasses.replace(c["cam"], pose=Pose((0.0, 0.0, 0.0), (40.0, 0.0, 0.0))),
        Grid((3, 4, 4), (-0.2, 0.2), (-0.2, 0.2), (-1.0, 1.0)), c["queue"]), ValueError,
     r"seen through the camera's pose .* entirely outside the camera's field of view"),
    ("reconstruct-cameras-count", lambda c: reconstruct([c["img"]], [c["proj"], c["proj"]]),
     ValueError, r"several cameras need one image per projector: got 1 image\(s\) and 2"),
    ("reconstruct-cameras-pose", lambda c: reconstruct([c["img"], c["img"]],
                                                       [c["proj"], c["proj"]]),
     ValueError, r"cameras 1 and 2 have the same pose .* give each camera its own pose"),
    ("reconstruct-cameras-start", lambda c: reconstruct(
        [c["img"], c["img"]], [c["proj"], c["proj"]],
        start=np.ones(c["proj"].grid.shape, np.float32), supersample=1),
     ValueError, "pixel_mask and start volumes are for one camera"),
    ("projector-depth-not-imageable", _proj(z=(-60.0, 1.0)), ValueError,
     "where the main lens forms no real image"),
    ("projector-outside-field-of-view", _proj(x=(10.0, 11.0)), ValueError,
     "entirely outside the camera's field of view"),
    ("projector-depth-not-resolved", _proj(z=(200.0, 210.0)), ValueError,
     r"reaches beyond the depths the camera resolves: this camera resolves z in \["),
    ("grid-for-camera-depth-not-resolved",
     lambda c: Grid.for_camera(c["cam"], (-2.0, 25.0)), ValueError,
     r"reaches beyond the depths the camera resolves: this camera resolves z in \["),
    ("grid-for-camera-voxel-zero", lambda c: Grid.for_camera(c["cam"], (-1.0, 1.0),
                                                             voxel_mm=0), ValueError,
     "voxel_mm must be a positive size in mm"),
    ("grid-for-camera-voxel-unit", lambda c: Grid.for_camera(c["cam"], (-1.0, 1.0),
                                                             voxel_mm=50.0), ValueError,
     "is larger than the field of view covered"),
    ("grid-for-camera-fraction", lambda c: Grid.for_camera(c["cam"], (-1.0, 1.0),
                                                           fraction=0), ValueError,
     r"0 < fraction <= 1"),
    ("projector-centres-swapped",
     lambda c: Projector(c["cam"].with_centers(c["cam"].microlens_centers[..., ::-1]),
                         c["proj"].grid),
     ValueError, r"rows run along the sensor's columns.*centres\[\.\.\., ::-1\]"),
    ("projector-not-a-camera", lambda c: Projector("camera.toml", c["proj"].grid),
     TypeError, "takes a plenocl.Camera and a plenocl.Grid"),
    ("projector-method", _proj(method="sparse"), ValueError, "method must be one of"),
    ("lightfield-refocus-two-depths",
     lambda c: LightField(c["img"], c["cam"], queue=c["queue"]).refocus(z_mm=[0.0, 1.0]),
     ValueError, r"refocus takes one depth.*LightField.focal_stack"),
    ("camera-depth-nan", lambda c: c["cam"].image_distance_at(NAN), ValueError,
     "depth z must be a finite number of mm"),
    ("lightfield-axial-view",
     lambda c: LightField(np.ones((70, 70)),
                          Camera(**{**TINY, "ml_layout": "hexagonal"}).on_lens_lattice(),
                          queue=c["queue"]),
     ValueError, "not its axial view"),
    ("projector-back-mode", _proj(back="scatter"), ValueError, "back must be one of"),
    ("projector-oversample-zero", _proj(oversample=0), ValueError,
     "oversample must be a positive number"),
    ("projector-oversample-pinhole", _proj(oversample=0.01), ValueError,
     r"samples the aperture .* times across, fewer than 3: a pinhole"),
    ("projector-shear-tol", _proj(shear_tol=float("nan")), ValueError,
     "shear_tol must be a finite number"),
    ("projector-scratch-bytes", _proj(scratch_bytes=-5), ValueError,
     "scratch_bytes must be a positive whole number of bytes"),
    ("reconstruct-threshold-negative", _rec(threshold=-1.0), ValueError,
     "threshold must be a finite number >= 0"),
    ("reconstruct-tol", _rec(tol=float("nan")), ValueError, "tol must be a finite number >= 0"),
    ("reconstruct-mask-text", lambda c: reconstruct(c["img"], c["proj"], pixel_mask=np.full(
        c["img"].shape, "False")), ValueError, "pixel_mask must be boolean or numbers"),
    ("reconstruct-not-a-projector", lambda c: reconstruct(c["img"], c["cam"]), TypeError,
     r"reconstruct takes a projector \(plenocl.Projector\(camera, grid\)\)"),
    ("projector-buffer-too-large", _proj(max_alloc_bytes=1000), MemoryError,
     "the device allocates at most"),
    ("projector-forward-shape", lambda c: c["proj"].forward(np.ones((3, 4, 5))), ValueError,
     r"volume has shape \(3, 4, 5\), expected \(3, 4, 4\)"),
    ("projector-forward-nan", lambda c: c["proj"].forward(np.full((3, 4, 4), np.nan)),
     ValueError, "NaN or Inf"),
    ("projector-forward-complex", lambda c: c["proj"].forward(np.ones((3, 4, 4), complex)),
     TypeError, "must hold real numbers"),
    ("projector-back-shape", lambda c: c["proj"].back(np.ones((70, 71))), ValueError,
     r"image has shape \(70, 71\), expected \(70, 70\)"),
    ("projector-voxel-index", lambda c: c["proj"].voxel_weights(3, 0, 0), IndexError,
     "voxel indices must lie in the grid"),
    ("projector-lit-lenses-shape", lambda c: c["proj"].lit_lenses(np.ones((70, 71))),
     ValueError, r"image has shape \(70, 71\), expected \(70, 70\)"),
    ("projector-lit-lenses-nan", lambda c: c["proj"].lit_lenses(np.full((70, 70), np.nan)),
     ValueError, "NaN or Inf"),
    ("projector-lit-lenses-threshold-nan",
     lambda c: c["proj"].lit_lenses(np.ones((70, 70)), threshold=NAN), ValueError,
     "threshold must be a finite number"),
    ("projector-cropped-outside",
     lambda c: c["proj"].cropped((slice(0, 3), slice(0, 4), slice(2, 9))), ValueError,
     "box must be a non-empty, unit-step sub-box of the grid"),
    ("projector-cropped-empty",
     lambda c: c["proj"].cropped((slice(1, 1), slice(0, 4), slice(0, 4))), ValueError,
     "box must be a non-empty, unit-step sub-box of the grid"),
    ("projector-lens-set-size", lambda c: c["proj"].lens_set(np.ones(5, bool)), ValueError,
     "lit must hold one flag per microlens"),
    ("projector-lens-set-foreign", _foreign_lens_set, ValueError,
     "the lens set has 9 lenses, the camera 16"),
    # reconstruct
    ("reconstruct-image-shape", _rec(lambda i: i[:, :-1]), ValueError,
     "does not match the camera's sensor"),
    ("reconstruct-image-nan", _rec(_with_nan), ValueError, "NaN or Inf"),
    ("reconstruct-image-inf", _rec(lambda i: np.full(i.shape, np.inf)), ValueError,
     "NaN or Inf"),
    ("reconstruct-image-blank", _rec(np.zeros_like), ValueError,
     "the image is blank: every pixel is 0"),
    ("reconstruct-image-saturated", _rec(_saturated), ValueError, "the image is saturated"),
    ("reconstruct-image-no-light", _rec(lambda i: -1.0 - i, background=None), ValueError,
     "holds no light above its background, so the volume would be empty"),
    ("reconstruct-image-all-dark", _rec(_dense), ValueError,
     "every pixel counts as dark and the volume would be empty"),
    ("reconstruct-background", _rec(background="mean"), ValueError,
     "background must be 'median' or None"),
    ("reconstruct-image-bool", _rec(lambda i: i > 0), ValueError, "image must be numeric"),
    ("reconstruct-relax-zero", _rec(relax=0.0), ValueError, "relax"),
    ("reconstruct-relax-too-large", _rec(relax=2.0), ValueError, "relax"),
    ("reconstruct-relax-above-one", _rec(method="smart", relax=1.5), ValueError, "relax"),
    ("reconstruct-relax-nan", _rec(relax=NAN), ValueError, "relax"),
    ("reconstruct-method", _rec(method="art"), ValueError, "method must be one of"),
    ("reconstruct-iterations-negative", _rec(iterations=-1), ValueError,
     "iterations must be a non-negative integer"),
    ("reconstruct-iterations-fraction", _rec(iterations=1.5), ValueError,
     "iterations must be a non-negative integer"),
    ("reconstruct-mask-fraction", _rec(mask_fraction=1.5), ValueError,
     r"mask_fraction must be in \[0, 1\]"),
    ("reconstruct-mask-fraction-nan", _rec(mask_fraction=NAN), ValueError,
     r"mask_fraction must be in \[0, 1\]"),
    ("reconstruct-min-sensitivity-one", _rec(min_sensitivity=1.0), ValueError,
     r"min_sensitivity must be in \[0, 1\)"),
    ("reconstruct-min-sensitivity-nan", _rec(min_sensitivity=NAN), ValueError,
     r"min_sensitivity must be in \[0, 1\)"),
    ("reconstruct-start", _rec(start="zero"), ValueError,
     "start must be 'uniform', 'mlos' or a volume array"),
    ("reconstruct-start-zero", _rec(start=np.zeros((3, 4, 4))), ValueError,
     "start volume has no positive voxel"),
    ("reconstruct-iterations-bool", _rec(iterations=True), ValueError,
     "iterations must be a non-negative integer"),
    ("reconstruct-relax-text", _rec(relax="1"), ValueError, "relax must be a number"),
    ("reconstruct-zero-image-bad-relax", _rec(lambda i: np.zeros_like(i), relax=2.0),
     ValueError, "relax"),
    ("reconstruct-threshold-nan", _rec(threshold=NAN), ValueError, "threshold"),
    ("reconstruct-mart-blocks-zero", _rec(method="mart", mart_blocks=0), ValueError,
     "mart_blocks"),
    ("reconstruct-image-complex", _rec(lambda i: i.astype(complex)), (TypeError, ValueError),
     "complex|real"),
    ("reconstruct-supersample", _rec(supersample=5), ValueError,
     "supersample must be an integer from 1 to 4"),
    ("reconstruct-supersample-start", _rec(supersample=2, start=np.ones((3, 3, 3))), ValueError,
     "expected the grid's"),
    ("reconstruct-coarse-to-fine", _rec(supersample=2, coarse_iterations=-1), ValueError,
     "coarse_iterations must be a non-negative integer"),
    ("reconstruct-coarse-oversample", _rec(supersample=2, coarse_iterations=1,
                                           coarse_oversample=0.0), ValueError,
     "coarse_oversample must be a positive number"),
    ("reconstruct-early-sampling", _rec(supersample=2, early_oversample=-1.0), ValueError,
     "early_oversample must be a positive number"),
    ("reconstruct-early-iterations", _rec(supersample=2, early_iterations=1.5), ValueError,
     "early_iterations must be a non-negative integer"),
    ("reconstruct-ratio-floor-mlem", _rec(ratio_floor=0.3), ValueError,
     "geometric-mean methods"),
    ("reconstruct-ratio-floor-range", _rec(method="mart", ratio_floor=1.0), ValueError,
     r"ratio_floor must be in \(0, 1\)"),
    ("reconstruct-smooth-range", _rec(smooth_px=10.0), ValueError,
     "smooth_px must be a Gaussian's standard deviation"),
    # piv3d
    ("piv-shape-mismatch", _piv(b=lambda v: v[:-1]), ValueError, "must have the same shape"),
    ("piv-nan", _piv(a=lambda v: np.where(v > 0.5, np.nan, v)), ValueError, "NaN/Inf values"),
    ("piv-too-small", _piv(a=lambda v: v[:4], b=lambda v: v[:4]), ValueError,
     r"shape \(4, 16, 16\) holds no 8-voxel window"),
    ("piv-window-too-large", _piv(a=lambda v: v[:10], b=lambda v: v[:10], windows=(16,)),
     ValueError, "larger than the volume along z"),
    ("piv-all-zero", _piv(a=np.zeros_like), ValueError, "is constant"),
    ("piv-negative", _piv(b=lambda v: -v), ValueError, "vol_b holds negative intensities"),
    ("field-dt-text", lambda c: _tiny_field().velocity(0.1, dt="1e-3"), ValueError,
     r"dt must be a positive time in seconds \(a number"),
    ("field-origin-two", lambda c: save_field(c["dir"] / "o.npz", _tiny_field(),
                                              origin_mm=(1.0, 2.0)), ValueError,
     r"origin_mm must be finite, a scalar or \(z0, y0, x0\)"),
    ("field-voxel-size-two", lambda c: _tiny_field().velocity((0.1, 0.1), dt=1e-3),
     ValueError, r"voxel_size_mm must be positive, a scalar or \(dz, dy, dx\)"),
    ("piv-not-3d", _piv(a=lambda v: v[0], b=lambda v: v[0]), ValueError,
     "must be a 3-D volume"),
    ("piv-window-below-8", _piv(windows=(4,)), ValueError, "integers >= 8 voxels"),
    ("piv-settings-overlaps-count", lambda c: PIVSettings(windows=(16, 8),
                                                          overlaps=(0.5, 0.5, 0.5)),
     ValueError, r"overlaps \(3 values\) must match windows \(2 passes\)"),
    ("piv-overlap-one", _piv(windows=(8,), overlaps=1.0), ValueError,
     r"overlap of pass 1 must be a fraction in \[0, 1\)"),
    ("piv-complex", _piv(a=lambda v: v.astype(complex)), TypeError, "must hold real numbers"),
    ("piv-mask-not-bool", _piv(windows=(8,), mask=np.zeros((16, 16, 16))), TypeError,
     "mask must be boolean"),
    ("piv-mask-everything", _piv(windows=(8,), mask=np.ones((16, 16, 16), bool)), ValueError,
     r"nothing is left to correlate; True marks voxels to exclude \(pass ~mask"),
    ("piv-settings-windows-text", lambda c: PIVSettings(windows="32"), ValueError,
     "windows must be numbers .* not text"),
    ("piv-settings-overlap-alone", lambda c: PIVSettings(overlaps=1.5), ValueError,
     r"overlap of pass 1 must be a fraction in \[0, 1\)"),
    ("piv-settings-peak-ratio", lambda c: PIVSettings(min_peak_ratio=0.5), ValueError,
     "min_peak_ratio must be a finite number >= 1"),
    ("piv-settings-number", lambda c: PIVSettings(weighting=True), ValueError,
     "weighting must be a number, got True"),
    # the particles' fit to the raw images
    ("imagefit-image-shape", lambda c: ImageFit(c["cam"], c["proj"].grid, [c["img"][:-1]]),
     ValueError, "does not match the camera's sensor"),
    ("imagefit-image-nan", lambda c: ImageFit(
        c["cam"], c["proj"].grid, [np.where(c["img"] > 0, np.nan, c["img"])]),
     ValueError, "NaN or Inf pixel"),
    ("imagefit-rays", lambda c: ImageFitSettings(rays=8), ValueError,
     r"rays must be an integer >= 16"),
    ("imagefit-blur", lambda c: ImageFitSettings(blur_px=-1.0), ValueError,
     "blur_px must be a positive number"),
    ("imagefit-backgrounds-count", lambda c: ImageFit(
        c["cam"], c["proj"].grid, [c["img"], c["img"]], backgrounds=[(20.0, 3.0)]),
     ValueError, "got 1 backgrounds for 2 images"),
    ("imagefit-background-nan", lambda c: ImageFit(
        c["cam"], c["proj"].grid, [c["img"]], backgrounds=[(np.nan, 3.0)]),
     ValueError, "a known background needs a finite median"),
    # track
    ("track-too-few-frames", lambda c: track([c["img"]] * 3, c["proj"], dt=1e-3), ValueError,
     "tracking needs at least 4 frames"),
    ("track-frame-shape", lambda c: track([c["img"]] * 3 + [c["img"][:-1]], c["proj"],
                                          dt=1e-3), ValueError, "frame 3 is"),
    ("track-dt", lambda c: track([c["img"]] * 4, c["proj"], dt=0.0), ValueError,
     r"dt \(the time between frames\) must be a positive number"),
    ("track-gap", lambda c: TrackSettings(gap=-1), ValueError,
     "TrackSettings.gap must be an integer >= 0"),
    ("track-window", lambda c: TrackSettings(window=6), ValueError,
     "TrackSettings.window must be an odd number"),
    ("track-acceleration", lambda c: TrackSettings(acceleration=0.0), ValueError,
     "TrackSettings.acceleration must be a positive number"),
    ("track-neighbours", lambda c: TrackSettings(neighbours=3), ValueError,
     "TrackSettings.neighbours must be 0"),
    ("track-merge", lambda c: TrackSettings(merge=(0.7, 0.7)), ValueError,
     "TrackSettings.merge must be three distances"),
    ("track-search-scalar", lambda c: TrackSettings(search=5), ValueError,
     r"TrackSettings.search must be three positive distances .* got 5"),
    ("track-acceleration-text", lambda c: TrackSettings(acceleration="x"), ValueError,
     "TrackSettings.acceleration must be a positive number"),
    ("track-degree-prior", lambda c: TrackSettings(degree=0), ValueError,
     r"TrackSettings.degree = 0 gives the local fits no velocity"),
    ("track-one-image", lambda c: track(c["img"], c["proj"], dt=1e-3), ValueError,
     r"track takes a recording, a sequence of at least 4 frames .* got one 2-D image"),
    ("track-dt-text", lambda c: track([c["img"]] * 4, c["proj"], dt="1e-3"), ValueError,
     r"dt \(the time between frames\) must be a positive number"),
    # calibrate
    ("calibrate-blank", _cal(lambda c: np.zeros((70, 70))), ValueError, "white image is blank"),
    ("calibrate-noise", _cal(lambda c: np.random.default_rng(0).random((70, 70))), ValueError,
     "does not look like a white image"),
    ("calibrate-particle-image", _cal(_particle_image), ValueError,
     "does not look like a white image"),
    ("calibrate-shape", _cal(lambda c: np.ones((70, 71))), ValueError, "but the camera has"),
    ("calibrate-centres-index", lambda c: import_centers(c["dir"] / "centres_from_one.csv",
                                                         c["cam"]),
     ValueError, "outside the camera's 4 x 4 array"),
    ("calibrate-centres-region",
     lambda c: import_centers(c["dir"] / "centres_off_region.csv",
                              c["cam"].cropped((17, 0), (53, 70))),
     ValueError, "neither as the whole sensor's centres .* nor as the region's own"),
    ("calibrate-aperture", lambda c: calibrate(simulate_white_image(c["cam"], queue=c["queue"]),
                                               c["cam"], aperture="wide"),
     ValueError, "aperture must be one of"),
    ("calibrate-transposed",
     lambda c: calibrate(np.ones((71, 70)), Camera(**{**TINY, "pixels": (71, 70)})),
     ValueError, r"looks transposed: pass image\.T"),
    ("calibrate-nan", _cal(lambda c: np.full((70, 70), np.nan)), ValueError,
     "NaN or Inf pixels"),
    ("calibrate-lens-count", _cal_wrong_count, ValueError,
     r"shows about 4 x 4 microlens images .* the camera file has 2 x 2"),
    ("calibrate-hexagonal-stagger", _cal_wrong_stagger, ValueError,
     r"set \[microlens_array\] odd_row_shift = 0.5"),
    ("calibrate-colour", _cal(lambda c: np.ones((70, 70, 3))), ValueError,
     "one 2-D monochrome frame"),
    # io
    ("read-particles-missing", _file(read_particles, "nope.csv"), FileNotFoundError,
     "no such particle file"),
    ("read-particles-two-columns", _file(read_particles, "two_columns.csv"), ValueError,
     "expected 3 or 4 columns"),
    ("read-particles-five-columns", _file(read_particles, "five_columns.csv"), ValueError,
     "expected 3 or 4 columns"),
    ("read-particles-header-only", _file(read_particles, "header_only.csv"), ValueError,
     "at least one row"),
    ("read-particles-text", _file(read_particles, "text.csv"), ValueError,
     "expected CSV rows 'x_mm,y_mm,z_mm"),
    ("read-particles-no-header", _file(read_particles, "no_header.csv"), ValueError,
     "is a particle, not the header"),
    ("read-particles-other-units", _file(read_particles, "pixels.csv"), ValueError,
     r"the header names the columns \['x_px', 'y_px', 'z_px'\]"),
    ("read-image-empty", _file(read_image, "empty.tif"), ValueError, r"empty \(0 bytes\)"),
    ("read-volume-damaged", _file(load_volume, "cut.npz"), ValueError,
     "cannot be read as a volume"),
    ("grid-file-unknown-key", _file(Grid.from_toml, "grid_typo.toml"), ValueError,
     r"unknown key\(s\) \['rotaton_deg'\] in \[grid\]"),
    ("read-image-missing", _file(read_image, "nope.tif"), FileNotFoundError,
     "no such image file"),
    ("read-image-colour", _file(read_image, "colour.npy"), ValueError,
     "is a colour image with different red, green and blue"),
    ("read-image-channel", lambda c: read_image(c["dir"] / "colour.npy", channel="red"),
     ValueError, "channel must be one of"),
    ("read-image-stack", _file(read_image, "stack.npy"), ValueError, "expected one 2-D image"),
    ("load-frame-blank", _frame(np.zeros_like, "blank.npy"), ValueError,
     "blank.npy is blank: every pixel is 0"),
    ("load-frame-saturated", _frame(_saturated, "bright.npy"), ValueError,
     "bright.npy is saturated: 75% of its pixels"),
    ("load-volume-missing", _file(load_volume, "nope.npy"), FileNotFoundError,
     "no such volume file"),
    ("load-volume-not-3d", _file(load_volume, "line.npy"), ValueError, "not a 3-D volume"),
    ("save-field-format", lambda c: save_field(c["dir"] / "f.xyz", _tiny_field()), ValueError,
     "cannot tell the field format from 'f.xyz'"),
    ("save-field-folder-is-file",
     lambda c: save_field(c["dir"] / "two_columns.csv" / "f.npz", _tiny_field()),
     ValueError, "is a file, not a folder"),
    ("read-field-table", _file(read_field, "two_columns.csv"), ValueError,
     "reads fields back from .npz and .h5"),
    # plenocl plot
    ("plot-missing", _file(plot_file, "nope.npz"), FileNotFoundError, "no such file or store"),
    ("plot-unknown-file", _file(plot_file, "two_columns.csv"), ValueError,
     "cannot plot 'two_columns.csv'"),
    ("plot-figure-format", lambda c: plot_file(c["dir"] / "stack.npy", c["dir"] / "s.jpg"),
     ValueError, r"name it \.png \(PNG\) or \.pdf"),
    ("plot-view", lambda c: plot_file(c["dir"] / "stack.npy", c["dir"] / "s.png",
                                      PlotOptions(view="probe")),
     ValueError, "is a volume; its views are projection, slices"),
    ("plot-plane-outside", lambda c: plot_file(c["dir"] / "stack.npy", c["dir"] / "s.png",
                                               PlotOptions(view="slices", at=[99.0])),
     ValueError, "a plane at 99 voxel is outside the grid"),
]


@pytest.mark.parametrize(
    "call, exc, match",
    [pytest.param(*case[1:4], id=case[0])
     for case in INVALID])
def test_invalid_input_is_rejected_clearly(ctx, call, exc, match):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # e.g. NumPy's "input contained no data"
        with pytest.raises(exc, match=match):
            call(ctx)


def test_error_table_is_documented():
    """Every case of the table above has a row in docs/errors.md (by its id)."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parent.parent / "docs" / "errors.md").read_text()
    missing = [case[0] for case in INVALID if f"`{case[0]}`" not in doc]
    assert not missing, f"docs/errors.md lacks rows for {missing}"


def test_piv_too_small_message_suggests_valid_windows(ctx):
    vol = ctx["vol"][:4]
    with pytest.raises(ValueError) as err:
        piv3d(vol, vol)
    assert "windows=(0" not in str(err.value), str(err.value)


def test_mart_view_blocks_distinct_for_one_block_per_pixel(tiny):
    cam = tiny[0]
    n = 17  # ~17 px behind each lens: one block per sub-aperture view
    blocks = view_blocks(cam, n)
    assert len(np.unique(blocks)) == min(n * n, blocks.size)


def test_float32_limit_accepts_float32_1e30_and_names_both_numbers(tiny):
    """The limit is float32(1e30): a float32 image of 1e30 passes (it was refused because
    float32(1e30) = 1.0000000150e30 > 1e30), anything above is refused with a message
    whose two numbers differ."""
    cam = tiny[1].camera
    image = np.full(tiny[1].image_shape, 1e30, np.float32)
    scaled, scale, _ = preprocess(image, cam, None, 0.0)
    assert scale == float(np.float32(1e30)) == FLOAT32_LIMIT and scaled.max() == 1.0
    above = image.astype(np.float64) * (1 + 1e-7)
    with pytest.raises(ValueError, match="largest value") as info:
        preprocess(above, cam, None, 0.0)
    shown = [float(x) for x in re.findall(r"\d\.\d+e\+\d+", str(info.value))]
    assert len(shown) == 2 and shown[0] > shown[1], str(info.value)
