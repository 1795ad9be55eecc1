"""Lateral supersampling of the reconstruction (docs/design.md §6.4): the refined grid and
projector, binning back, and the depth it buys on ray-traced particles."""

from __future__ import annotations

import numpy as np
import pytest
import tolerances as tol
from helpers import assert_adjoint
from scipy import ndimage

from plenocl import Grid, Projector, random_particles, reconstruct
from plenocl.bench.accuracy_section import paper_optics
from plenocl.metrics import recovery
from plenocl.opencl import arrays
from plenocl.opencl.device import DeviceInfo
from plenocl.opencl.volume import DeviceVolume
from plenocl.reconstruction import (
    ReconstructionSettings,
    Solver,
    bin_lateral,
    spread_lateral,
)
from plenocl.reconstruction import images as images_module
from plenocl.reconstruction.images import prepare_image
from plenocl.reconstruction.schedule import box_dilated
from plenocl.reconstruction.settings import COARSE_OVERSAMPLE
from plenocl.reconstruction.supersample import LateralBinning
from plenocl.simulate import simulate_image


def test_refined_grid_keeps_the_volume_and_splits_lateral_voxels():
    g = Grid((5, 4, 6), x=(-1.2, 1.2), y=(-0.8, 0.8), z=(-1, 1), rotation_deg=3.0)
    f = g.refined(3)
    assert f.shape == (5, 12, 18) and (f.x, f.y, f.z) == (g.x, g.y, g.z)
    assert f.rotation_deg == g.rotation_deg
    assert np.allclose(np.array(f.spacing) * [1, 3, 3], g.spacing)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="positive integer"):
            g.refined(bad)


def test_binning_undoes_spreading_and_conserves_intensity():
    rng = np.random.default_rng(1)
    vol = rng.random((3, 5, 7)).astype(np.float32)
    assert np.allclose(bin_lateral(spread_lateral(vol, 3), 3), vol, rtol=tol.ROUNDING)
    fine = rng.random((3, 10, 14)).astype(np.float32)
    assert bin_lateral(fine, 2).sum() == pytest.approx(fine.sum(), rel=tol.CONSERVATION)
    assert bin_lateral(fine, 2)[1, 2, 3] == pytest.approx(fine[1, 4:6, 6:8].sum(),
                                                       rel=tol.ROUNDING)
    with pytest.raises(ValueError, match="does not bin by 3"):
        bin_lateral(fine, 3)


@pytest.fixture(scope="module")
def optics(queue):
    """The paper's optics on 24 x 16 lenses (a 150 x 16 x 23 grid of the paper's voxel)."""
    cam, grid = paper_optics((24, 16))
    return cam, grid, Projector(cam, grid, queue)


def test_the_refined_projector_is_built_once_adjoint_and_sees_the_same_volume(optics):
    cam, grid, proj = optics
    fine = proj.refined(2)
    assert proj.refined(2) is fine and proj.refined(1) is proj
    assert fine.grid == grid.refined(2)
    assert_adjoint(fine)
    # a coarse volume and the same volume spread over sub-voxels make nearly one image
    vol = np.zeros(grid.shape, np.float32)
    vol[30, 8, 11], vol[100, 5, 17] = 1.0, 2.0
    coarse, refined = proj.forward(vol), fine.forward(spread_lateral(vol, 2))
    assert refined.sum() == pytest.approx(coarse.sum(), rel=0.02)
    assert np.corrcoef(coarse.ravel(), refined.ravel())[0, 1] > 0.95


def test_supersampled_reconstruction_is_the_binned_fine_one(optics, queue):
    cam, grid, proj = optics
    pos, inten = random_particles(((-1.3, 1.3), (-0.8, 0.8), (-8, 8)), count=6, seed=3,
                                  intensity=2e4)
    img = simulate_image(cam, pos, inten, 4000, seed=1, queue=queue, background=20.0)
    flat = dict(supersample=2, coarse_iterations=0)  # the sub-voxels from a uniform start
    vol, info = reconstruct(img, proj, iterations=6, return_info=True, **flat)
    fine = reconstruct(img, proj.refined(2), iterations=6, supersample=1)
    # binned on the device (kernels/supersample.cl) against the NumPy twin
    np.testing.assert_allclose(vol, bin_lateral(fine, 2), rtol=tol.BINNED, atol=0)
    assert vol.shape == grid.shape and info.supersample == 2
    # a start volume is given on the coarse grid and spread over the sub-voxels
    resumed = reconstruct(img, proj, iterations=3, start=vol, **flat)
    assert resumed.shape == grid.shape and np.isfinite(resumed).all()
    with pytest.raises(ValueError, match=r"expected the grid's \(150, 16, 23\)"):
        reconstruct(img, proj, iterations=1, start=spread_lateral(vol, 2), **flat)


@pytest.mark.parametrize("bad", [0, 5, 1.5, True])
def test_bad_supersample_factors_are_refused(bad):
    with pytest.raises(ValueError, match="supersample must be an integer from 1 to 4"):
        ReconstructionSettings(supersample=bad)


@pytest.mark.parametrize("bad", [{"coarse_iterations": -1}, {"coarse_iterations": 2.5},
                                 {"support": 1.0}, {"support": -0.1},
                                 {"support": float("nan")}])
def test_bad_coarse_to_fine_options_are_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        ReconstructionSettings(supersample=3, **bad)


@pytest.mark.parametrize("coarse_oversample", [COARSE_OVERSAMPLE, None])
def test_coarse_to_fine_starts_flat_on_the_grown_support_and_conserves_zeros(
        coarse_oversample, optics, queue):
    """The fine iterations start from the coarse volume's support (grown by one voxel,
    flat) and stay on it; the coarse iterations run on the aperture sampled
    ``coarse_oversample`` times per pixel footprint (``None``: the projector's own); an
    empty image is refused."""
    cam, grid, proj = optics
    pos, inten = random_particles(((-1.3, 1.3), (-0.8, 0.8), (-8, 8)), count=6, seed=4,
                                  intensity=2e4)
    img = simulate_image(cam, pos, inten, 4000, seed=2, queue=queue, background=20.0)
    coarse_proj = proj if coarse_oversample is None else proj.sampled(coarse_oversample)
    assert coarse_proj.aperture.n < proj.aperture.n or coarse_oversample is None
    coarse = reconstruct(img, coarse_proj, iterations=4, supersample=1)
    vol, info = reconstruct(img, proj, iterations=3, supersample=2, coarse_iterations=4,
                            support=0.05, relax=1.0, coarse_oversample=coarse_oversample,
                            return_info=True)
    grown = ndimage.binary_dilation(coarse > 0.05 * coarse.max(), np.ones((3, 3, 3), bool))
    assert info.support_fraction == pytest.approx(grown.mean())
    assert not vol[~grown].any() and vol[grown].any()
    assert vol.sum() == pytest.approx(coarse.sum(), rel=0.1)
    with pytest.raises(ValueError, match="uniform: every pixel is 20"):
        reconstruct(np.full(img.shape, 20.0, np.float32), proj, supersample=2,
                    coarse_iterations=2)


def test_a_sampled_projector_is_kept_and_its_own_adjoint(optics, queue):
    """``Projector.sampled``: the same grid and camera on a coarser aperture sampling,
    built once per value, itself at its own value, and a true pair of transposes."""
    cam, grid, proj = optics
    coarse = proj.sampled(0.5)
    assert proj.sampled(0.5) is coarse and proj.sampled(proj.oversample) is proj
    assert coarse.grid == grid and coarse.oversample == 0.5
    assert coarse.n_samples < proj.n_samples / 4
    assert_adjoint(coarse, seed=3)


def test_an_operator_that_cannot_refine_is_refused(optics):
    class Plain:  # an operator without refined()
        grid = optics[1]

    with pytest.raises(ValueError, match="needs a projector that can refine its grid"):
        reconstruct(np.ones(optics[0].pixels[::-1]), Plain(), supersample=2)


def test_a_refined_grid_that_does_not_fit_names_the_smaller_factor(optics):
    class TooBig:  # an operator whose refined grid exceeds the device
        grid = optics[1]

        def refined(self, factor):
            raise MemoryError("projecting a grid needs 90 GiB of device memory")

    with pytest.raises(MemoryError, match=r"90 GiB.*supersample=3 reconstructs on 9x the "
                                          r"grid's voxels.*supersample=1"):
        reconstruct(np.ones(optics[0].pixels[::-1]), TooBig(), supersample=3)


def test_sub_voxels_recover_more_ray_traced_particles_and_fewer_ghosts(optics, queue):
    """At the paper's voxel (about one microlens), 3 x 3 sub-voxels place ray-traced,
    blurred, noisy particles within 1 voxel laterally and 2 in depth far more often
    (recovery up by at least 15 points on average) and leave less intensity in ghosts,
    in every scene."""
    cam, grid, proj = optics
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    gain, c2f_gain = [], []
    for seed in (21, 22):
        pos, inten = random_particles(box, count=20, seed=seed, intensity=2e4)
        img = simulate_image(cam, pos, inten, 20000, seed=seed, queue=queue, blur_px=0.8,
                             background=20.0, photon_noise=True, read_noise=3.0)
        one, three = (recovery(reconstruct(img, proj, supersample=f, coarse_iterations=0),
                               grid, pos) for f in (1, 3))  # 30 iterations on each grid
        vol, info = reconstruct(img, proj, supersample=3, iterations=10, coarse_iterations=10,
                                support=1e-2, relax=1.0, return_info=True)
        c2f = recovery(vol, grid, pos)
        assert three.ghost_fraction < one.ghost_fraction
        gain.append(three.fraction - one.fraction)
        c2f_gain.append(c2f.fraction - one.fraction)
        # the fine iterations never leave the coarse support
        assert info.coarse_iterations == 10 and 0 < info.support_fraction < 0.5
        assert np.count_nonzero(vol) <= info.support_fraction * vol.size
    assert np.mean(gain) >= 0.15 and np.mean(c2f_gain) >= 0.15


# ---- device binning (kernels/supersample.cl) against bin_lateral ----------------------
@pytest.mark.parametrize(("factor", "shape"), [(3, (5, 7, 11)), (2, (4, 9, 5)),
                                               (4, (3, 2, 3))])
def test_device_binning_is_bin_lateral_on_awkward_sizes(queue, factor, shape):
    """Odd sizes, several slabs, a scale, and a part whose lateral start and end are not
    on a block boundary (the rest of the fine grid zero)."""
    import pyopencl.array as cla

    nz, ny, nx = shape
    rng = np.random.default_rng(factor)
    fine = (rng.random((nz, ny * factor, nx * factor)) ** 4).astype(np.float32)
    fine[fine < 0.2] = 0
    binning = LateralBinning(queue)
    slabs = [cla.to_device(queue, np.ascontiguousarray(s)) for s in
             np.array_split(fine, min(3, nz))]
    got = binning.to_host(slabs, factor, scale=7.5)
    np.testing.assert_allclose(got, bin_lateral(fine * np.float32(7.5), factor),
                               rtol=tol.BINNED, atol=0)
    ys, xs = slice(1, ny * factor - 1), slice(factor - 1, nx * factor)
    part = fine[:, ys, xs]
    full = np.zeros_like(fine)
    full[:, ys, xs] = part
    got = binning.to_host([cla.to_device(queue, np.ascontiguousarray(part))], factor,
                          (1, factor - 1))
    np.testing.assert_allclose(got, bin_lateral(full, factor), rtol=tol.BINNED, atol=0)
    with pytest.raises(ValueError, match=r"offset \(0, 5\) must lie in"):
        binning.to_host(slabs, factor, (0, 5))


@pytest.mark.parametrize(("factor", "shape"), [(3, (5, 7, 11)), (2, (4, 1, 5)),
                                               (4, (3, 2, 3))])
def test_device_spreading_is_spread_lateral_on_awkward_sizes(queue, factor, shape):
    """A coarse volume spread into several device slabs, scaled, equals spread_lateral to
    float32 rounding; binned back it is the coarse volume (intensity conserved); slabs
    of another shape are refused."""
    import pyopencl.array as cla

    nz, ny, nx = shape
    coarse = (np.random.default_rng(factor).random(shape) ** 4).astype(np.float32)
    coarse[coarse < 0.2] = 0
    binning = LateralBinning(queue)
    parts = np.array_split(np.zeros((nz, ny * factor, nx * factor), np.float32), min(3, nz))
    slabs = [cla.to_device(queue, np.ascontiguousarray(p)) for p in parts]
    binning.spread_into(coarse, factor, slabs, scale=0.5)
    got = np.concatenate([s.get() for s in slabs])
    np.testing.assert_allclose(got, spread_lateral(coarse, factor) * np.float32(0.5),
                               rtol=tol.ROUNDING, atol=0)
    assert np.array_equal(got == 0, spread_lateral(coarse, factor) == 0)
    np.testing.assert_allclose(bin_lateral(got, factor), 0.5 * coarse, rtol=tol.BINNED * 4,
                               atol=0)
    with pytest.raises(ValueError, match="does not spread by"):
        binning.spread_into(coarse[:-1], factor, slabs)


@pytest.mark.parametrize(("factor", "shape"), [(3, (5, 7, 11)), (2, (4, 1, 5)),
                                               (4, (3, 2, 3)), (3, (9, 6, 2))])
def test_the_support_found_on_the_device_is_the_hosts_spread(queue, factor, shape):
    """The coarse run's support found and spread on the device
    (``LateralBinning.spread_support``) is the host's flat start (``support_of``: the
    voxels above the float32 floor, grown by the 3 x 3 x 3 box within the faces, at the
    support's mean) spread into the same slabs, bit for bit, with voxels exactly at,
    just above and just below the floor; slabs of another shape are refused."""
    import pyopencl.array as cla

    from plenocl.reconstruction.schedule import support_of

    rng = np.random.default_rng(sum(shape) + factor)
    coarse = (rng.random(shape) ** 6).astype(np.float32)
    settings = ReconstructionSettings(support=0.3)
    floor = np.float32(0.3 * float(coarse.max()))
    flat = coarse.ravel()  # voxels on the floor's edge: at it is out, above is in
    flat[rng.choice(flat.size, 3, replace=False)] = [
        floor, np.nextafter(floor, np.float32(np.inf)), np.nextafter(floor, np.float32(0))]
    start = support_of(coarse, settings, on_device=cla.to_device(queue, coarse))
    assert start.floor == floor and 0 < start.fraction <= 1
    nz, ny, nx = shape
    binning = LateralBinning(queue)

    def slabs():
        parts = np.array_split(np.full((nz, ny * factor, nx * factor), 7.0, np.float32),
                               min(3, nz))
        return [cla.to_device(queue, np.ascontiguousarray(p)) for p in parts]

    want, got = slabs(), slabs()
    binning.spread_into(start.flat(), factor, want, scale=0.37)
    binning.spread_support(start.on_device, start.floor, start.level, factor, got,
                           scale=0.37)
    assert np.array_equal(np.concatenate([g.get() for g in got]),
                          np.concatenate([w.get() for w in want]))
    assert np.array_equal(start.mask, ndimage.binary_dilation(
        coarse > floor, np.ones((3, 3, 3), bool)))
    with pytest.raises(ValueError, match="does not spread by"):
        binning.spread_support(start.on_device, floor, start.level, factor + 1, got)


@pytest.mark.parametrize("fp64", [True, False])
@pytest.mark.parametrize("shape", [(5, 7, 11), (4, 1, 5), (3, 2, 3), (9, 6, 1), (1, 1, 1),
                                   (3, 100, 2)])
def test_the_support_found_from_the_device_volume_is_the_hosts(queue, shape, fp64):
    """``support_on_device`` (the peak, the grown support's sums in parts and count read
    back, not the volume; the parts made on the device in double precision, or from the
    rows on the host) gives the host's ``support_of`` floor, level and fraction bit for
    bit, with voxels at and beside the floor, on fewer and more rows than parts; the
    level is the support's mean within float32 rounding; no support for a volume without
    light."""
    import pyopencl.array as cla

    from plenocl.reconstruction.schedule import support_of, support_on_device

    rng = np.random.default_rng(sum(shape))
    coarse = (rng.random(shape) ** 6 * 3e3).astype(np.float32)
    settings = ReconstructionSettings(support=0.3)
    floor = np.float32(0.3 * float(coarse.max()))
    flat = coarse.ravel()  # the brightest voxel kept: the floor stays
    chosen = rng.choice(np.flatnonzero(flat < flat.max()), min(3, flat.size - 1),
                        replace=False)
    flat[chosen] = [floor, np.nextafter(floor, np.float32(np.inf)),
                    np.nextafter(floor, np.float32(0))][:len(chosen)]
    if fp64 and not DeviceInfo.probe(queue.device).fp64:
        pytest.skip("the device has no cl_khr_fp64: its parts are made on the host")
    binning = LateralBinning(queue, fp64)
    host = support_of(coarse, settings)
    device = support_on_device(cla.to_device(queue, coarse), settings, binning)
    assert (device.floor, device.level, device.fraction) == (floor, host.level,
                                                             host.fraction)
    keep = ndimage.binary_dilation(coarse > floor, np.ones((3, 3, 3), bool))
    assert host.fraction == np.count_nonzero(keep) / keep.size > 0
    assert host.level == pytest.approx(coarse[keep].astype(np.float64).mean(), rel=1e-6)
    assert device.mask is None and np.array_equal(device.on_device.get(), coarse)
    with pytest.raises(ValueError, match="found on the device"):
        device.flat()
    dark = np.zeros(shape, np.float32)
    assert support_of(dark, settings) is None
    assert support_on_device(cla.to_device(queue, dark), settings, binning) is None


def test_row_parts_add_each_part_in_row_order():
    """The twin of ``support_parts``: part ``p`` is rows ``p, p + parts, ...`` added one
    by one in float64, 0 where a part has no row; the parts hold every row's sum."""
    from plenocl.reconstruction.supersample import row_parts

    rows = np.random.default_rng(3).random(11).astype(np.float32) * 1e3
    got = row_parts(rows, 4)
    want = [float(rows[0]) + float(rows[4]) + float(rows[8]),
            float(rows[1]) + float(rows[5]) + float(rows[9]),
            float(rows[2]) + float(rows[6]) + float(rows[10]),
            float(rows[3]) + float(rows[7])]
    assert got.tolist() == want
    assert row_parts(rows[:2], 4).tolist() == [float(rows[0]), float(rows[1]), 0.0, 0.0]
    assert got.sum() == pytest.approx(rows.astype(np.float64).sum(), rel=1e-15)


def test_the_support_of_a_paper_size_volume_reads_back_its_parts_not_its_rows(queue):
    """A coarse volume of 30,000 rows (a paper-size reconstruction's) gives its support
    with a few kilobytes back, not a peak, a sum and a count per row (360 kB)."""
    import pyopencl.array as cla

    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.opencl.volume import SUMMARY_PARTS
    from plenocl.reconstruction.schedule import support_of, support_on_device
    from plenocl.reconstruction.supersample import SUPPORT_PARTS

    coarse = (np.random.default_rng(4).random((150, 200, 7)) ** 8).astype(np.float32)
    binning = LateralBinning(queue)
    on_device = cla.to_device(queue, coarse)
    settings = ReconstructionSettings(support=0.3)
    with OpenCLProfile() as prof:
        got = support_on_device(on_device, settings, binning)
    back = sum(c.nbytes for c in prof.calls if c.kind == "d2h")
    parts = SUPPORT_PARTS if binning.fp64 else 150 * 200
    assert back <= 24 * SUMMARY_PARTS + 16 * parts
    if binning.fp64:
        assert back < 12 * 150 * 200 / 10
    host = support_of(coarse, settings)
    assert (got.floor, got.level, got.fraction) == (host.floor, host.level, host.fraction)


def test_a_cropped_solver_bins_its_slabs_into_the_full_grid(optics, queue):
    """A solver cropped to a box that starts and ends inside 3 x 3 blocks, on several
    depth slabs, bins on the device to the full grid's binned volume."""
    cam, grid, _ = optics
    fine = Projector(cam, grid.refined(3), queue, max_alloc_bytes=500_000)
    box = (slice(20, 97), slice(4, 41), slice(7, 68))
    sub = Solver(fine.cropped(box), box=box)
    assert len(sub.proj.plan.slabs) > 1
    rng = np.random.default_rng(5)
    host = rng.random(sub.proj.grid.shape).astype(np.float32)
    full = np.zeros(fine.grid.shape, np.float32)
    full[box] = host
    got = sub.binned_to_host(sub.proj.volume_to_device(host), 3, grid.shape, 2.0)
    np.testing.assert_allclose(got, bin_lateral(full * np.float32(2.0), 3), rtol=tol.BINNED,
                               atol=0)
    whole = Solver(fine)
    got = whole.binned_to_host(fine.volume_to_device(full), 3, grid.shape)
    np.testing.assert_allclose(got, bin_lateral(full, 3), rtol=tol.BINNED, atol=0)


@pytest.mark.parametrize("box", [None, (slice(20, 97), slice(4, 41), slice(7, 68))])
def test_the_binned_device_volume_is_the_host_volume_bit_for_bit(optics, queue, box):
    """``Solver.binned_to_device`` (the volume a reconstruction keeps on the device for
    PIV) holds the host volume's values to the bit, cropped or not, over several slabs;
    at factor 1 it is the volume times the scale as NumPy rounds it (no lateral sum)."""
    cam, grid, _ = optics
    fine = Projector(cam, grid.refined(3), queue, max_alloc_bytes=500_000)
    solver = Solver(fine) if box is None else Solver(fine.cropped(box), box=box)
    assert len(solver.proj.plan.slabs) > 1
    host = np.random.default_rng(7).random(solver.proj.grid.shape).astype(np.float32)
    vol = solver.proj.volume_to_device(host)
    dev = solver.binned_to_device(vol, 3, grid.shape, 1.7)
    assert dev.shape == grid.shape and dev.dtype == np.float32 and dev.flags.c_contiguous
    assert np.array_equal(dev.get(), solver.binned_to_host(vol, 3, grid.shape, 1.7))
    full = np.zeros(fine.grid.shape, np.float32)
    full[box or slice(None)] = host
    same = solver.binned_to_device(vol, 1, fine.grid.shape, 1.7).get()
    assert np.array_equal(same, full * np.float32(1.7))


# ---- coarse-to-fine: the image prepared once, the callback over both runs -------------
@pytest.fixture(scope="module")
def scene(optics, queue):
    """A raw image of six particles on the optics' camera."""
    cam = optics[0]
    pos, inten = random_particles(((-1.3, 1.3), (-0.8, 0.8), (-8, 8)), count=6, seed=4,
                                  intensity=2e4)
    return simulate_image(cam, pos, inten, 4000, seed=2, queue=queue, background=20.0)


def test_the_refined_projector_lights_the_lenses_the_coarse_one_does(optics, scene):
    """Same camera, same lit lenses: a coarse-to-fine reconstruction computes them once."""
    cam, grid, proj = optics
    prepared = prepare_image(scene, proj, ReconstructionSettings())
    assert 0 < prepared.lit.mean() < 1
    for f in (2, 3):
        np.testing.assert_array_equal(proj.refined(f).lit_lenses(prepared.image,
                                                                  prepared.threshold),
                                      prepared.lit)


def test_coarse_to_fine_prepares_the_image_once_and_equals_two_separate_runs(
        optics, scene, monkeypatch):
    """One preprocessing, one lit-lens search and one upload of the image for both runs;
    the fine volume is the one of two separate reconstructions (the coarse one, then the
    fine one from its flat support spread on the host), binned on the device: equal to
    the rounding of the start's spreading on the device (one product instead of two
    quotients per sub-voxel), carried through the iterations."""
    cam, grid, proj = optics
    coarse = reconstruct(scene, proj.sampled(COARSE_OVERSAMPLE), iterations=4,
                         supersample=1)
    grown = ndimage.binary_dilation(coarse > 0.05 * coarse.max(), np.ones((3, 3, 3), bool))
    flat = np.where(grown, np.float32(coarse[grown].mean()), np.float32(0))
    fine = reconstruct(scene, proj.refined(2), iterations=3, start=spread_lateral(flat, 2),
                       supersample=1)
    calls = {"_preprocessed": 0, "lit_lenses": 0, "fine": []}

    def counted(name, function):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return function(*args, **kwargs)
        return wrapper

    def binned_to_device(solver, vol, factor, shape, scale=1.0):
        if factor > 1:  # the fine run's sub-voxels (the coarse run's voxels pass too)
            calls["fine"].append(solver.volume_to_host(vol, fine.shape) * np.float32(scale))
        return binned_to_device.__wrapped__(solver, vol, factor, shape, scale)

    binned_to_device.__wrapped__ = Solver.binned_to_device
    monkeypatch.setattr(images_module, "_preprocessed",
                        counted("_preprocessed", images_module._preprocessed))
    monkeypatch.setattr(Projector, "lit_lenses", counted("lit_lenses", Projector.lit_lenses))
    monkeypatch.setattr(Solver, "binned_to_device", binned_to_device)
    uploads, made = [], arrays.buffer_from_host  # where every upload goes
    monkeypatch.setattr(arrays, "buffer_from_host",
                        lambda context, host: uploads.append(np.shape(host))
                        or made(context, host))
    vol, info = reconstruct(scene, proj, iterations=3, supersample=2, coarse_iterations=4,
                            support=0.05, relax=1.0, early_oversample=None, return_info=True)
    assert calls["_preprocessed"] == 1 and calls["lit_lenses"] == 1
    assert uploads.count(scene.shape) == 1  # the image goes to the device once, not per run
    assert grid.shape not in uploads  # the coarse support is found and spread on the device
    assert info.cropped_shape is not None  # the fine run cropped itself before binning
    peak = float(fine.max())
    np.testing.assert_allclose(calls["fine"][0], fine, rtol=tol.ITERATED,
                               atol=tol.ROUNDING * peak)
    np.testing.assert_allclose(vol, bin_lateral(calls["fine"][0], 2), rtol=tol.BINNED, atol=0)


@pytest.mark.parametrize("options", [{"supersample": 2, "coarse_iterations": 3,
                                      "iterations": 3, "support": 0.05},
                                     {"supersample": 1, "iterations": 3}])
def test_a_reconstruction_keeps_its_volume_on_the_device_when_asked(optics, scene,
                                                                    options):
    """``run_reconstruction(keep_for_next_stage=True)``: the volume returned stays on the
    device (a ``DeviceVolume`` of ``info.volume_on_device``, on the projector's context),
    its host copy the volume made without keeping it, to the bit, its share of non-zero
    voxels counted there (coarse-to-fine sub-voxels and plain voxels), with the image
    fit's background-free image; without it (the default, ``reconstruct``'s) no device
    memory and no image is held."""
    from plenocl.reconstruction import run_reconstruction

    proj = optics[2]
    rec = ReconstructionSettings(**options)
    kept, info = run_reconstruction(scene, proj, rec, keep_for_next_stage=True)
    dev = info.volume_on_device
    assert dev.context == proj.queue.context and dev.dtype == np.float32
    assert isinstance(kept, DeviceVolume) and kept.array is dev  # returned on the device
    vol = kept.get()
    assert np.array_equal(dev.get(), vol) and vol.any()
    assert info.active_fraction == np.count_nonzero(vol) / vol.size
    free = info.background_free  # the image fit's: the solver's image, on its device too
    assert free.values.shape == scene.shape and free.on_device.context == proj.queue.context
    assert np.array_equal(free.on_device.get(), free.values) and free.scale > 0
    again, plain = run_reconstruction(scene, proj, rec)
    assert plain.volume_on_device is None and plain.background_free is None
    assert np.array_equal(again, vol)


@pytest.mark.parametrize("crop", [True, False])
def test_the_first_sub_voxel_iterations_run_on_the_early_sampling(optics, scene, crop,
                                                                  monkeypatch):
    """``early_iterations`` of the sub-voxel iterations on the aperture sampled
    ``early_oversample`` times per pixel footprint, from the coarse support; the rest on
    the refined projector from their volume: the same volume as the three runs made
    separately, on the support alone, with every iteration in the info. The early volume
    goes on to the rest on the device, cropped or not (a crop's box placed on the refined
    grid there): no full volume crosses to the host."""
    cam, grid, proj = optics
    kw = dict(supersample=1, relax=1.0, crop=crop)
    coarse = reconstruct(scene, proj.sampled(COARSE_OVERSAMPLE), iterations=4, **kw)
    grown = ndimage.binary_dilation(coarse > 0.05 * coarse.max(), np.ones((3, 3, 3), bool))
    flat = np.where(grown, np.float32(coarse[grown].mean()), np.float32(0))
    fine = proj.refined(2)
    early = reconstruct(scene, fine.sampled(0.6), iterations=2, start=spread_lateral(flat, 2),
                        **kw)
    assert fine.sampled(0.6).n_samples < fine.n_samples / 2
    late = reconstruct(scene, fine, iterations=1, start=early, **kw)
    to_host, binned, whole = [], Solver.binned_to_device, Solver.volume_to_host

    def counted_binned(solver, vol, factor, shape, scale=1.0):  # a run's end, kept
        to_host.append(shape)
        return binned(solver, vol, factor, shape, scale)

    def counted_whole(solver, vol, shape):  # a run's end handed on through the host
        to_host.append(shape)
        return whole(solver, vol, shape)

    monkeypatch.setattr(Solver, "binned_to_device", counted_binned)
    monkeypatch.setattr(Solver, "volume_to_host", counted_whole)
    vol, info = reconstruct(scene, proj, iterations=3, supersample=2, coarse_iterations=4,
                            support=0.05, relax=1.0, early_iterations=2, early_oversample=0.6,
                            crop=crop, return_info=True)
    assert info.iterations == 3 and len(info.residuals) == 3 and not info.stopped
    assert not vol[~grown].any()
    assert fine.grid.shape not in to_host  # handed over on the device
    peak = float(late.max())
    np.testing.assert_allclose(vol, bin_lateral(late, 2), rtol=tol.ITERATED,
                               atol=tol.ROUNDING * 4 * peak)


def test_the_callback_counts_the_coarse_iterations_then_the_fine_ones(optics, scene):
    cam, grid, proj = optics
    settings = ReconstructionSettings(iterations=2, supersample=2, coarse_iterations=3,
                                      support=0.05)
    assert settings.total_iterations == 5
    voxels = ReconstructionSettings(iterations=2, coarse_iterations=3, supersample=1)
    assert voxels.total_iterations == 2  # no coarse run on the voxels themselves
    seen = []
    vol, info = reconstruct(scene, proj, settings=settings, return_info=True,
                            callback=lambda it, resid: seen.append(it))
    assert seen == [1, 2, 3, 4, 5] and info.iterations == 2
    # stopped in the coarse run: the coarse volume; in the fine run: the fine one so far
    for stop, fine_done in ((2, None), (4, 1)):
        seen.clear()
        vol, info = reconstruct(scene, proj, settings=settings, return_info=True,
                                callback=lambda it, resid, s=stop: seen.append(it) or it < s)
        assert seen == list(range(1, stop + 1)) and vol.shape == grid.shape
        assert info.supersample == (1 if fine_done is None else 2)
        assert info.iterations == (stop if fine_done is None else fine_done)


@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 5, 2), (7, 3, 9), (12, 11, 10)])
def test_box_dilation_is_scipys(shape):
    """The coarse support's growth by one voxel is SciPy's binary dilation by the
    3 x 3 x 3 box (nothing beyond the faces), on masks touching every face."""
    rng = np.random.default_rng(sum(shape))
    for share in (0.02, 0.3):
        mask = rng.random(shape) < share
        mask[(0,) * 3] = mask[tuple(n - 1 for n in shape)] = True
        want = ndimage.binary_dilation(mask, np.ones((3, 3, 3), bool))
        assert np.array_equal(box_dilated(mask), want)
    assert not box_dilated(np.zeros(shape, bool)).any()
