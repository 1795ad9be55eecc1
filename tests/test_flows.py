"""Synthetic flows, particle displacement and volume rendering (plenocl.flows)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import erf

from plenocl import flows


def _divergence(flow, points: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference divergence and the Frobenius norm of the velocity gradient."""
    grad = np.zeros((len(points), 3, 3))
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        grad[:, :, j] = (flow(points + step) - flow(points - step)) / (2 * h)
    return np.trace(grad, axis1=1, axis2=2), np.linalg.norm(grad, axis=(1, 2))


def test_uniform_and_input_checks():
    flow = flows.Uniform((0.5, -1.0, 2.0))
    out = flow(np.random.default_rng(0).random((7, 3)))
    assert out.shape == (7, 3)
    assert np.all(out == [0.5, -1.0, 2.0])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        flow(np.zeros((4, 2)))


def test_solid_body_rotation_is_rigid():
    rng = np.random.default_rng(1)
    omega = rng.normal(size=3)
    centre = rng.normal(size=3)
    flow = flows.SolidBodyRotation(tuple(omega), tuple(centre))
    p = rng.normal(size=(50, 3)) * 10
    u = flow(p)
    assert np.allclose(np.einsum("ij,ij->i", u, p - centre), 0, atol=1e-9)   # u ⟂ r
    assert np.allclose(np.einsum("ij,j->i", u, omega), 0, atol=1e-9)         # u ⟂ omega
    div, _ = _divergence(flow, p, 1e-3)
    assert np.allclose(div, 0, atol=1e-8)


def test_displace_rk4_matches_exact_rotation():
    rng = np.random.default_rng(2)
    omega = rng.normal(size=3)
    centre = rng.normal(size=3)
    flow = flows.SolidBodyRotation(tuple(omega), tuple(centre))
    p = rng.normal(size=(40, 3)) * 5
    dt = 0.7
    exact = Rotation.from_rotvec(omega * dt).apply(p - centre) + centre
    moved = flows.displace(p, flow, dt, steps=8)
    assert np.abs(moved - exact).max() < 1e-6
    back = flows.displace(moved, flow, -dt, steps=8)
    assert np.abs(back - p).max() < 1e-6
    chord = flows.centred_displacement(p, flow, dt, steps=8)
    exact_chord = (Rotation.from_rotvec(omega * dt / 2).apply(p - centre)
                   - Rotation.from_rotvec(-omega * dt / 2).apply(p - centre))
    assert np.abs(chord - exact_chord).max() < 1e-6


def test_lamb_oseen_profile_circulation_and_vorticity():
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    centre = rng.normal(size=3)
    rc, u_max = 3.0, 2.5
    flow = flows.LambOseen.from_peak_velocity(u_max, rc, tuple(centre), tuple(axis))
    e = axis / np.linalg.norm(axis)
    perp = np.cross(e, [1.0, 0.0, 0.0])
    perp /= np.linalg.norm(perp)
    r = np.linspace(0.0, 8 * rc, 4001)
    speed = np.linalg.norm(flow(centre + r[:, None] * perp + 1.7 * e), axis=1)
    assert speed[0] < 1e-12 and np.all(np.isfinite(speed))
    assert speed.max() == pytest.approx(u_max, rel=1e-4)
    assert r[np.argmax(speed)] == pytest.approx(1.1209 * rc, rel=2e-3)
    far = 40 * rc  # circulation of a large loop -> Gamma
    assert 2 * np.pi * far * np.linalg.norm(flow((centre + far * perp)[None]))[()] == \
        pytest.approx(flow.circulation, rel=1e-9)
    h = 1e-4 * rc  # axial vorticity at the centre: Gamma / (pi rc^2)
    b = np.cross(e, perp)
    dv = (flow((centre + h * perp)[None]) - flow((centre - h * perp)[None]))[0] @ b / (2 * h)
    du = (flow((centre + h * b)[None]) - flow((centre - h * b)[None]))[0] @ perp / (2 * h)
    assert dv - du == pytest.approx(flow.vorticity_on_axis(), rel=1e-6)
    div, norm = _divergence(flow, centre + rng.normal(size=(200, 3)) * 2 * rc, 1e-4)
    assert np.abs(div).max() < 1e-6 * norm.max()


def test_musker_profile_limits():
    assert flows.musker_profile(0.0) == pytest.approx(0.0, abs=1e-12)
    yp = np.array([0.1, 0.5, 1.0])
    assert np.allclose(flows.musker_profile(yp), yp, rtol=2e-3)           # viscous sublayer
    yp = np.array([100.0, 300.0, 1000.0, 3000.0])
    assert np.allclose(flows.musker_profile(yp), np.log(yp) / 0.41 + 5.0, atol=0.1)  # log law


@pytest.fixture(scope="module")
def tbl():
    return flows.TurbulentBoundaryLayer(u_inf=2.0, delta=40.0, re_tau=800.0, wall_y=5.0,
                                        x_range=(0.0, 80.0), z_range=(0.0, 60.0), seed=11)


def test_tbl_mean_profile(tbl):
    assert tbl.mean_velocity(np.array([5.0]))[0] == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(tbl.mean_velocity(np.array([45.0, 60.0, 300.0])), 2.0)
    assert np.all(np.diff(tbl.mean_velocity(np.linspace(5, 45, 400))) > 0)
    # friction law: u_tau from Re_tau and nu consistent; log law in wall units
    assert tbl.delta * tbl.u_tau / tbl.nu == pytest.approx(800.0)
    y_plus = np.array([60.0, 120.0])
    u_plus = tbl.mean_velocity(5.0 + y_plus * tbl.nu / tbl.u_tau) / tbl.u_tau
    assert np.allclose(u_plus, np.log(y_plus) / 0.41 + 5.0, atol=0.4)
    assert 0.03 < tbl.u_tau / tbl.u_inf < 0.05   # Cf/2 of a Re_tau ~ 1000 layer


def test_tbl_fluctuations_divergence_free_wall_bounded_and_scaled(tbl):
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(10, 70, 3000), rng.uniform(5.5, 50, 3000),
                           rng.uniform(10, 50, 3000)])
    div, norm = _divergence(tbl, pts, 1e-3)
    assert np.abs(div).max() < 1e-5 * norm.max()   # finite-difference truncation only
    # no slip and continuity at the wall: tangential u' ~ y, wall-normal v' ~ y^2
    near = [tbl.fluctuation(np.column_stack([pts[:200, 0], np.full(200, 5.0 + h),
                                             pts[:200, 2]])) for h in (1e-3, 2e-3)]
    ratio = np.abs(near[1]).sum(axis=0) / np.abs(near[0]).sum(axis=0)
    assert np.allclose(ratio, [2.0, 4.0, 2.0], rtol=0.01)
    assert np.abs(near[0]).max() < 1e-3 * tbl.u_inf
    assert np.all(tbl(np.column_stack([pts[:, 0], np.full(3000, 4.9), pts[:, 2]])) == 0)
    band = (pts[:, 1] > 9) & (pts[:, 1] < 25)      # 0.1 < y/delta < 0.5
    fluct = tbl.fluctuation(pts[band])
    rms = np.sqrt(np.mean(fluct**2, axis=0))
    assert 0.7 * 0.07 * 2.0 < rms[0] < 1.3 * 0.07 * 2.0
    assert np.all(rms > 0.3 * rms[0])      # all three components fluctuate
    outside = np.column_stack([np.full(10, 300.0), np.linspace(6, 40, 10), np.full(10, 30.0)])
    assert np.abs(tbl.fluctuation(outside)).max() < 1e-6


def test_tbl_fluctuations_are_anisotropic_like_a_boundary_layer():
    wide = flows.TurbulentBoundaryLayer(delta=1.0, x_range=(0, 8), z_range=(0, 4), seed=4)
    rng = np.random.default_rng(6)
    pts = np.column_stack([rng.uniform(1, 7, 20000), rng.uniform(0.1, 0.5, 20000),
                           rng.uniform(0.5, 3.5, 20000)])
    rms = np.sqrt(np.mean(wide.fluctuation(pts) ** 2, axis=0)) / wide.u_tau
    assert 1.4 < rms[0] < 2.6                      # u'+ of the log region, about 2
    assert rms[0] > 1.3 * max(rms[1], rms[2])      # streamwise fluctuations dominate
    outer = np.column_stack([pts[:, 0], np.full(20000, 1.3), pts[:, 2]])
    assert np.sqrt(np.mean(wide.fluctuation(outer) ** 2)) < 0.3 * np.sqrt(np.mean(rms**2)) \
        * wide.u_tau                               # intermittent, quiet free stream


def _erf_fraction(offset: float, sigma: float) -> float:
    s = np.sqrt(2) * sigma
    return 0.5 * (erf((offset + 0.5) / s) - erf((offset - 0.5) / s))


def test_render_particles_integrates_gaussian_over_voxels():
    pos = np.array([[10.3, 12.0, 9.75]])
    vol = flows.render_particles((20, 24, 22), pos, 0.8, sigma=1.3)
    assert vol.dtype == np.float32
    assert vol.sum() == pytest.approx(0.8 * (2 * np.pi * 1.3**2) ** 1.5, rel=1e-5)
    zz, yy, xx = np.indices(vol.shape)
    centroid = [np.sum(c * vol) / vol.sum() for c in (xx, yy, zz)]
    assert np.allclose(centroid, pos[0], atol=1e-5)
    expected = 0.8 * (2 * np.pi * 1.3**2) ** 1.5 * np.prod(
        [_erf_fraction(round(c) - c, 1.3) for c in pos[0]])
    assert vol[10, 12, 10] == pytest.approx(expected, rel=1e-5)
    assert vol[10, 12, 10] < 0.8   # integrated, not point-sampled (which would give 0.8 here)


def test_volume_pair_density_truth_and_inflow():
    shape = (30, 40, 36)
    d = (1.6, -0.7, 0.4)
    pair = flows.volume_pair(shape, flows.Uniform(d), density=0.004, sigma=1.0, seed=21)
    a, b, pa, pb, inten = pair
    assert a.shape == b.shape == shape and a.dtype == b.dtype == np.float32
    assert np.allclose(pb - pa, d)
    assert np.all((inten >= 0.5) & (inten <= 1.0))
    inside = np.all((pa > -0.5) & (pa < np.array(shape[::-1]) - 0.5), axis=1)
    expected = 0.004 * np.prod(shape)
    assert abs(inside.sum() - expected) < 5 * np.sqrt(expected)
    assert (~inside).sum() > 0   # seeded around the volume too: particles flow in
    again = flows.volume_pair(shape, flows.Uniform(d), density=0.004, sigma=1.0, seed=21)
    assert np.array_equal(again.vol_a, a)
    other = flows.volume_pair(shape, flows.Uniform(d), density=0.004, sigma=1.0, seed=22)
    assert not np.array_equal(other.vol_a, a)


def test_volume_pair_rejects_bad_arguments():
    with pytest.raises(ValueError, match="density"):
        flows.volume_pair((10, 10, 10), flows.Uniform(), density=0)
    with pytest.raises(ValueError, match="shape"):
        flows.volume_pair((10, 10), flows.Uniform())
    with pytest.raises(ValueError, match="sigma"):
        flows.render_particles((5, 5, 5), np.zeros((1, 3)), sigma=0.0)
