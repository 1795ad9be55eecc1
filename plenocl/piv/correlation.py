"""Interrogation-window grids, batched 3-D FFT cross-correlation and sub-voxel peak fits.

All windows of a pass are correlated at once (in memory-bounded batches) with
real-to-complex FFTs over the last three axes (:mod:`plenocl.piv.fft`: FFTW, or SciPy's
pocketfft). Windows are zero-mean and the correlation is normalised by
``sqrt(sum a^2 sum b^2)``, so a perfect match peaks at 1. Displacement convention:
``vol_b(p) = vol_a(p - d)``, i.e. particles move by ``+d`` from ``a`` to ``b``.
Arrays are in volume order ``(z, y, x)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..peaks import gaussian_subpixel
from .fft import CorrelationFFT

#: Upper bound on the float32 correlation planes held at once (bytes).
BATCH_BYTES = 64 * 2**20


@dataclass(frozen=True)
class WindowGrid:
    """Regular grid of interrogation windows in a volume, per axis ``(z, y, x)``.

    Window ``k`` along an axis covers voxels ``[offset + k step, offset + k step + size)``
    and is centred at ``offset + k step + (size - 1) / 2`` (voxel-index units).
    """

    size: tuple[int, int, int]
    step: tuple[int, int, int]
    offset: tuple[int, int, int]
    count: tuple[int, int, int]

    @property
    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Window-centre coordinates ``(z, y, x)``, each 1-D, in voxel-index units."""
        return tuple(o + s * np.arange(n) + 0.5 * (w - 1)
                     for o, s, n, w in zip(self.offset, self.step, self.count, self.size))


def window_grid(shape: tuple[int, int, int], size: tuple[int, int, int],
                overlap: float) -> WindowGrid:
    """Windows of ``size`` overlapping by the fraction ``overlap``, centred in the volume.

    Parameters
    ----------
    shape
        Volume shape ``(nz, ny, nx)``.
    size
        Window size ``(wz, wy, wx)``, each no larger than the volume.
    overlap
        Fraction in ``[0, 1)``; the step is ``round(size (1 - overlap))``, at least 1.

    Returns
    -------
    WindowGrid
        As many whole windows as fit, the leftover split evenly between both faces.
    """
    steps, offsets, counts = [], [], []
    for n, w in zip(shape, size):
        step = max(1, int(round(w * (1.0 - overlap))))
        count = (n - w) // step + 1
        steps.append(step)
        counts.append(count)
        offsets.append((n - w - (count - 1) * step) // 2)
    return WindowGrid(tuple(size), tuple(steps), tuple(offsets), tuple(counts))


def window_fraction(mask: np.ndarray, grid: WindowGrid) -> np.ndarray:
    """Fraction of ``True`` voxels of ``mask`` inside every window, shaped ``grid.count``."""
    table = np.zeros(tuple(n + 1 for n in mask.shape))
    table[1:, 1:, 1:] = mask.cumsum(0).cumsum(1).cumsum(2)
    lo = [o + s * np.arange(c) for o, s, c in zip(grid.offset, grid.step, grid.count)]
    hi = [a + w for a, w in zip(lo, grid.size)]
    total = 0.0
    for bits in range(8):
        sel = [hi[a] if bits >> a & 1 else lo[a] for a in range(3)]
        sign = (-1) ** (3 - bin(bits).count("1"))
        total = total + sign * table[np.ix_(*sel)]
    return total / float(np.prod(grid.size))


def padded_size(window: int) -> int:
    """FFT length of a zero-padded window: the smallest even product of 2, 3 and 5 that
    holds the window plus a third of it, enough for linear (not circular) correlation of
    displacements up to a third of the window, beyond the quarter a first pass finds
    reliably, at about a third of the cost of doubling it (48 -> 64, 32 -> 48)."""
    size = window + -(-window // 3)
    while size % 2 or not smooth_length(size):
        size += 1
    return size


def fft_shape_of(grid: WindowGrid, pad: bool = False) -> tuple[int, int, int]:
    """The FFT box of ``grid``'s windows: the window, or :func:`padded_size` per axis with
    ``pad``."""
    return tuple(padded_size(w) if pad else int(w) for w in grid.size)


def smooth_length(n: int) -> bool:
    """``n`` has no prime factor above 5 (fast FFT lengths)."""
    for p in (2, 3, 5):
        while n % p == 0:
            n //= p
    return n == 1


@dataclass
class Correlation:
    """Per-window correlation outcome, every array shaped ``grid.count``."""

    displacement: np.ndarray  # (3, nz, ny, nx) as (dz, dy, dx), voxels
    peak: np.ndarray          # normalised correlation peak height
    peak_ratio: np.ndarray    # primary over secondary peak
    signal: np.ndarray        # bool: both windows had non-zero variance
    sigma: np.ndarray | None = None  # (3, nz, ny, nx) standard uncertainty, voxels


def gaussian_weight(size: tuple[int, int, int], fraction: float) -> np.ndarray:
    """Separable Gaussian window weight, standard deviation ``fraction * size`` per axis."""
    axes = [np.exp(-0.5 * ((np.arange(n) - 0.5 * (n - 1)) / (fraction * n)) ** 2) for n in size]
    return (axes[0][:, None, None] * axes[1][None, :, None] * axes[2]).astype(np.float32)


def correlate(vol_a: np.ndarray, vol_b: np.ndarray, grid: WindowGrid, *, pad: bool = False,
              weight: np.ndarray | None = None, workers: int = -1,
              backend: str | None = None, select: np.ndarray | None = None,
              windows=None) -> Correlation:
    """Cross-correlate every window of ``grid`` between two volumes.

    Parameters
    ----------
    vol_a, vol_b
        Volumes of equal shape (float32 recommended).
    grid
        Window grid from :func:`window_grid`.
    pad
        Zero-pad each window by a third of its size or more (:func:`padded_size`), so
        that the correlation is linear, not circular, for displacements up to a third of
        the window:
        for a first pass with unknown, possibly large displacement (it finds up to about
        a quarter of the window reliably).
    weight
        Optional ``grid.size`` array multiplying both zero-mean windows (e.g.
        :func:`gaussian_weight`): a smoother spatial filter than the top-hat window, which
        lets iterative deformation converge on structures of the window's size.
    workers
        FFT threads (``-1``: all cores).
    backend
        ``"fftw"`` or ``"scipy"`` (:class:`plenocl.piv.fft.CorrelationFFT`; by default
        FFTW where pyfftw is installed).
    select
        Optional bool array shaped ``grid.count``: correlate only these windows (the
        others come back with zero displacement and no signal).
    windows
        Optional ``windows(vol, lows)``: the windows of ``vol`` whose low corners are
        ``lows`` ``(B, 3)``, ``(B, *grid.size)`` float32, for volumes that are not host
        arrays (:meth:`plenocl.piv.devicefft.DeviceCorrelation.windows`: only the
        windows come to the host). By default they are sliced from the host volumes.

    Returns
    -------
    Correlation
        Sub-voxel peak displacement, peak height, peak ratio and signal flags.
    """
    vols = ((vol_a, vol_b) if windows is not None
            else (np.asarray(vol_a, np.float32), np.asarray(vol_b, np.float32)))
    fft_shape = fft_shape_of(grid, pad)
    n = int(np.prod(grid.count))
    todo = np.arange(n) if select is None else np.flatnonzero(select)
    batch = max(1, min(max(len(todo), 1), BATCH_BYTES // (4 * int(np.prod(fft_shape)))))
    fft = CorrelationFFT(batch, grid.size, fft_shape, workers, backend)
    disp = np.zeros((3, n))
    peak, ratio, signal = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    for start in range(0, len(todo), batch):
        sel = todo[start:start + batch]
        lows = window_lows(grid, sel)
        prepared = [_gather(vol, lows, fft.windows(k, len(lows)), weight, windows)
                    for k, vol in enumerate(vols)]
        out = _fit_batch(fft.correlate(len(lows)), fft.scale, *prepared)
        disp[:, sel], peak[sel], ratio[sel], signal[sel] = out
    shape = grid.count
    return Correlation(disp.reshape((3, *shape)), peak.reshape(shape), ratio.reshape(shape),
                       signal.reshape(shape))


#: Windows gathered and prepared together: small enough that a chunk stays in cache
#: between the copy, the mean, the weighting and the energy sums.
CHUNK = 16


def window_lows(grid: WindowGrid, flat: np.ndarray) -> np.ndarray:
    """The low corners ``(B, 3)`` ``(z, y, x)`` of ``grid``'s windows of flat indices
    ``flat`` (C order over ``grid.count``)."""
    index = np.unravel_index(np.asarray(flat, np.int64), grid.count)
    return np.column_stack([o + s * i for o, s, i in zip(grid.offset, grid.step, index)])


def _gather(vol, lows: np.ndarray, out: np.ndarray, weight, windows=None):
    """Copy the windows whose low corners are ``lows`` ``(B, 3)`` into ``out``
    ``(B, wz, wy, wx)`` (sliced from a host ``vol``, or by ``windows(vol, lows)``) and
    prepare them (:func:`_prepare_windows`), a chunk at a time.

    Returns
    -------
    energy, signal
        Each window's energy after preparation and whether it had any variance.
    """
    wz, wy, wx = out.shape[1:]
    if windows is not None:
        out[...] = windows(vol, lows)
    else:
        for i, (z, y, x) in enumerate(lows):
            out[i] = vol[z:z + wz, y:y + wy, x:x + wx]
    parts = [_prepare_windows(out[c:c + CHUNK], weight) for c in range(0, len(lows), CHUNK)]
    return tuple(np.concatenate(p) for p in zip(*parts))


def _prepare_windows(windows: np.ndarray, weight: np.ndarray | None):
    """Make a window batch zero-mean and weighted, in place; return its energy and which
    windows had any variance."""
    mean = windows.mean(axis=(1, 2, 3), keepdims=True)
    windows -= mean
    spread = np.einsum("bijk,bijk->b", windows, windows).astype(np.float64)
    raw = spread + windows[0].size * mean.ravel().astype(np.float64) ** 2  # sum of squares
    if weight is not None:
        windows *= weight
    energy = np.einsum("bijk,bijk->b", windows, windows).astype(np.float64)
    return energy, (spread > 1e-9 * raw) & (energy > 0)


def _fit_batch(corr: np.ndarray, scale: float, prepared_a, prepared_b):
    """Normalise a batch's correlation planes ``(B, pz, py, px)`` (which carry the factor
    ``scale``) and fit their peaks."""
    (energy_a, signal_a), (energy_b, signal_b) = prepared_a, prepared_b
    signal = signal_a & signal_b
    norm = (scale * np.sqrt(np.where(signal, energy_a * energy_b, 1.0))).astype(np.float32)
    corr /= norm[:, None, None, None]
    disp, peak, ratio = fit_peaks(corr)
    disp[:, ~signal] = 0.0
    return disp, np.where(signal, peak, 0.0), np.where(signal, ratio, 0.0), signal


def fit_peaks(corr: np.ndarray, exclude: int = 2):
    """Locate the highest peak of each correlation plane ``(B, pz, py, px)`` (circular).

    Returns
    -------
    displacement : numpy.ndarray
        ``(3, B)`` sub-voxel peak positions ``(dz, dy, dx)``, wrapped to ``[-p/2, p/2)``.
    peak : numpy.ndarray
        ``(B,)`` correlation value at the integer peak.
    ratio : numpy.ndarray
        ``(B,)`` primary peak over the highest value outside a ``+-exclude`` cube around it
        (``inf`` where that is not positive).
    """
    nb, shape = corr.shape[0], corr.shape[1:]
    flat = corr.reshape(nb, -1)
    first = np.argmax(flat, axis=1)
    rows = np.arange(nb)
    peak = flat[rows, first].astype(np.float64)
    centre = np.unravel_index(first, shape)
    disp = np.empty((3, nb))
    for axis, (idx, n) in enumerate(zip(centre, shape)):
        nbr = [list(centre), list(centre)]
        nbr[0][axis], nbr[1][axis] = (idx - 1) % n, (idx + 1) % n
        cm = corr[(rows, *nbr[0])]
        cp = corr[(rows, *nbr[1])]
        whole = np.where(idx >= (n + 1) // 2, idx - n, idx)
        disp[axis] = whole + gaussian_subpixel(cm, peak, cp)
    return disp, peak, _peak_ratio(flat, centre, shape, peak, exclude)


def _peak_ratio(flat, centre, shape, peak, exclude: int) -> np.ndarray:
    """Primary over secondary peak; masks the primary's neighbourhood in ``flat`` in place."""
    offs = np.arange(-exclude, exclude + 1)
    rz, ry, rx = ((c[:, None] + offs) % n for c, n in zip(centre, shape))
    idx = (rz[:, :, None, None] * shape[1] + ry[:, None, :, None]) * shape[2] + rx[:, None, None, :]
    flat[np.arange(len(peak))[:, None], idx.reshape(len(peak), -1)] = -np.inf
    second = flat.max(axis=1).astype(np.float64)
    return np.where(second > 0, peak / np.where(second > 0, second, 1.0), np.inf)
