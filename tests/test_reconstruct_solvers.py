"""Solver kernels and loop against the NumPy references, on an explicit weight matrix
(a matrix-backed projector), plus the stability guards of docs/design.md §6."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
import tolerances as tol
from helpers import lens_camera

from plenocl import Grid, Projector
from plenocl.reconstruction import reconstruct, view_blocks
from plenocl.reconstruction.operator import ProjectionOperator
from plenocl.reference import reconstruct as ref


def reconstruct_voxels(image, projector, *args, **keywords):
    """:func:`plenocl.reconstruction.reconstruct` on the voxels themselves
    (``supersample=1``): the kernels are checked voxel by voxel against the references,
    and a matrix operator has no sub-voxels; on the image as given (``smooth_px=0`` unless
    said: the references take no smoothing, which tests/test_smoothing.py checks)."""
    keywords.setdefault("smooth_px", 0)
    return reconstruct(image, projector, *args, supersample=1, **keywords)


class MatrixProjector:
    """A projector from an explicit matrix W (pixels x voxels), for solver tests; it holds
    volumes as two depth slabs so the per-slab code paths are exercised. It implements
    the whole operator contract (plenocl.reconstruction.ProjectionOperator): every lens
    counts as lit and lens sets are ignored (skipping dark lenses is exact), and a crop
    keeps the columns of W of the sub-box."""

    def __init__(self, W, camera, grid, queue):
        self.W, self.camera, self.grid, self.queue = W, camera, grid, queue
        self._sens = None

    def empty_volume(self):
        """Two depth slabs, like a projector that splits the volume."""
        nz, ny, nx = self.grid.shape
        return [cla.empty(self.queue, (1, ny, nx), np.float32),
                cla.empty(self.queue, (nz - 1, ny, nx), np.float32)]

    def volume_to_host(self, slabs):
        return np.concatenate([s.get() for s in slabs])

    def volume_to_device(self, vol):
        vol = np.ascontiguousarray(vol, dtype=np.float32)
        return [cla.to_device(self.queue, vol[:1]), cla.to_device(self.queue, vol[1:])]

    def forward_device(self, vol, out=None, active=None, lenses=None):
        img = (self.W @ self.volume_to_host(vol).ravel().astype(np.float64)).astype(np.float32)
        return cla.to_device(self.queue, img.reshape(self.camera.pixels[::-1]))

    def back_device(self, img, out=None, active=None, lenses=None, support=None):
        vol = (self.W.T @ img.get().ravel().astype(np.float64)).astype(np.float32)
        return self.volume_to_device(vol.reshape(self.grid.shape))

    def sensitivity(self):
        if self._sens is None:
            self._sens = self.back_device(cla.to_device(
                self.queue, np.ones(self.camera.pixels[::-1], np.float32)))
        return self._sens

    def lit_lenses(self, image, threshold=0.0):
        return np.ones(self.camera.ml_count[0] * self.camera.ml_count[1], bool)

    def lens_set(self, lit):
        return None

    def cropped(self, box):
        cols = np.arange(self.grid.size).reshape(self.grid.shape)[box].ravel()
        shape = tuple(s.stop - s.start for s in box)
        sub = Grid(shape, x=(0, shape[2]), y=(0, shape[1]), z=(0, shape[0]))
        return MatrixProjector(self.W[:, cols], self.camera, sub, self.queue)


def test_both_projectors_implement_the_operator_contract(tiny, queue):
    cam = lens_camera(3, 3)
    assert isinstance(tiny[0], ProjectionOperator)
    assert isinstance(Projector(cam, Grid((3, 4, 5), x=(-0.2, 0.2), y=(-0.2, 0.2),
                                          z=(-1, 1)), queue), ProjectionOperator)
    assert not isinstance(object(), ProjectionOperator)


def _solver(expected: np.ndarray) -> dict:
    """A solver against its NumPy twin: :data:`tolerances.SOLVER`, floor of the peak."""
    return dict(rtol=tol.SOLVER, atol=tol.SOLVER_FLOOR * expected.max())


@pytest.fixture(scope="module")
def tiny(queue):
    """A 3 x 3-lens camera (51 x 51 px) and a 3 x 4 x 5 grid with a random sparse,
    column-normalised W, and an image made from a sparse true volume."""
    cam = lens_camera(3, 3)
    grid = Grid((3, 4, 5), x=(-0.2, 0.2), y=(-0.2, 0.2), z=(-1, 1))
    rng = np.random.default_rng(0)
    W = rng.random((51 * 51, 60)) * (rng.random((51 * 51, 60)) < 0.05)
    W /= W.sum(0, keepdims=True) * 1.05  # 5% of each voxel's light misses the sensor
    truth = np.zeros(60)
    truth[[3, 17, 42]] = [2.0, 1.0, 3.0]
    image = (W @ truth).reshape(51, 51)
    return MatrixProjector(W, cam, grid, queue), W, image


@pytest.mark.parametrize("method, fn", [("mlem", ref.mlem), ("smart", ref.smart)])
def test_simultaneous_solvers_match_reference(tiny, method, fn):
    proj, W, image = tiny
    vol = reconstruct_voxels(image, proj, method, iterations=12, relax=0.8)
    expected = fn(W, image / image.max(), 12, 0.8) * image.max()
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))


@pytest.mark.parametrize("relax", [1.5, 1.3, 1.9])
def test_over_relaxed_mlem_matches_reference(tiny, relax):
    """MLEM at 1 < μ < 2 (the kernel's square-root form at 1.5, pow otherwise) is the
    reference's update."""
    proj, W, image = tiny
    vol = reconstruct_voxels(image, proj, "mlem", iterations=6, relax=relax)
    expected = ref.mlem(W, image / image.max(), 6, relax) * image.max()
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))


def test_block_mart_matches_block_reference_and_approaches_sequential(tiny):
    proj, W, image = tiny
    blocks = view_blocks(proj.camera, 2).ravel()
    vol = reconstruct_voxels(image, proj, "mart", iterations=5, relax=0.7, mart_blocks=2)
    groups = [np.nonzero(blocks == b)[0] for b in range(4)]
    expected = ref.mart_blocks(W, image / image.max(), groups, 5, 0.7) * image.max()
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))
    seq = ref.mart_sequential(W, image / image.max(), 5, 0.7) * image.max()
    assert np.corrcoef(vol.ravel(), seq)[0, 1] > 0.99


@pytest.mark.parametrize("floor", [0.05, 0.5])
def test_ratio_floor_matches_the_references(tiny, floor):
    """SMART and block MART with a ratio floor, kernel against NumPy. The floor changes
    the result: a dark pixel's log ratio is log(floor), not -13.8, so the voxels seen by
    dark pixels fall far more slowly than in the literal form."""
    proj, W, image = tiny
    top = image.max()
    vol = reconstruct_voxels(image, proj, "smart", iterations=8, relax=0.8, ratio_floor=floor)
    expected = ref.smart(W, image / top, 8, 0.8, ratio_floor=floor) * top
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))
    literal = ref.smart(W, image / top, 8, 0.8) * top
    dark = (W.T @ (image.ravel() <= 0)) > 0
    assert expected[dark].max() > 1e3 * literal[dark].max()
    groups = [np.nonzero(view_blocks(proj.camera, 2).ravel() == b)[0] for b in range(4)]
    vol = reconstruct_voxels(image, proj, "mart", iterations=4, relax=0.7, ratio_floor=floor)
    expected = ref.mart_blocks(W, image / top, groups, 4, 0.7, ratio_floor=floor) * top
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))


def test_solvers_converge_to_the_truth_on_a_determined_case(tiny):
    proj, W, image = tiny
    vol = reconstruct_voxels(image, proj, "mlem", iterations=300)
    assert np.argsort(vol.ravel())[-3:].tolist() == [17, 3, 42]
    resid = np.linalg.norm(W @ vol.ravel() - image.ravel()) / np.linalg.norm(image)
    assert resid < 0.05


@pytest.mark.parametrize("method", ["mlem", "smart", "mart"])
@pytest.mark.parametrize("relax", [1e-6, 1.0])
def test_thousand_iterations_stay_finite(tiny, method, relax):
    proj, _, image = tiny
    vol = reconstruct_voxels(image, proj, method, iterations=1000 if method != "mart" else 250,
                             relax=relax)
    assert np.all(np.isfinite(vol)) and vol.min() >= 0 and vol.max() > 0


@pytest.mark.parametrize("make", [
    lambda im: np.pad(np.ones((1, 1)), ((10, 40), (20, 30))) * 1e6,
    lambda im: im / im.max() * 1e-6,
    lambda im: im / im.max() * 1e6,
    lambda im: (im / im.max() * 255).astype(np.uint8),
    lambda im: (im / im.max() * 65535).astype(np.uint16),
    lambda im: im.astype(np.float16),
])
def test_extreme_images_never_give_nan_or_inf(tiny, make):
    """Finite and non-negative, or (one lit pixel, whose light no voxel sends half of
    its own to) the mask's emptying every voxel said (it returned zeros)."""
    proj, _, image = tiny
    img = make(image)
    if np.count_nonzero(img) == 1:
        with pytest.raises(ValueError, match="mask_fraction=0.5 zeroed every voxel"):
            reconstruct_voxels(img, proj, "mlem", iterations=20, start="mlos",
                               mask_fraction=0.5)
        return
    vol = reconstruct_voxels(img, proj, "mlem", iterations=20, start="mlos",
                             mask_fraction=0.5)
    assert np.all(np.isfinite(vol)) and vol.min() >= 0


@pytest.mark.parametrize("make, message", [
    (np.zeros_like, "blank: every pixel is 0"),
    (lambda im: np.clip(im * 1e3, 0, 1.0) ** 0, "uniform: every pixel is 1"),  # saturated
])
def test_images_without_an_image_are_refused_not_reconstructed(tiny, make, message):
    proj, _, image = tiny
    with pytest.raises(ValueError, match=message):
        reconstruct_voxels(make(image), proj, "mlem", iterations=20, start="mlos",
                           mask_fraction=0.5)


def test_dynamic_range_scales_linearly(tiny):
    proj, _, image = tiny
    lo = reconstruct_voxels(image * 1e-6, proj, "smart", iterations=10)
    hi = reconstruct_voxels(image * 1e6, proj, "smart", iterations=10)
    np.testing.assert_allclose(lo * 1e12, hi, rtol=tol.ITERATED, atol=1e-6 * hi.max())


def test_same_input_same_output(tiny):
    proj, _, image = tiny
    a = reconstruct_voxels(image, proj, "mlem", iterations=10)
    np.testing.assert_array_equal(a, reconstruct_voxels(image, proj, "mlem", iterations=10))


def test_masking_keeps_zero_voxels_zero_and_callback_can_stop(tiny):
    proj, W, image = tiny
    seen = []
    vol, info = reconstruct_voxels(image, proj, "mlem", iterations=50, mask_fraction=0.0,
                                   callback=lambda it, r: seen.append(it) or it < 7,
                                   return_info=True)
    dark_voxels = (W.T @ (image.ravel() <= 0)) > 0
    assert np.all(vol.ravel()[dark_voxels] == 0)
    assert seen == list(range(1, 8)) and info.iterations == 7
    _, info = reconstruct_voxels(image, proj, "mlem", iterations=5000, tol=1e-4, return_info=True)
    assert info.converged and info.iterations < 5000


@pytest.mark.parametrize("kwargs, message", [
    (dict(relax=0.0), "0 < μ < 2"), (dict(relax=2.0), "0 < μ < 2 for MLEM"),
    (dict(method="smart", relax=1.5), "0 < μ <= 1 for SMART"),
    (dict(method="mart", relax=1.01), "0 < μ <= 1 for MART"),
    (dict(method="art"), "method must be"), (dict(iterations=-1), "non-negative"),
    (dict(mask_fraction=2.0), "mask_fraction"), (dict(start="random"), "start must be"),
    (dict(ratio_floor=0.3), "geometric-mean methods"),
    (dict(method="mart", ratio_floor=1.0), "ratio_floor must be in"),
    (dict(method="smart", ratio_floor=float("nan")), "ratio_floor must be in"),
])
def test_bad_options_are_rejected(tiny, kwargs, message):
    proj, _, image = tiny
    with pytest.raises(ValueError, match=message):
        reconstruct_voxels(image, proj, **{"iterations": 1, **kwargs})


@pytest.mark.parametrize("bad, message, kw", [
    (np.zeros((50, 51)), "does not match", {}),
    (np.full((51, 51), np.nan), r"NaN or Inf pixel\(s\), the first at row 0, column 0", {}),
    (-np.ones((51, 51)), "uniform: every pixel is -1", dict(background=None)),
    (np.ones((51, 51)), "background must be", dict(background="mean")),
])
def test_bad_images_are_rejected(tiny, bad, message, kw):
    proj, _, _ = tiny
    with pytest.raises(ValueError, match=message):
        reconstruct_voxels(bad, proj, iterations=1, **kw)


def test_the_median_background_and_noise_threshold_are_the_default(tiny):
    """A dark level with read noise (negative pixels after dark subtraction) reconstructs
    as the clean image does, by default; an image without light is refused."""
    proj, _, image = tiny
    clean = reconstruct_voxels(image, proj, "mlem", iterations=10)
    rng = np.random.default_rng(2)
    noisy = image + 0.002 * image.max() * rng.standard_normal(image.shape) - 5e-4
    assert noisy.min() < 0
    got = reconstruct_voxels(noisy, proj, "mlem", iterations=10)
    assert np.corrcoef(got.ravel(), clean.ravel())[0, 1] > 0.99
    with pytest.raises(ValueError, match="uniform: every pixel is 7"):
        reconstruct_voxels(np.full(image.shape, 7.0), proj, iterations=3)


@pytest.mark.parametrize("rotation, jitter", [(0.0, 0.0), (2.0, 0.0), (0.3, 0.2)])
def test_view_blocks_from_the_lattice_match_the_nearest_centre(small_camera, rotation, jitter):
    """MART's blocks from the lens lattice are the reference's nearest-centre blocks at
    every pixel whose nearest centre is clearly nearer than the next one (ties at cell
    borders may go either way)."""
    from scipy.spatial import cKDTree

    cam = lens_camera(ml_rotation_deg=rotation)
    if jitter:
        rng = np.random.default_rng(1)
        cam = cam.with_centers(cam.microlens_centers
                               + rng.uniform(-jitter, jitter, cam.microlens_centers.shape))
    for n in (2, 3):
        got, ref_blocks = view_blocks(cam, n), ref.view_blocks(cam, n)
        h, w = got.shape
        rows, cols = np.mgrid[0:h, 0:w]
        pix = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
        d, _ = cKDTree(cam.microlens_centers.reshape(-1, 2)).query(pix, k=2)
        clear = (d[:, 1] - d[:, 0] > 2 * jitter + 1e-6).reshape(h, w)
        # rounding the offset is ambiguous at half pixels too
        assert clear.mean() > 0.9
        agree = got[clear] == ref_blocks[clear]
        assert agree.mean() > 0.995, (n, agree.mean())


def test_mart_blocks_are_set_up_once_per_projector(tiny):
    from plenocl.reconstruction import device_view_blocks

    proj = tiny[0]
    first = device_view_blocks(proj, 2)
    assert device_view_blocks(proj, 2) is first
    np.testing.assert_array_equal(first.get(), view_blocks(proj.camera, 2))
    assert device_view_blocks(proj, 3) is not first


@pytest.mark.parametrize("method, fn", [("mlem", ref.mlem), ("smart", ref.smart)])
def test_pixels_without_data_match_the_reference(tiny, method, fn):
    """A pixel mask: the kernels' missing-data update (ratio 1) equals the twin's."""
    proj, W, image = tiny
    observed = np.random.default_rng(4).random(image.shape) > 0.3
    vol = reconstruct_voxels(image, proj, method, iterations=12, relax=0.8, background=None,
                             threshold=0.0, pixel_mask=observed)
    top = image[observed].max()
    expected = fn(W, np.where(observed, image, 0.0) / top, 12, 0.8, observed=observed) * top
    np.testing.assert_allclose(vol.ravel(), expected, **_solver(expected))


def test_a_pixel_mask_is_checked(tiny):
    proj, _, image = tiny
    with pytest.raises(ValueError, match="pixel_mask shape"):
        reconstruct_voxels(image, proj, pixel_mask=np.ones((5, 5), bool))
    with pytest.raises(ValueError, match="leaves no pixel"):
        reconstruct_voxels(image, proj, pixel_mask=np.zeros(image.shape, bool))
    with pytest.raises(ValueError, match="start='mlos' cannot use a pixel_mask"):
        reconstruct_voxels(image, proj, start="mlos", pixel_mask=np.ones(image.shape, bool))


def test_pixels_without_data_carry_no_light_after_a_negative_median(tiny):
    """A frame whose dark level was over-subtracted (median -50): the masked pixels, 0 in
    the image, stay 0, and the scale is the observed pixels' brightest above the median
    (20), not the masked pixels' 50 above it."""
    from plenocl.reconstruction import preprocess

    proj, _, _ = tiny
    rng = np.random.default_rng(6)
    shape = proj.camera.pixels[::-1]
    image = -50.0 + rng.normal(0, 0.5, shape)
    image[10, 10] = -30.0
    observed = np.ones(shape, bool)
    observed[:, :10] = False
    out, scale, _ = preprocess(image, proj.camera, "median", None, observed)
    med = np.median(image[observed])
    assert scale == pytest.approx(-30.0 - med) and np.all(out[~observed] == 0)
