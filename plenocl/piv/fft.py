"""Batched real-to-complex 3-D FFT cross-correlation of window stacks.

:class:`CorrelationFFT` correlates a batch of windows ``(B, wz, wy, wx)`` circularly over
an FFT shape (the window, or twice it for a zero-padded first pass). It uses FFTW
through ``pyfftw`` (plans made once per batch and FFT shape, multi-threaded, into
aligned buffers the windows are gathered into), and SciPy's pocketfft where pyfftw is
not installed or ``backend="scipy"`` asks for it: the reference the FFTW path is tested
against. On 2 CPU cores FFTW is about 2x SciPy for 32-voxel windows (measured in
``benchmarks/batch.py``).
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.fft

from ..opencl.threads import thread_count

try:  # wheels exist for the common platforms; SciPy's pocketfft otherwise
    import pyfftw
except ImportError:  # pragma: no cover - depends on the installation
    pyfftw = None

BACKENDS = ("fftw", "scipy")


def default_backend() -> str:
    """The host FFT's backend when none is given: FFTW where pyfftw is installed."""
    return "fftw" if pyfftw is not None else "scipy"


class CorrelationFFT:
    """Circular cross-correlation of window batches over ``fft_shape``.

    Parameters
    ----------
    batch
        The most windows one call takes.
    window, fft_shape
        Window size and FFT size ``(z, y, x)`` (each FFT axis >= the window's; the
        windows are zero-padded into the leading corner).
    workers
        Threads (``-1``: all cores).
    backend
        ``"fftw"`` (default where pyfftw is installed) or ``"scipy"``.
    """

    def __init__(self, batch: int, window, fft_shape, workers: int = -1,
                 backend: str | None = None) -> None:
        backend = backend or default_backend()
        if backend not in BACKENDS or (backend == "fftw" and pyfftw is None):
            raise ValueError(f"FFT backend must be one of {BACKENDS} (fftw needs pyfftw), "
                             f"got {backend!r}")
        self.backend, self.batch = backend, int(batch)
        self.window, self.fft_shape = tuple(window), tuple(fft_shape)
        self.threads = thread_count(workers)
        #: The factor the planes of :meth:`correlate` carry.
        self.scale = float(np.prod(self.fft_shape)) if backend == "fftw" else 1.0
        shape = (self.batch, *self.fft_shape)
        if backend == "fftw":
            self._plans = _fftw_plans(shape, self.window, self.threads)
            self.buffers = self._plans[0], self._plans[1]
        else:
            self.buffers = tuple(np.zeros(shape, np.float32) for _ in range(2))

    def windows(self, k: int, count: int) -> np.ndarray:
        """The region of buffer ``k`` (0: first volume, 1: second) the first ``count``
        windows go into: ``(count, wz, wy, wx)``; fill it, then call :meth:`correlate`."""
        wz, wy, wx = self.window
        return self.buffers[k][:count, :wz, :wy, :wx]

    def correlate(self, count: int) -> np.ndarray:
        """``(count, *fft_shape)`` float32 correlation planes of the filled windows,
        ``scale * c(s)``, ``c(s) = sum_p a(p) b(p + s)`` (circular) and :attr:`scale` the
        FFT length for FFTW (which does not normalise) or 1 for SciPy."""
        if self.backend == "scipy":
            axes, s = (1, 2, 3), self.fft_shape
            fa = scipy.fft.rfftn(self.buffers[0][:count], axes=axes, workers=self.threads)
            fb = scipy.fft.rfftn(self.buffers[1][:count], axes=axes, workers=self.threads)
            np.conjugate(fa, out=fa)
            fa *= fb
            return scipy.fft.irfftn(fa, s=s, axes=axes, workers=self.threads)
        real_a, real_b, spec_a, spec_b, fwd_a, fwd_b, inv, out = self._plans
        if count < self.batch:  # windows left from a previous call would only cost time
            real_a[count:] = 0.0
            real_b[count:] = 0.0
        fwd_a.execute()
        fwd_b.execute()
        np.conjugate(spec_a, out=spec_a)
        spec_a *= spec_b
        inv.execute()
        return out[:count]


_LOCAL = threading.local()
#: The FFTW plans a thread keeps (the least recently used go first): at most this many,
#: and their buffers within :data:`PLAN_BYTES` (the newest always kept). A pair uses six
#: (the first call's route measurement two, its four passes four); four kept made the
#: second pair of a process plan its first pass again (0.1 s on the 116 x 78 pair).
PLAN_COUNT = 8
PLAN_BYTES = 768 * 2**20


def _fftw_plans(shape: tuple[int, ...], window: tuple[int, ...], threads: int):
    """Aligned buffers and FFTW plans for one batch shape and window, made once per
    thread (the most recently used kept: :data:`PLAN_COUNT`, :data:`PLAN_BYTES`), so that
    every pass of every pair reuses them."""
    cache = _LOCAL.__dict__.setdefault("plans", {})
    key = (shape, window, threads)
    plans = cache.pop(key, None)
    cache[key] = _make_plans(shape, threads) if plans is None else plans
    while len(cache) > 1 and (len(cache) > PLAN_COUNT or _plan_bytes(cache) > PLAN_BYTES):
        cache.pop(next(iter(cache)))
    return cache[key]


def _plan_bytes(cache: dict) -> int:
    """The bytes of the buffers of every kept plan."""
    return sum(a.nbytes for plans in cache.values() for a in plans[:4] + plans[7:])


def _make_plans(shape: tuple[int, ...], threads: int):
    spec = (*shape[:-1], shape[-1] // 2 + 1)
    real_a, real_b, out = (pyfftw.zeros_aligned(shape, np.float32) for _ in range(3))
    spec_a, spec_b = (pyfftw.empty_aligned(spec, np.complex64) for _ in range(2))
    axes, flags = (1, 2, 3), ("FFTW_ESTIMATE",)
    fwd_a = pyfftw.FFTW(real_a, spec_a, axes=axes, flags=flags, threads=threads)
    fwd_b = pyfftw.FFTW(real_b, spec_b, axes=axes, flags=flags, threads=threads)
    inv = pyfftw.FFTW(spec_a, out, axes=axes, direction="FFTW_BACKWARD",
                      flags=(*flags, "FFTW_DESTROY_INPUT"), threads=threads)
    return real_a, real_b, spec_a, spec_b, fwd_a, fwd_b, inv, out
