"""3-D PIV (plenocl.piv and its parts) against synthetic flows with known displacement.

Accuracy limits are the issue's (interior RMS error: 0.05 voxel uniform, 0.10 solid-body
rotation, 0.15 Lamb-Oseen; >= 95 % valid) on awkward, non-cubic volumes, two seeds each;
the flows' parameters (displacement, axes, centres) are drawn from the seed.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from vtkfiles import read_appended

from plenocl import flows
from plenocl import vectorfield as fieldio
from plenocl.piv import PIVResult, piv3d
from plenocl.piv.correlation import correlate, fit_peaks, window_fraction, window_grid
from plenocl.piv.interpolate import resample
from plenocl.piv.validation import nan_median, normalized_median_test, replace_outliers

CASES = [((70, 90, 80), 20251), ((64, 72, 66), 777)]   # (nz, ny, nx), seed
LIMITS = {"uniform": 0.05, "rotation": 0.10, "oseen": 0.15}
MARGIN = 16   # interior: window centres at least this far (voxels) from every face


def make_flow(kind: str, shape, seed: int):
    """A flow in voxel units whose parameters come from the seed."""
    rng = np.random.default_rng(seed + 1000)
    nz, ny, nx = shape
    centre = np.array([(nx - 1) / 2, (ny - 1) / 2, (nz - 1) / 2]) + rng.uniform(-4, 4, 3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "uniform":
        return flows.Uniform(tuple(rng.uniform(-3.0, 3.0, 3)))
    if kind == "rotation":   # ~3 voxels at half the smallest size from the axis
        return flows.SolidBodyRotation(tuple(axis * 3.0 / (0.5 * min(shape))), tuple(centre))
    # core radius 16 voxels, 3 voxels peak swirl: the core turns 0.29 rad between volumes
    return flows.LambOseen.from_peak_velocity(3.0, 16.0, tuple(centre), tuple(axis))


def truth(res: PIVResult, flow) -> np.ndarray:
    """Reference displacement ``(3, nz', ny', nx')`` at the window centres (mid-time)."""
    zz, yy, xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")
    d = flows.centred_displacement(np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]),
                                   flow, 1.0)
    return d.T.reshape((3, *res.shape))


def interior(res: PIVResult, shape, margin: float = MARGIN) -> np.ndarray:
    zz, yy, xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")
    inside = np.ones(res.shape, bool)
    for c, n in zip((zz, yy, xx), shape):
        inside &= (c >= margin) & (c <= n - 1 - margin)
    return inside


_RUNS: dict = {}


def run_case(kind: str, shape, seed: int, **kwargs):
    """piv3d on a rendered pair (cached across tests); returns (result, error, interior)."""
    key = (kind, shape, seed, tuple(sorted(kwargs.items())))
    if key not in _RUNS:
        flow = make_flow(kind, shape, seed)
        pair = flows.volume_pair(shape, flow, density=0.004, sigma=1.0, seed=seed)
        res = piv3d(pair.vol_a, pair.vol_b, **kwargs)
        err = np.stack([res.u, res.v, res.w]) - truth(res, flow)
        _RUNS[key] = res, err, interior(res, shape)
    return _RUNS[key]


@pytest.mark.parametrize("shape,seed", CASES)
@pytest.mark.parametrize("kind", ["uniform", "rotation", "oseen"])
def test_accuracy_and_valid_fraction(kind, shape, seed):
    res, err, inner = run_case(kind, shape, seed)
    assert inner.sum() >= 8
    rms = np.sqrt(np.mean(np.sum(err[:, inner] ** 2, axis=0)))
    assert rms <= LIMITS[kind], f"{kind}: interior RMS error {rms:.4f} voxel"
    assert res.valid[inner].mean() >= 0.95
    assert np.all(np.isfinite(err))
    assert res.u.shape == (len(res.z), len(res.y), len(res.x))


@pytest.mark.parametrize("shape,seed", CASES)
@pytest.mark.parametrize("kind", ["uniform", "rotation"])
def test_unbiased(kind, shape, seed):
    _, err, inner = run_case(kind, shape, seed)
    assert np.abs(err[:, inner].mean(axis=1)).max() <= 0.01


def test_large_displacement_found_by_padded_first_pass():
    shape = (64, 72, 66)
    flow = flows.Uniform((8.6, -5.3, 3.2))   # ~ a fifth of the 48-voxel first window
    pair = flows.volume_pair(shape, flow, seed=91)
    res = piv3d(pair.vol_a, pair.vol_b)
    err = np.stack([res.u, res.v, res.w]) - truth(res, flow)
    assert np.sqrt(np.mean(np.sum(err**2, axis=0))) <= 0.05
    assert res.valid.mean() >= 0.95


def test_cubic_deformation_beats_trilinear():
    """Trilinear deformation biases sub-voxel shifts (docs/design.md §7); cubic B-splines do not."""
    shape = (64, 64, 64)
    flow = flows.Uniform((1.5, -0.5, 2.5))   # half-voxel parts: the worst case
    pair = flows.volume_pair(shape, flow, seed=404)
    bias = {}
    for order in (1, 3):
        res = piv3d(pair.vol_a, pair.vol_b, deform_order=order)
        err = np.stack([res.u, res.v, res.w]) - truth(res, flow)
        bias[order] = np.abs(err[:, interior(res, shape)].mean(axis=1)).max()
    assert bias[3] <= 0.01
    assert bias[1] >= 3 * bias[3]


def _rotation_field(shape=(7, 8, 9)):
    zz, yy, xx = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
    return np.stack([0.3 * xx - 0.2 * yy, 0.5 * xx + 0.1 * zz, -0.4 * yy + 0.25 * zz])


@pytest.mark.parametrize("shape", [(26, 2), (26, 3, 4, 5, 6), (7, 40)])
def test_nan_median_is_numpys_nanmedian_bit_for_bit(shape):
    """The validation's median of the neighbours is NumPy's ``nanmedian`` exactly: odd
    and even counts of finite values, columns without any (NaN, no warning), ties."""
    rng = np.random.default_rng(len(shape))
    values = np.round(rng.normal(size=shape), 1)  # ties
    values[rng.random(shape) < 0.3] = np.nan
    values[:, 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NumPy's all-NaN slice warning
        want = np.nanmedian(values, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = nan_median(values)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.isnan(got[0]).all() and np.isfinite(got[1:]).any()


def test_median_test_flags_injected_outliers_and_replacement_restores_them():
    rng = np.random.default_rng(8)
    clean = _rotation_field() + rng.normal(0, 0.02, (3, 7, 8, 9))
    field = clean.copy()
    bad = np.zeros(clean.shape[1:], bool)
    spots = [(0, 0, 0), (6, 7, 8), (0, 4, 4), (3, 0, 5), (3, 4, 8), (2, 2, 2), (5, 5, 3)]
    for spot in spots:     # corners, faces and interior
        bad[spot] = True
        field[(slice(None), *spot)] += rng.choice([-1, 1], 3) * rng.uniform(1.0, 4.0, 3)
    flags = normalized_median_test(field, eps=0.1, threshold=2.0)
    assert np.all(flags[bad])
    assert flags[~bad].mean() <= 0.02
    fixed = replace_outliers(field, flags)
    assert np.abs(fixed[:, bad] - clean[:, bad]).max() < 0.3
    assert np.array_equal(fixed[:, ~flags], field[:, ~flags])


def test_median_test_needs_no_nan_padding_in_a_gradient():
    """Odd-reflection padding: a linear field has no outliers, faces and corners included."""
    assert not normalized_median_test(5.0 * _rotation_field()).any()


def test_replace_outliers_fills_clusters_and_ignores_nothing_else():
    field = _rotation_field()
    bad = np.zeros(field.shape[1:], bool)
    bad[2:5, 3:6, 3:6] = True
    filled = replace_outliers(np.where(bad, 99.0, field), bad)
    assert np.all(np.isfinite(filled))
    assert np.abs(filled - field)[:, bad].max() < 1.5   # neighbour medians of a ramp
    assert np.array_equal(filled[:, ~bad], field[:, ~bad])


def test_corrupted_region_is_flagged_and_replaced():
    shape = (64, 72, 66)
    flow = make_flow("rotation", shape, 5)
    pair = flows.volume_pair(shape, flow, seed=5)
    noise = flows.volume_pair(shape, flows.Uniform((0.0, 0.0, 0.0)), seed=6).vol_b
    vol_b = pair.vol_b.copy()
    block = (slice(22, 42), slice(26, 46), slice(23, 43))
    vol_b[block] = noise[block]          # uncorrelated particles in a 20^3 block
    res = piv3d(pair.vol_a, vol_b)
    zz, yy, xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")
    core = (abs(zz - 31.5) <= 4) & (abs(yy - 35.5) <= 4) & (abs(xx - 32.5) <= 4)
    assert core.any() and not res.valid[core].any()
    err = np.linalg.norm(np.stack([res.u, res.v, res.w]) - truth(res, flow), axis=0)
    assert err[core].max() < 1.0         # replaced from the valid surroundings
    half = res.window[0] / 2
    clear = np.zeros(res.shape, bool)     # windows that do not touch the block
    for c, sl in zip((zz, yy, xx), block):
        clear |= (c + half <= sl.start) | (c - half >= sl.stop)
    assert clear.sum() > 50 and res.valid[clear].mean() >= 0.95


def test_mask_excludes_windows():
    shape = (64, 72, 66)
    flow = make_flow("uniform", shape, 12)
    pair = flows.volume_pair(shape, flow, seed=12)
    mask = np.zeros(shape, bool)
    mask[:, :, 44:] = True               # a "wall" on the high-x side
    res = piv3d(pair.vol_a, pair.vol_b, mask=mask)
    xx = np.meshgrid(res.z, res.y, res.x, indexing="ij")[2]
    # windows more than a quarter in the wall: their centre within a quarter window of it
    assert np.array_equal(res.masked, xx > 44 - res.window[2] / 4)
    assert np.isnan(res.u[res.masked]).all() and not res.valid[res.masked].any()
    err = np.stack([res.u, res.v, res.w]) - truth(res, flow)
    keep = interior(res, shape) & (xx < 30)
    assert np.sqrt(np.mean(np.sum(err[:, keep] ** 2, axis=0))) <= 0.05


@pytest.mark.parametrize("args,kwargs,error,match", [
    ((np.zeros((4, 4)), np.zeros((4, 4))), {}, ValueError, "3-D volume"),
    (("ok", "short"), {}, ValueError, "same shape"),
    (("nan", None), {}, ValueError, "NaN/Inf"),
    ((np.zeros((40, 40, 40)), np.zeros((40, 40, 40))), {}, ValueError, "constant"),
    (("ok", None), {"windows": (48, 24)}, ValueError, "larger than the volume"),
    (("ok", None), {"windows": (32, 6)}, ValueError, ">= 8"),
    (("ok", None), {"overlaps": 1.0}, ValueError, r"\[0, 1\)"),
    (("ok", None), {"overlaps": (0.5, 0.5, 0.5)}, ValueError, "must match windows"),
    (("ok", None), {"deform_order": 2}, ValueError, "deform_order"),
    (("ok", None), {"mask": np.zeros((40, 40, 40))}, TypeError, "boolean"),
    (("ok", None), {"mask": np.zeros((4, 4, 4), bool)}, ValueError, "mask must have"),
    (("ok", None), {"final_iterations": 0}, ValueError, "final_iterations"),
    ((np.ones((40, 40, 40), complex), None), {}, TypeError, "real numbers"),
])
def test_input_errors_say_what_to_fix(args, kwargs, error, match):
    vol = flows.render_particles((40, 40, 40), np.random.default_rng(0).random((60, 3)) * 40)
    a, b = args
    if isinstance(a, str):
        a = vol.copy()
        if args[0] == "nan":
            a[3, 4, 5] = np.nan
    b = {None: vol, "short": vol[:, :, :-1]}.get(b, b) if not isinstance(b, np.ndarray) else b
    with pytest.raises(error, match=match):
        piv3d(a, b, **({"windows": (32, 24)} | kwargs))


def _rotation_result(omega_z: float, step: int = 4) -> PIVResult:
    """A PIVResult holding the exact solid-body rotation about z (voxels per dt)."""
    x, y, z = (np.arange(n) * step + 10.0 for n in (9, 8, 5))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    ones = np.ones(zz.shape, bool)
    return PIVResult(x=x, y=y, z=z, u=-omega_z * (yy - 20), v=omega_z * (xx - 30),
                     w=np.zeros(zz.shape), valid=ones, peak_ratio=ones * 5.0,
                     outlier=~ones, masked=~ones, window=(24, 24, 24))


def test_velocity_vorticity_and_q_criterion_in_physical_units():
    res = _rotation_result(0.02)
    dt, size = 2e-4, 0.05                       # s, mm (isotropic voxels)
    u, v, w = res.velocity(size, dt)
    assert np.allclose(u, res.u * size * 1e-3 / dt) and np.allclose(w, 0)
    omega = 0.02 / dt                           # rad/s
    wx, wy, wz = res.vorticity(size, dt)
    assert np.allclose(wz, 2 * omega) and np.allclose(wx, 0) and np.allclose(wy, 0)
    assert np.allclose(res.q_criterion(size, dt), omega**2)   # pure rotation: Q = Omega^2
    assert np.allclose(res.vorticity()[2], 2 * 0.02)            # per dt, voxel units
    x_mm, y_mm, z_mm = res.positions_mm((0.1, 0.05, 0.025), origin_mm=(1.0, 2.0, 3.0))
    assert np.allclose(x_mm, 3.0 + 0.025 * res.x) and np.allclose(z_mm, 1.0 + 0.1 * res.z)


def test_anisotropic_voxels_scale_each_component():
    res = _rotation_result(0.01)
    u, v, _ = res.velocity((0.3, 0.2, 0.1), 1e-3)
    assert np.allclose(u, res.u * 0.1 * 1e-3 / 1e-3) and np.allclose(v, res.v * 0.2)
    with pytest.raises(ValueError, match="dt"):
        res.velocity(0.1, 0.0)
    with pytest.raises(ValueError, match="voxel_size_mm"):
        res.velocity(-1.0, 1e-3)


def _gaussian_planes(shifts: np.ndarray, size: int = 16, width: float = 1.3) -> np.ndarray:
    idx = np.arange(size)
    planes = []
    for s in shifts:   # circular: peak at s mod size
        axes = [np.exp(-0.5 * ((((idx - c) + size / 2) % size - size / 2) / width) ** 2)
                for c in s]
        planes.append(axes[0][:, None, None] * axes[1][None, :, None] * axes[2])
    return np.array(planes, np.float32)


def test_gaussian_peak_fit_is_exact_for_gaussian_peaks():
    shifts = np.random.default_rng(3).uniform(-6, 6, (20, 3))
    disp, peak, ratio = fit_peaks(_gaussian_planes(shifts))
    assert np.allclose(disp.T, shifts, atol=2e-4)
    assert np.all(peak > 0.7) and np.all(ratio > 1)


def test_peak_fit_guards_non_positive_neighbours():
    corr = np.full((1, 8, 8, 8), -0.2, np.float32)
    corr[0, 2, 3, 1] = 1.0
    corr[0, 3, 3, 1] = 0.4          # one positive neighbour, the rest negative
    disp, _, _ = fit_peaks(corr)
    assert np.all(np.isfinite(disp)) and np.all(np.abs(disp[:, 0] - [2, 3, 1]) <= 0.5)
    assert disp[0, 0] > 2.0         # pulled towards the larger neighbour


def test_correlate_padded_window_finds_a_large_shift():
    rng = np.random.default_rng(4)
    pos = rng.random((250, 3)) * 64
    d = np.array([9.3, -7.6, 4.2])
    a = flows.render_particles((64, 64, 64), pos)
    b = flows.render_particles((64, 64, 64), pos + d)
    grid = window_grid((64, 64, 64), (48, 48, 48), 0.5)
    corr = correlate(a, b, grid, pad=True)
    assert np.allclose(corr.displacement[:, 0, 0, 0], d[::-1], atol=0.35)
    assert corr.signal.all() and corr.peak.min() > 0.3


def test_window_grid_is_centred_and_window_fraction_counts():
    grid = window_grid((70, 90, 80), (24, 24, 24), 0.75)
    for centres, n in zip(grid.centres, (70, 90, 80)):
        assert centres[0] - 11.5 >= 0 and centres[-1] + 12.5 <= n
        assert abs((centres[0] - 11.5) - (n - 1 - centres[-1] - 11.5)) <= 1
    mask = np.random.default_rng(1).random((70, 90, 80)) > 0.7
    frac = window_fraction(mask, grid)
    k = (2, 5, 3)
    lo = [o + s * i for o, s, i in zip(grid.offset, grid.step, k)]
    assert frac[k] == pytest.approx(mask[lo[0]:lo[0] + 24, lo[1]:lo[1] + 24,
                                         lo[2]:lo[2] + 24].mean())


@pytest.mark.parametrize("kind", ["linear", "cubic"])
def test_predictor_extrapolates_linearly(kind):
    """A linear field is reproduced exactly, also beyond the outermost vectors."""
    src = (np.arange(4) * 6.0 + 11.5, np.arange(5) * 6.0 + 11.5, np.arange(6) * 6.0 + 11.5)
    zz, yy, xx = np.meshgrid(*src, indexing="ij")
    field = np.stack([0.1 * xx - 0.05 * zz + 1, 0.02 * yy, -0.03 * xx + 0.07 * yy])
    target = tuple(np.arange(n, dtype=float) for n in (40, 50, 60))
    out = resample(field, src, target, kind)
    tz, ty, tx = np.meshgrid(*target, indexing="ij")
    expect = np.stack([0.1 * tx - 0.05 * tz + 1, 0.02 * ty, -0.03 * tx + 0.07 * ty])
    assert np.allclose(out, expect, atol=1e-9)


# ----------------------------------------------------------------------------- field files

@pytest.fixture(scope="module")
def small_result() -> PIVResult:
    res = _rotation_result(0.02)
    res.valid[1, 2, 3] = False
    res.outlier[1, 2, 3] = True
    rng = np.random.default_rng(1)
    for comp, scale in (("u", 0.05), ("v", 0.04), ("w", 0.2)):
        setattr(res, f"sigma_{comp}", np.where(res.valid, scale * rng.random(res.shape),
                                               np.nan))
    return res


def test_save_npz_round_trip(tmp_path: Path, small_result):
    path = fieldio.save_field(tmp_path / "f.npz", small_result, voxel_size_mm=(0.1, 0.05, 0.05),
                              origin_mm=(1.0, 2.0, 3.0), dt=2e-4)
    back, arrays = fieldio.read_npz(path)
    for name in ("x", "y", "z", "u", "v", "w", "valid", "outlier", "masked", "peak_ratio",
                 "sigma_u", "sigma_v", "sigma_w"):
        assert np.array_equal(getattr(back, name), getattr(small_result, name),
                              equal_nan=True), name
    sigma = np.stack([small_result.sigma_u, small_result.sigma_v, small_result.sigma_w])
    assert np.isfinite(sigma[:, small_result.valid]).mean() > 0.9
    assert np.isnan(sigma[:, ~small_result.valid]).all()
    np.testing.assert_allclose(arrays["velocity_uncertainty"][0],
                               small_result.sigma_u * 0.05 * 1e-3 / 2e-4)
    assert np.allclose(arrays["velocity"], np.stack(small_result.velocity((0.1, .05, .05), 2e-4)))
    assert np.allclose(arrays["vorticity"][2], 2 * 0.02 / 2e-4)
    assert arrays["dt"] == 2e-4 and np.allclose(arrays["x_mm"], 3.0 + 0.05 * small_result.x)
    assert [p.name for p in tmp_path.iterdir()] == ["f.npz"]   # no temporary left


def test_save_vti_layout_is_x_fastest_in_mm(tmp_path: Path, small_result):
    res = small_result
    path = fieldio.save_field(tmp_path / "f.vti", res, voxel_size_mm=(0.1, 0.05, 0.025),
                              origin_mm=(1.0, 2.0, 3.0), dt=1e-3)
    attrs, arrays = read_appended(path)
    nz, ny, nx = res.shape
    assert attrs["WholeExtent"].split() == ["0", str(nx - 1), "0", str(ny - 1), "0", str(nz - 1)]
    assert np.allclose([float(s) for s in attrs["Origin"].split()],
                       [3.0 + 0.025 * res.x[0], 2.0 + 0.05 * res.y[0], 1.0 + 0.1 * res.z[0]])
    assert np.allclose([float(s) for s in attrs["Spacing"].split()], [0.1, 0.2, 0.4])
    valid, _ = arrays["valid"]
    assert np.array_equal(valid.reshape(res.shape), res.valid.astype(np.uint8))
    disp, ncomp = arrays["displacement_voxels"]
    assert ncomp == 3
    assert np.allclose(disp.reshape((*res.shape, 3)), np.stack([res.u, res.v, res.w], -1))
    assert "velocity_m_per_s" in arrays and "vorticity_per_s" in arrays
    sigma, ncomp = arrays["displacement_uncertainty_voxels"]
    assert ncomp == 3 and "velocity_uncertainty_m_per_s" in arrays
    np.testing.assert_array_equal(sigma.reshape((*res.shape, 3))[..., 2], res.sigma_w)
    assert [p.name for p in tmp_path.iterdir()] == ["f.vti"]


def test_save_field_takes_the_volume_grid(tmp_path: Path, small_result):
    from plenocl import Grid

    grid = Grid(shape=(60, 50, 70), x=(-7.0, 7.0), y=(-5.0, 5.0), z=(10.0, 16.0))  # mm
    _, arrays = fieldio.read_npz(fieldio.save_field(tmp_path / "g.npz", small_result,
                                                    grid=grid, dt=1e-3))
    dz, dy, dx = grid.spacing
    assert np.allclose(arrays["voxel_size_mm_xyz"], grid.spacing[::-1])   # (x, y, z)
    assert np.allclose(arrays["x_mm"], -7.0 + (small_result.x + 0.5) * dx)   # voxel centres
    assert np.allclose(arrays["z_mm"], 10.0 + (small_result.z + 0.5) * dz)
    assert np.allclose(arrays["velocity"][1], small_result.v * dy * 1e-3 / 1e-3)


def test_rotated_grid_fields_are_written_in_object_space(tmp_path: Path, small_result):
    """On a grid turned by 10 degrees (a rotated array's lens-row frame) the stored
    velocity and vorticity are object-space vectors: the grid-axis ones turned by 10
    degrees, same magnitudes; the displacement stays along the grid's axes."""
    from plenocl import Grid

    kw = dict(shape=(60, 50, 70), x=(-7.0, 7.0), y=(-5.0, 5.0), z=(10.0, 16.0))
    flat = fieldio.field_arrays(small_result, Grid(**kw).spacing, dt=1e-3)
    _, turned = fieldio.read_npz(fieldio.save_field(
        tmp_path / "r.npz", small_result, grid=Grid(**kw, rotation_deg=10.0), dt=1e-3))
    assert float(turned["rotation_deg"]) == 10.0
    np.testing.assert_array_equal(turned["displacement"], flat["displacement"])
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    for key in ("velocity", "vorticity"):
        a, b = flat[key], turned[key]
        np.testing.assert_allclose(b[0], c * a[0] - s * a[1], atol=1e-12)
        np.testing.assert_allclose(b[1], s * a[0] + c * a[1], atol=1e-12)
        np.testing.assert_allclose(b[2], a[2])
        np.testing.assert_allclose(np.linalg.norm(b, axis=0), np.linalg.norm(a, axis=0))
    a, b = flat["velocity_uncertainty"], turned["velocity_uncertainty"]   # independent errors
    np.testing.assert_allclose(b[0], np.hypot(c * a[0], s * a[1]))
    np.testing.assert_allclose(b[2], a[2])


def test_fields_describe_themselves(tmp_path: Path, small_result):
    """Units and axis order travel with the arrays; the vector grid's origin and spacing
    are stored as the .vti file gives them, (x, y, z)."""
    import json

    from plenocl import Grid

    grid = Grid(shape=(60, 50, 70), x=(-7.0, 7.0), y=(-5.0, 5.0), z=(10.0, 16.0))
    _, arrays = fieldio.read_npz(fieldio.save_field(tmp_path / "m.npz", small_result,
                                                    grid=grid, dt=1e-3))
    meta = json.loads(str(arrays["metadata"]))
    assert meta["units"]["velocity"] == "m s-1" and meta["units"]["x_mm"] == "mm"
    assert "every per-axis triple (x, y, z)" in meta["axes"]
    assert arrays["vector_origin_mm_xyz"][0] == pytest.approx(arrays["x_mm"][0])
    assert arrays["vector_origin_mm_xyz"][2] == pytest.approx(arrays["z_mm"][0])
    assert arrays["vector_spacing_mm_xyz"][1] == pytest.approx(np.diff(arrays["y_mm"][:2])[0])


def test_save_h5(tmp_path: Path, small_result):
    import h5py
    fieldio.save_field(tmp_path / "f.h5", small_result)
    with h5py.File(tmp_path / "f.h5") as fh:
        assert np.array_equal(fh["displacement"][0], small_result.u)
        assert "velocity" not in fh and "vorticity" in fh
        assert fh["displacement"].attrs["units"] == "voxel" and "z slowest" in fh.attrs["axes"]
        assert fh["displacement_uncertainty"].attrs["units"] == "voxel"
        np.testing.assert_array_equal(fh["displacement_uncertainty"][1], small_result.sigma_v)


def test_failed_write_keeps_the_old_file(tmp_path: Path, small_result, monkeypatch):
    path = tmp_path / "f.npz"
    path.write_bytes(b"old")

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError, match="disk full"):
        fieldio.save_field(path, small_result)
    assert path.read_bytes() == b"old" and len(list(tmp_path.iterdir())) == 1


def test_save_field_rejects_unknown_extension(tmp_path: Path, small_result):
    with pytest.raises(ValueError, match=r"\.vti .*\.dat .*\.csv"):
        fieldio.save_field(tmp_path / "f.xyz", small_result)


# ----------------------------------------------------------------------------- slow checks

@pytest.mark.slow
@pytest.mark.parametrize("kind", ["uniform", "rotation", "oseen"])
def test_accuracy_larger_volume(kind):
    shape, seed = (80, 96, 128), 4242
    res, err, inner = run_case(kind, shape, seed)
    rms = np.sqrt(np.mean(np.sum(err[:, inner] ** 2, axis=0)))
    assert rms <= LIMITS[kind] and res.valid[inner].mean() >= 0.95


@pytest.mark.slow
def test_boundary_layer_profile_is_recovered():
    shape = (64, 96, 128)
    tbl = flows.TurbulentBoundaryLayer(u_inf=6.0, delta=80.0, re_tau=1000.0, wall_y=-8.0,
                                       x_range=(0, 128), z_range=(0, 64), seed=3)
    pair = flows.volume_pair(shape, tbl, seed=3)
    res = piv3d(pair.vol_a, pair.vol_b)
    err = np.stack([res.u, res.v, res.w]) - truth(res, tbl)
    inner = interior(res, shape)
    assert np.sqrt(np.mean(np.sum(err[:, inner] ** 2, axis=0))) <= 0.15
    profile = res.u.mean(axis=(0, 2))        # the paper's spatially averaged profile
    expect = truth(res, tbl)[0].mean(axis=(0, 2))
    assert np.abs(profile - expect).max() < 0.05


def test_default_windows_fit_the_volume():
    """No windows given: 48, 32, 24 cut per axis to what the volume holds (the README's
    20-deep grids), a larger first window for a large expected displacement, and a clear
    error for a volume thinner than 8 voxels."""
    from plenocl.piv import auto_windows

    assert auto_windows((20, 40, 40)) == ((16, 40, 40), (16, 32, 32), (16, 24, 24))
    assert auto_windows((150, 200, 300)) == ((48, 48, 48), (32, 32, 32), (24, 24, 24))
    assert auto_windows((150, 200, 300), max_displacement=15)[0] == (64, 64, 64)
    with pytest.raises(ValueError, match="no 8-voxel window"):
        auto_windows((5, 40, 40))
    rng = np.random.default_rng(0)
    vol = np.zeros((20, 40, 40), np.float32)
    vol[rng.integers(0, 20, 300), rng.integers(0, 40, 300), rng.integers(0, 40, 300)] = 1.0
    from scipy import ndimage

    vol = ndimage.gaussian_filter(vol, 1.0)
    res = piv3d(vol, np.roll(vol, 2, axis=2))
    assert res.window == (16, 24, 24)
    assert np.nanmedian(res.u[res.valid]) == pytest.approx(2.0, abs=0.05)


def test_likely_mistakes_warn(small_result):
    """dt typed in microseconds and windows that grow from pass to pass."""
    with pytest.warns(UserWarning, match="dt = 175 s .* 175e-6"):
        small_result.velocity(0.1, 175)
    vol = np.random.default_rng(1).random((24, 24, 24)).astype(np.float32)
    with pytest.warns(UserWarning, match="larger than pass 1's"):
        piv3d(vol, vol, windows=(16, 24), final_iterations=1)


def test_default_windows_hold_enough_particles():
    """Sparse volumes get larger final windows (about 10 particles each); the count comes
    from the volume's peaks."""
    from plenocl.piv import MIN_PARTICLES_PER_WINDOW, auto_windows, count_particles

    shape = (150, 66, 95)
    sparse = auto_windows(shape, particles=250)
    final = sparse[-1]
    assert 250 * np.prod(final) / np.prod(shape) >= MIN_PARTICLES_PER_WINDOW
    assert all(a >= b for a, b in zip(sparse[0], final))
    assert auto_windows(shape, particles=20000) == auto_windows(shape)
    vol = np.zeros((40, 40, 40), np.float32)
    rng = np.random.default_rng(3)
    vol[2::4, 2::4, 2::4] = rng.uniform(0.5, 1.0, (10, 10, 10))  # separated peaks
    vol[2::4, 2::4, 2::4][rng.random((10, 10, 10)) < 0.5] = 0.0
    assert count_particles(vol) == int((vol > 0).sum())


def test_a_volume_too_thin_for_three_vector_layers_is_said_with_the_fix():
    """The README's old path: a 16-voxel-deep volume gives one layer of vectors in
    depth (no gradient, all-NaN peak ratios) and used to say nothing."""
    import warnings

    from plenocl.opencl.device import DeviceFallbackWarning

    rng = np.random.default_rng(0)
    a = (rng.random((16, 40, 40)) > 0.995).astype(np.float32)
    b = np.roll(a, 1, axis=2)
    with pytest.warns(UserWarning, match=r"give 1 x 3 x 3 vectors .* fewer than 3 along z.*"
                                         r"depth_voxel_mm"):
        res = piv3d(a, b)
    assert res.u.shape[0] == 1
    deep = np.concatenate([a, np.roll(a, 5, 1), np.roll(a, 9, 2)])  # 48 voxels deep
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        warnings.simplefilter("ignore", DeviceFallbackWarning)  # which device, not PIV's
        assert piv3d(deep, np.roll(deep, 1, axis=2)).u.shape[0] >= 3


def test_vectors_beside_a_mask_are_not_pulled_to_zero():
    """A wall (the mask) fixed in both volumes: the final windows it covers by more than a
    quarter are left out, and the others beside it keep the displacement across it (the
    zeroed wall correlated at zero displacement: 1.03 of 1.3 voxels, valid, at 46 %)."""
    pair = flows.volume_pair((48, 48, 48), flows.Uniform((1.3, -0.7, 0.4)), density=0.01,
                             seed=1)   # (u, v, w)
    mask = np.zeros((48, 48, 48), bool)
    mask[:, :, 25:] = True
    for correlation in ("auto", "fft"):
        res = piv3d(pair.vol_a, pair.vol_b, queue=False, mask=mask, correlation=correlation)
        beside = res.valid & (np.abs(res.x - 25)[None, None, :] < res.window[2] / 2)
        assert beside.sum() >= 20
        assert abs(res.u[beside].mean() - 1.3) < 0.05, res.u[beside].mean()


def test_displacements_beyond_the_first_windows_are_said():
    """A displacement the first windows cannot hold gave valid-looking wrong vectors in
    silence (u = 14 in windows of 16: every valid vector wrong); a small one says
    nothing."""
    far = flows.volume_pair((48, 48, 48), flows.Uniform((0.0, 0.0, 14.0)), density=0.01,
                            seed=2)
    with pytest.warns(UserWarning, match=r"beyond a quarter of the window.*larger first"):
        piv3d(far.vol_a, far.vol_b, windows=(16, 16), queue=False)
    near = flows.volume_pair((48, 48, 48), flows.Uniform((0.4, -0.7, 1.3)), density=0.01,
                             seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        piv3d(near.vol_a, near.vol_b, windows=(16, 16), queue=False)


def test_a_field_without_a_valid_vector_is_said():
    pair = flows.volume_pair((40, 40, 40), flows.Uniform((0.4, -0.7, 1.3)), density=0.01,
                             seed=3)
    with pytest.warns(UserWarning, match="no vector passed validation"):
        res = piv3d(pair.vol_a, pair.vol_b, queue=False, min_peak_ratio=100.0)
    assert not res.valid.any()
