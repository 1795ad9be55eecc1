"""Each lens's own image centre in a full-aperture white image: a joint fit of the disks.

At full aperture each microlens images the main lens's exit pupil as a disk centred on
its image centre ``c_k = x_k (1 + f_ml/d)`` (docs/design.md §2, §3): the same centre the
stopped-down spots mark and the rest of the chain uses. Neighbouring disks touch, so a
disk's centroid in a window takes in its neighbours' edges and, with them, part of
their offsets; and a brightness falloff across a disk pulls it toward the bright side.
Here every disk is modelled instead::

    image(x) ≈ Σ_j (a_j + g_j · (x - c_j)) D(|x - c_j|; r_j, s_j)

``D`` a pillbox with a Gaussian-blurred edge (``erfc``) of radius ``r_j`` and width
``s_j``, ``a_j`` a lens's brightness, ``g_j`` its linear falloff across the disk
(vignetting); the image's black level is taken off first. Gauss-Newton steps update
each lens's ``(c, a, g, r, s)`` in its own window against the image minus all the disks
at their current estimates, so that the neighbours' edges are explained by the
neighbours; the lenses are swept colour by colour (no two touching lenses share a
colour), each batch seeing the disks as the batches before it left them. Disks the
sensor's edge cuts take the others' radius and edge width. Each centre's deviation comes
from its fit's residuals and normal equations (scaled up where the image's noise is
correlated between neighbouring pixels), so that calibration can weigh it against
the smooth grid model.

Plain NumPy; calibration (:func:`plenocl.calibration.find_centers`) is its one caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

#: Sweeps at most (measured: converged to 0.001 px in 6 on 17 px lenses).
MAX_SWEEPS = 6
#: A lens whose centre moves less than this (px), and whose neighbours' too, rests; the
#: sweeps stop when all rest.
CONVERGED_PX = 1e-3
#: A lens needs this fraction of its window on the sensor to be fitted.
MIN_ON_SENSOR = 0.35
#: Lenses per batch (bounds memory: a batch holds a few arrays of its windows' pixels).
BATCH = 2048


@dataclass(frozen=True)
class DiskFit:
    """Per-lens disk centres of a full-aperture white image.

    Attributes
    ----------
    centres
        ``(rows, cols, 2)`` fitted disk centres as ``(col, row)`` px, ``NaN`` where a lens
        was not fitted (off the sensor, too little of it on the sensor, no light).
    sigma
        ``(rows, cols)`` standard deviation (px, per axis) of each centre from the fit's
        residuals, ``inf`` where not fitted.
    radius_px, edge_px
        The disks' median radius and edge width (the edge's Gaussian standard deviation,
        the pixels' area included), px.
    """

    centres: np.ndarray
    sigma: np.ndarray
    radius_px: float
    edge_px: float


@dataclass
class _State:
    """Every lens's parameters (flat over the lenses fitted)."""

    c: np.ndarray  # (N, 2) centres
    amp: np.ndarray  # (N, 3) a, g_x, g_y
    r: np.ndarray  # (N,) disk radius
    s: np.ndarray  # (N,) edge width


def fit_disks(image: np.ndarray, prior: np.ndarray, pitch: float,
              lit: np.ndarray | None = None) -> DiskFit:
    """Fit every lens's disk in a full-aperture white image.

    Parameters
    ----------
    image
        ``(H, W)`` white image (float, hot pixels removed).
    prior
        ``(rows, cols, 2)`` predicted centre of every lens (the lattice model), px.
    pitch
        Microlens image pitch (px).
    lit
        Optional ``(rows, cols)`` lenses to fit (default: all); the others are neither
        fitted nor rendered (dead lenses). Lenses with under ``MIN_ON_SENSOR`` of their
        window on the sensor are fitted (their neighbours see them) but get no centre.

    Returns
    -------
    DiskFit
    """
    img = np.asarray(image, np.float64)
    img = img - _black_level(img)
    shape = prior.shape[:2]
    use = np.isfinite(prior).all(-1) & (np.ones(shape, bool) if lit is None else lit)
    half = int(math.ceil(0.5 * pitch + 3.0))
    share = _on_sensor_share(prior[use], half, img.shape)
    on = share > 0  # every disk that reaches the sensor is rendered: its neighbours see it
    idx = np.flatnonzero(use.ravel())[on]
    st = _initial_state(img, prior[use][on], pitch)
    free = share[on] >= MIN_ON_SENSOR
    doubt = _near(st.c[~free], 0.5 * pitch + 1.5, img.shape)
    sigma = _sweeps(img, st, half, pitch, free, _whole(st.c, 0.5 * pitch + 1.0, img.shape),
                    doubt)
    centres = np.full((*shape, 2), np.nan)
    sig = np.full(shape, np.inf)
    centres.reshape(-1, 2)[idx] = st.c
    sig.ravel()[idx] = sigma
    bad = ~np.isfinite(sig) | ~np.isfinite(centres).all(-1)
    centres[bad], sig[bad] = np.nan, np.inf
    return DiskFit(centres, sig, float(np.median(st.r)), float(np.median(st.s)))


def _initial_state(img: np.ndarray, c: np.ndarray, pitch: float) -> _State:
    """The lenses at their predicted centres ``c``, as bright as their centres' pixels,
    without falloff, 0.45 pitch in radius with a 1 px edge."""
    n = len(c)
    st = _State(c.copy(), np.zeros((n, 3)), np.full(n, 0.45 * pitch), np.ones(n))
    st.amp[:, 0] = _inner_level(img, st.c, int(0.3 * pitch))
    return st


def _sweeps(img: np.ndarray, st: _State, half: int, pitch: float, free: np.ndarray,
            whole: np.ndarray, doubt: np.ndarray) -> np.ndarray:
    """Gauss-Newton sweeps until the centres settle; the centres' deviations.

    Each sweep updates the lenses colour by colour (no two touching lenses share a
    colour, :func:`_colours`), each batch against the image of all disks as the lenses
    before it left it (Gauss-Seidel: updating every lens at once against the same model
    made touching lenses overcorrect each other and converge in ~20 sweeps instead of
    ~6). Every lens moves (a disk mostly off the sensor still shows its edge, and its
    neighbours need it in its place); only ``free`` ones report a deviation. A disk the
    sensor's edge cuts (not ``whole``) takes its radius and edge width from the whole
    ones, and fits no falloff: with part of its edge missing they would trade with its
    centre (0.16 px toward the edge, measured on a hexagonal array's last lenses). The
    pixels ``doubt`` marks (where a disk mostly off the sensor, poorly placed by its
    sliver, lies) are left out of the ``free`` lenses' fits (its misplaced edge moved
    its neighbours by 0.2-0.6 px)."""
    start = st.c.copy()
    model = _render(img.shape, st, half, np.arange(len(st.c)))
    sigma = np.full(len(st.c), np.inf)
    pairs = _neighbour_pairs(st.c, pitch)
    batches = [b for group in _colours(len(st.c), pairs, st.c) for b in _batches(group)]
    active = np.ones(len(st.c), bool)
    for _ in range(MAX_SWEEPS):
        moved = np.zeros(len(st.c), bool)
        for sel in (b[active[b]] for b in batches):
            if len(sel) == 0:
                continue
            move, sigma[sel] = _update_batch(img, model, st, sel, half, whole[sel], doubt,
                                             free[sel])
            moved[sel] = np.abs(move).max(1) >= CONVERGED_PX
            lost = sel[np.abs(st.c[sel] - start[sel]).max(1) > 0.3 * pitch]
            if len(lost):
                before = _render(img.shape, st, half, lost)
                st.c[lost], sigma[lost] = start[lost], np.inf
                model += _render(img.shape, st, half, lost) - before
        _share_the_shape(img.shape, st, half, whole, model)
        active = moved | ~whole  # the next sweep: lenses still moving, and their neighbours
        active[pairs[moved[pairs[:, 0]], 1]] = active[pairs[moved[pairs[:, 1]], 0]] = True
        if not moved[free].any():
            break
    return np.where(free, sigma * _correlation_factor(img - model), np.inf)


def _correlation_factor(resid: np.ndarray) -> float:
    """How much more a centre's deviation is than the fit's residuals say when the
    image's noise is correlated between neighbouring pixels (a resampled or blurred
    image): ``√(1 + 2 Σ ρ)`` over the residuals' correlation ``ρ`` with the 4 next
    pixels (along the rows, the columns and the two diagonals), at least 1."""
    r = resid - resid.mean()
    var = float((r * r).mean())
    if var <= 0:
        return 1.0
    lags = [(r[:, 1:], r[:, :-1]), (r[1:], r[:-1]), (r[1:, 1:], r[:-1, :-1]),
            (r[1:, :-1], r[:-1, 1:])]
    rho = sum(float((a * b).mean()) for a, b in lags) / var
    return math.sqrt(max(1.0 + 2.0 * rho, 1.0))


def _share_the_shape(shape, st: _State, half: int, whole: np.ndarray,
                     model: np.ndarray) -> None:
    """The disks not ``whole`` take the whole ones' median radius and edge width (the
    model image follows)."""
    cut = np.flatnonzero(~whole)
    if len(cut) == 0 or not whole.any():
        return
    before = _render(shape, st, half, cut)
    st.r[cut], st.s[cut] = np.median(st.r[whole]), np.median(st.s[whole])
    model += _render(shape, st, half, cut) - before


def _near(c: np.ndarray, radius: float, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` the pixels within ``radius`` of any of the points ``c``."""
    out = np.zeros(shape, bool)
    flat, inside, dx, dy = _window(c, int(math.ceil(radius)), shape)
    out.ravel()[flat[inside & (dx * dx + dy * dy <= radius * radius)]] = True
    return out


def _whole(c: np.ndarray, radius: float, shape: tuple[int, int]) -> np.ndarray:
    """Lenses whose disk (``radius`` px about ``c``) lies on the sensor entirely."""
    h, w = shape
    return ((c >= radius - 0.5) & (c <= np.array([w, h]) - 0.5 - radius)).all(1)


def _neighbour_pairs(c: np.ndarray, pitch: float) -> np.ndarray:
    """``(pairs, 2)`` indices of lenses within 1.25 pitches of each other (touching)."""
    return cKDTree(c).query_pairs(1.25 * pitch, output_type="ndarray").reshape(-1, 2)


def _colours(n: int, pairs: np.ndarray, c: np.ndarray) -> list[np.ndarray]:
    """The ``n`` lenses split into groups of which no two are ``pairs`` (touching
    disks), by greedy colouring (2 groups for a rectangular array, 3-4 for a hexagonal
    one), each group in row-major order so that its batches are nearby lenses."""
    near = [[] for _ in range(n)]
    for i, j in pairs:
        near[i].append(j)
        near[j].append(i)
    colour = np.full(n, -1)
    for i in np.lexsort((c[:, 0], c[:, 1])):
        taken = {colour[j] for j in near[i]}
        colour[i] = next(k for k in range(len(taken) + 1) if k not in taken)
    order = np.lexsort((c[:, 0], np.rint(c[:, 1])))
    return [order[colour[order] == k] for k in range(colour.max() + 1)]


def _black_level(img: np.ndarray) -> float:
    """The image's level without light: its darkest pixels (the 0.1 % quantile after a
    3 x 3 mean, so that read noise does not pull it below), the gaps between disks and
    the sensor beyond the array. A background under the disks is otherwise not modelled:
    under touching disks it cannot be told from their brightness, and a level left in
    the image is symmetric about a lens, so it does not move its centre."""
    return float(np.percentile(ndimage.uniform_filter(img, 3), 0.1))


def _on_sensor_share(c: np.ndarray, half: int, shape: tuple[int, int]) -> np.ndarray:
    """Fraction of each lens's ``(2 half + 1)²`` window that lies on the sensor."""
    h, w = shape
    base = np.rint(c).astype(np.int64)
    span = 2 * half + 1
    nx = np.clip(np.minimum(base[:, 0] + half, w - 1) - np.maximum(base[:, 0] - half, 0) + 1,
                 0, None)
    ny = np.clip(np.minimum(base[:, 1] + half, h - 1) - np.maximum(base[:, 1] - half, 0) + 1,
                 0, None)
    return nx * ny / span**2


def _inner_level(img: np.ndarray, c: np.ndarray, half: int) -> np.ndarray:
    """Mean of each lens's central ``(2 half + 1)²`` pixels: its disk's first brightness."""
    flat, inside = _window(c, half, img.shape)[:2]
    vals = np.where(inside, img.ravel()[flat], 0.0)
    return vals.sum((1, 2)) / np.maximum(inside.sum((1, 2)), 1)


def _window(c: np.ndarray, half: int, shape: tuple[int, int]):
    """Pixel geometry of each lens's window: flat indices ``(n, P, P)`` (clipped),
    on-sensor mask, and the offsets ``dx (n, 1, P)``, ``dy (n, P, 1)`` from the centre."""
    h, w = shape
    base = np.rint(c).astype(np.int64)
    off = np.arange(-half, half + 1)
    cols, rows = base[:, 0, None] + off, base[:, 1, None] + off
    inside = (((cols >= 0) & (cols < w))[:, None, :] & ((rows >= 0) & (rows < h))[:, :, None])
    flat = np.clip(rows, 0, h - 1)[:, :, None] * w + np.clip(cols, 0, w - 1)[:, None, :]
    dx = (cols - c[:, 0, None])[:, None, :].astype(np.float32)  # float32: half the memory
    dy = (rows - c[:, 1, None])[:, :, None].astype(np.float32)  # traffic, ample precision
    return flat, inside, dx, dy


#: Abramowitz & Stegun 7.1.26: ``erfc(z) = k P(k) exp(-z²)``, ``k = 1/(1 + p z)``, z >= 0
#: (absolute error below 1.5e-7; scipy's erfc took most of the fit's time).
_ERFC_P = 0.3275911
_ERFC_A = (1.061405429, -1.453152027, 1.421413741, -0.284496736, 0.254829592)


def _disk(dx, dy, r, s):
    """The pillbox profile ``D = erfc(t/√2)/2`` at ``t = (ρ - r)/s``, the edge's Gaussian
    ``φ(t)`` (``dD/dρ = -φ/s``), ``ρ`` and ``t``, over each lens's window."""
    rho = np.sqrt(dx * dx + dy * dy)
    t = (rho - r[:, None, None].astype(np.float32)) / s[:, None, None].astype(np.float32)
    gauss = np.exp(-0.5 * t * t)
    k = 1 / (1 + np.float32(_ERFC_P / math.sqrt(2)) * np.abs(t))
    poly = np.zeros_like(k)
    for coef in _ERFC_A:
        poly = poly * k + np.float32(coef)
    tail = np.float32(0.5) * k * poly * gauss  # D for t >= 0, 1 - D for t < 0
    return (np.where(t >= 0, tail, 1 - tail), gauss * np.float32(1 / math.sqrt(2 * math.pi)),
            rho, t)


def _render(shape: tuple[int, int], st: _State, half: int, which: np.ndarray) -> np.ndarray:
    """The image of the disks ``which`` at their current parameters (no background)."""
    out = np.zeros(shape)
    for sel in _batches(which):
        _add(out, *_patch_values(st, sel, half, shape))
    return out


def _batches(which: np.ndarray):
    for start in range(0, len(which), BATCH):
        yield which[start:start + BATCH]


def _update_batch(img, model, st: _State, sel: np.ndarray, half: int, whole: np.ndarray,
                  doubt: np.ndarray, free: np.ndarray):
    """One Gauss-Newton step of the lenses ``sel`` against the image minus all disks
    (``model``, brought up to date with their new disks); their centre moves and the
    centres' deviations (px, from the residuals and the normal equations). A lens not
    ``whole`` on the sensor fits its centre and brightness only; a ``free`` one leaves
    the pixels ``doubt`` marks out."""
    amp, r, s = st.amp[sel], st.r[sel], st.s[sel]
    flat, inside, dx, dy = _window(st.c[sel], half, img.shape)
    d, phi, rho, t = _disk(dx, dy, r, s)
    weight = inside & (rho <= (r + 3 * s + 1.0)[:, None, None])
    weight &= ~(doubt.ravel()[flat] & free[:, None, None])
    err = np.where(weight, img.ravel()[flat] - model.ravel()[flat], 0.0)
    jac = _jacobian(d, phi, rho, t, dx, dy, amp, s, weight)
    jac[~whole, :, 3:] = 0.0
    normal = np.matmul(jac.transpose(0, 2, 1), jac).astype(np.float64)
    rhs = np.matmul(jac.transpose(0, 2, 1),
                    err.reshape(len(sel), -1, 1).astype(np.float32))[..., 0].astype(np.float64)
    normal[~whole, 3:, 3:] += np.eye(4)  # no step in the parameters left out
    inverse = _inverse(normal)
    step = np.matmul(inverse, rhs[..., None])[..., 0]
    ok = np.isfinite(step).all(1) & (amp[:, 0] > 0)
    step = np.where(ok[:, None], step, 0.0)
    move = np.clip(step[:, :2], -1.0, 1.0)
    before = _values(d, dx, dy, amp)
    st.c[sel] += move
    st.amp[sel] = amp + step[:, 2:5]
    st.r[sel] = np.clip(r + step[:, 5], 1.0, None)
    st.s[sel] = np.clip(s + step[:, 6], 0.3, None)
    _add(model, flat[inside], -before[inside])
    _add(model, *_patch_values(st, sel, half, img.shape))
    var = (err**2).sum((1, 2)) / np.maximum(weight.sum((1, 2)) - normal.shape[-1], 1.0)
    cov = np.diagonal(inverse, axis1=1, axis2=2)[:, :2].mean(1)
    return move, np.where(ok & np.isfinite(cov), np.sqrt(var * cov), np.inf)


def _jacobian(d, phi, rho, t, dx, dy, amp, s, weight) -> np.ndarray:
    """``(n, pixels, 7)`` derivatives of a lens's disk by its centre ``(x, y)``,
    brightness ``(a, g_x, g_y)``, radius and edge width, zero outside ``weight``."""
    n = len(d)
    amp = amp.astype(np.float32)
    val = _values(np.float32(1), dx, dy, amp)
    edge = val * phi / s[:, None, None].astype(np.float32)  # dM/dr
    unit = np.where(weight, 1 / np.maximum(rho, np.float32(1e-9)), np.float32(0))
    jac = np.empty((n, *d.shape[1:], 7), np.float32)
    jac[..., 0] = edge * dx * unit - amp[:, 1, None, None] * d
    jac[..., 1] = edge * dy * unit - amp[:, 2, None, None] * d
    jac[..., 2] = d
    jac[..., 3] = d * dx
    jac[..., 4] = d * dy
    jac[..., 5] = edge
    jac[..., 6] = edge * t
    jac *= weight[..., None]
    return jac.reshape(n, -1, 7)


def _values(d, dx, dy, amp) -> np.ndarray:
    """A disk's brightness ``(a + g · (x - c)) d`` over its window."""
    return (amp[:, 0, None, None] + amp[:, 1, None, None] * dx
            + amp[:, 2, None, None] * dy) * d


def _patch_values(st: _State, sel: np.ndarray, half: int, shape: tuple[int, int]):
    """Flat pixel indices and values of the disks ``sel`` (on the sensor only)."""
    flat, inside, dx, dy = _window(st.c[sel], half, shape)
    d = _disk(dx, dy, st.r[sel], st.s[sel])[0]
    return flat[inside], _values(d, dx, dy, st.amp[sel])[inside]


def _add(model: np.ndarray, flat: np.ndarray, values: np.ndarray) -> None:
    """``model.flat[flat] += values`` with repeated indices summed, over the span of
    ``flat`` only (a batch of nearby lenses spans a few lens rows of the image)."""
    if len(flat) == 0:
        return
    lo, hi = int(flat.min()), int(flat.max())
    model.ravel()[lo:hi + 1] += np.bincount(flat - lo, values, minlength=hi - lo + 1)


def _inverse(normal: np.ndarray) -> np.ndarray:
    """Batched inverse; ``NaN`` for singular systems."""
    out = np.full(normal.shape, np.nan)
    ok = np.linalg.cond(normal) < 1e12
    if ok.any():
        out[ok] = np.linalg.inv(normal[ok])
    return out
