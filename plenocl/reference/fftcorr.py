"""Plain twins of ``kernels/fftcorr.cl`` (:class:`plenocl.piv.devicefft.DeviceCorrelation`):
each kernel's result for one window at a time, in float64, written for clarity."""

from __future__ import annotations

import numpy as np


def window_moments(vol: np.ndarray, low, size, weight=None) -> tuple[float, ...]:
    """``window_moments`` of one window: its mean, the sum of squares about the mean, the
    sum of squares and the energy after the weight, ``sum ((x - mean) w)^2``."""
    (z, y, x), (wz, wy, wx) = low, size
    win = np.asarray(vol, np.float64)[z:z + wz, y:y + wy, x:x + wx]
    mean = win.mean()
    centred = win - mean
    weighted = centred if weight is None else centred * weight
    return mean, float((centred ** 2).sum()), float((win ** 2).sum()), float((weighted ** 2).sum())


def packed_box(vol_a: np.ndarray, vol_b: np.ndarray, low, size, box, weight=None
               ) -> np.ndarray:
    """``fill_windows`` of one window pair: ``a'`` in the real part and ``b'`` in the
    imaginary part of a complex ``box``, ``a'`` and ``b'`` the windows less their means
    and weighted, zeros beyond the window."""
    out = np.zeros(box, complex)
    wz, wy, wx = size
    parts = []
    for vol in (vol_a, vol_b):
        z, y, x = low
        mean = window_moments(vol, low, size)[0]
        win = np.asarray(vol, np.float64)[z:z + wz, y:y + wy, x:x + wx] - mean
        parts.append(win if weight is None else win * weight)
    out[:wz, :wy, :wx] = parts[0] + 1j * parts[1]
    return out


def cross_spectrum(packed: np.ndarray) -> np.ndarray:
    """``conj(A) B`` from the spectrum ``Z = A + i B`` of a packed box: ``A(k) = (Z(k) +
    conj(Z(-k))) / 2`` and ``B(k) = (Z(k) - conj(Z(-k))) / 2i``."""
    mirrored = np.conj(np.roll(np.flip(packed), 1, axis=(0, 1, 2)))  # conj(Z(-k))
    spec_a = (packed + mirrored) / 2
    spec_b = (packed - mirrored) / 2j
    return np.conj(spec_a) * spec_b


def peak_fit(plane: np.ndarray, norm: float, exclude: int = 2) -> tuple[float, ...]:
    """``peak_fit`` of one real correlation plane ``(pz, py, px)`` divided by ``norm``:
    the peak's position (the first highest value, each axis wrapped to ``[-n/2, n/2)``
    plus the three-point Gaussian offset, parabolic where a value is not positive), its
    value, and its ratio to the highest value outside the ``+-exclude`` cube around it."""
    corr = np.asarray(plane, np.float64) / norm
    centre = np.unravel_index(int(np.argmax(corr)), corr.shape)
    peak = corr[centre]
    position = []
    for axis, n in enumerate(corr.shape):
        lo, hi = list(centre), list(centre)
        lo[axis], hi[axis] = (centre[axis] - 1) % n, (centre[axis] + 1) % n
        whole = centre[axis] - n if centre[axis] >= (n + 1) // 2 else centre[axis]
        position.append(whole + _subpixel(corr[tuple(lo)], peak, corr[tuple(hi)]))
    outside = corr.copy()
    near = [(np.arange(-exclude, exclude + 1) + c) % n for c, n in zip(centre, corr.shape)]
    outside[np.ix_(*near)] = -np.inf
    second = outside.max()
    return (*position, peak, peak / second if second > 0 else np.inf)


def _subpixel(cm: float, c0: float, cp: float) -> float:
    """The three-point Gaussian offset, parabolic where a value is not positive or the
    log-curvature is not negative, clipped to ``[-0.5, 0.5]``."""
    if min(cm, c0, cp) > 0:
        curvature = 2 * (np.log(cm) - 2 * np.log(c0) + np.log(cp))
        if curvature < 0:
            return float(np.clip((np.log(cm) - np.log(cp)) / curvature, -0.5, 0.5))
    curvature = 2 * (cm - 2 * c0 + cp)
    return float(np.clip((cm - cp) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def correlate_window(vol_a, vol_b, low, size, box, weight=None) -> tuple[float, ...]:
    """The whole chain for one window: the packed box, its FFT, the cross spectrum, the
    inverse FFT's real part (``P`` times the circular correlation), normalised by ``P
    sqrt(energy_a energy_b)`` and fitted; ``(dz, dy, dx, peak, ratio)``."""
    spec = cross_spectrum(np.fft.fftn(packed_box(vol_a, vol_b, low, size, box, weight)))
    plane = np.fft.ifftn(spec).real * np.prod(box)
    energy = [window_moments(v, low, size, weight)[3] for v in (vol_a, vol_b)]
    return peak_fit(plane, np.prod(box) * np.sqrt(energy[0] * energy[1]))
