"""FFT cross-correlation of interrogation windows on an OpenCL device (docs/design.md §7.5).

:class:`DeviceCorrelation` runs :func:`plenocl.piv.correlation.correlate` with
``kernels/fftcorr.cl``: the windows are gathered from the volumes on the device, made
zero-mean and weighted, both windows of a pair packed into one complex box and
transformed by mixed-radix (2, 3, 4, 5, 8) FFTs along each axis, their cross spectrum
transformed back and each plane's peak fitted there; six numbers per window come back
instead of the volumes going to the host. The host's FFTW path stays the reference and
the path for FFT lengths with a prime factor above 5 (``supports``).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pyopencl.array as cl_array

from ..io.kept import KeptChoices
from ..opencl.arrays import KeptUpload
from ..opencl.build import source_digest
from ..opencl.device import check_fits, is_cpu
from ..opencl.program import GPU_GROUP, KernelSet
from ..opencl.volume import host_volume
from ..options import is_number
from ..version import __version__
from .correlation import (
    BATCH_BYTES,
    Correlation,
    WindowGrid,
    correlate,
    fft_shape_of,
    smooth_length,
    window_lows,
)
from .fft import BACKENDS, default_backend

__all__ = ["CPU_GROUP", "KEPT_ROUTES", "MAX_LINE", "DeviceCorrelation", "FFTRoute",
           "forget_measured_routes", "is_route", "measured_routes"]

i32, f32 = np.int32, np.float32
#: The FFT correlation's program (``kernels/``).
PROGRAM = "fftcorr.cl"
_KERNELS = ("window_moments", "fill_windows", "fft_lines", "cross_spectrum", "peak_fit",
            "gather_windows")
#: The longest FFT line the kernel holds in local memory (``PL_MAXN``).
MAX_LINE = 512
#: Work-items per line and per window on a CPU device (a GPU takes
#: :data:`plenocl.opencl.program.GPU_GROUP`).
CPU_GROUP = 1
#: The windows :class:`FFTRoute` times on each route to choose one (the first of a call's).
MEASURED_WINDOWS = 8
#: The device's route is chosen when it took at most this fraction of the host's time: a
#: clear gain, so that two routes about as fast do not flip between processes (their
#: results differ at float32 rounding); the host's is the reference.
DEVICE_GAIN = 0.8
#: The peak ratio's excluded neighbourhood, as :func:`plenocl.piv.correlation.fit_peaks`.
EXCLUDE = 2


class DeviceCorrelation:
    """Window correlation by FFT on ``queue``'s device.

    Parameters
    ----------
    queue
        The device's queue (the kernels are built once per context).
    group
        Work-items per FFT line and per window (a power of two); ``None``:
        :data:`CPU_GROUP` on a CPU, :data:`plenocl.opencl.program.GPU_GROUP` elsewhere.
    """

    def __init__(self, queue, group: int | None = None) -> None:
        cpu = is_cpu(queue.device)
        self.group = int(group or (CPU_GROUP if cpu else GPU_GROUP))
        if self.group < 1 or self.group & (self.group - 1):
            raise ValueError(f"group must be a power of two, got {group!r}")
        self._k = KernelSet(queue, PROGRAM, _KERNELS,
                            [f"-DPL_GROUP={self.group}", f"-DPL_MAXN={MAX_LINE}"])
        self._buffers: dict[str, cl_array.Array] = {}
        self._twiddles: dict[tuple[int, bool], cl_array.Array] = {}
        self._weight = KeptUpload(queue, f32)  # a pair's passes give one weight

    @property
    def queue(self):
        """The device's queue."""
        return self._k.queue

    @staticmethod
    def supports(grid: WindowGrid, pad: bool = False) -> bool:
        """Whether every FFT length of ``grid``'s windows (padded with ``pad``) is a
        product of 2, 3 and 5 no longer than :data:`MAX_LINE`."""
        return all(n <= MAX_LINE and smooth_length(n) for n in fft_shape_of(grid, pad))

    def upload(self, vol) -> cl_array.Array:
        """``vol`` as a float32 device array (a device array as it is)."""
        return self._k.on_device(vol)

    def correlate(self, vol_a, vol_b, grid: WindowGrid, *, pad: bool = False,
                  weight: np.ndarray | None = None,
                  select: np.ndarray | None = None) -> Correlation:
        """:func:`plenocl.piv.correlation.correlate` of host or device volumes.

        Parameters are those of the host function but its FFT options; the planes are
        ``P`` times the circular correlation (``P`` the FFT box's size), normalised by
        ``P sqrt(energy_a energy_b)`` as the host's FFTW planes.
        """
        if not self.supports(grid, pad):
            raise ValueError(f"FFT box {fft_shape_of(grid, pad)} has a length above "
                             f"{MAX_LINE} or a prime factor above 5; correlate on the host")
        a, b = self.upload(vol_a), self.upload(vol_b)
        if a.shape != b.shape or a.ndim != 3 or a.dtype != f32 or b.dtype != f32:
            raise ValueError(f"the volumes must be 3-D float32 of one shape, got "
                             f"{a.dtype} {a.shape} and {b.dtype} {b.shape}")
        box = fft_shape_of(grid, pad)
        n = int(np.prod(grid.count))
        todo = np.arange(n) if select is None else np.flatnonzero(select)
        batch = max(1, min(max(len(todo), 1), BATCH_BYTES // (8 * int(np.prod(box)))))
        check_fits(self.queue, 2 * 8 * batch * int(np.prod(box)), "the FFT correlation")
        (wt,) = self._weight(np.ones(1, f32) if weight is None else weight)
        result = np.zeros((n, 6))
        for start in range(0, len(todo), batch):
            sel = todo[start:start + batch]
            result[sel] = self._batch(a, b, window_lows(grid, sel), grid.size, box, wt,
                                      weight is not None)
        shape = grid.count
        disp = result[:, :3].T.reshape((3, *shape))
        return Correlation(disp, result[:, 3].reshape(shape), result[:, 4].reshape(shape),
                           result[:, 5].reshape(shape) > 0)

    def windows(self, vol: cl_array.Array, lows: np.ndarray, size) -> np.ndarray:
        """The windows of size ``size`` ``(wz, wy, wx)`` of the device volume ``vol`` whose
        low corners are ``lows`` ``(B, 3)``, gathered on the device: ``(B, *size)``
        float32 on the host."""
        wz, wy, wx = size
        out = self._k.array((len(lows), wz, wy, wx))
        if len(lows):
            self._k.launch("gather_windows", (wx, wy, wz * len(lows)), vol,
                           *map(i32, vol.shape[1:]), self._k.to_device(np.asarray(lows, i32)),
                           i32(wz), out)
        return out.get()

    def _batch(self, a, b, lows: np.ndarray, size, box, weight, weighted: bool) -> np.ndarray:
        """The six outputs of ``len(lows)`` windows ``(B, 6)``."""
        k, g, count = self._k, self.group, len(lows)
        (ny, nx), (pz, py, px) = a.shape[1:], box
        dev_lows = k.to_device(np.asarray(lows, i32))
        geometry = (i32(ny), i32(nx), dev_lows, *map(i32, size))
        moments = k.array(8 * count)
        k.launch("window_moments", (count * g, 2), a, b, *geometry, weight, i32(weighted),
                 moments, local_size=(g, 1))
        data = self._kept("boxes", (count * pz * py, px))
        k.launch("fill_windows", (px, py, pz * count), a, b, *geometry, i32(pz), weight,
                 i32(weighted), moments, data)
        self.transform(data, box, count, -1.0, size)
        pairs = -(-count // 2)
        spec = self._kept("planes", (pairs * pz * py, px))
        k.launch("cross_spectrum", (px, py, pz * pairs), data, i32(pz), i32(count), spec)
        self.transform(spec, box, pairs, 1.0)
        out = k.array(6 * count)
        k.launch("peak_fit", (count * g,), spec, i32(pz), i32(py), i32(px), moments,
                 i32(EXCLUDE), out, local_size=(g,))
        return out.get().reshape(count, 6).astype(np.float64)

    def transform(self, data: cl_array.Array, box, count: int, sign: float,
                  window=None) -> None:
        """The 3-D FFT in place of ``count`` complex boxes ``box`` ``(z, y, x)`` in
        ``data`` (``sign`` -1 forward, +1 inverse, not normalised). ``window``: the values
        lie in the boxes' leading ``window`` corner, zeros elsewhere (the x lines outside
        it and the y lines beyond its depth are skipped)."""
        pz, py, px = box
        wz, wy, _ = box if window is None else window
        plane = py * px
        passes = (  # (n, element step, (nu, su), (nv, sv))
            (px, 1, (wz, plane), (wy, px)),
            (py, px, (wz, plane), (px, 1)),
            (pz, plane, (py, px), (px, 1)))
        for n, step, (nu, su), (nv, sv) in passes:
            if n > 1:
                lines = count * nu * nv
                args = (data, i32(n), i32(step), i32(nu), i32(su), i32(nv), i32(sv),
                        np.int64(pz * plane), f32(sign), self._twiddle_table(n, sign))
                self._k.launch("fft_lines", (lines * self.group,), *args,
                               local_size=(self.group,))

    def _kept(self, name: str, shape: tuple[int, int]) -> cl_array.Array:
        """A complex buffer of ``shape`` from the kept one ``name``, grown as needed: on a
        CPU device a fresh buffer costs a page fault per 4 KiB at its first touch (the
        in-order queue finishes the previous batch's kernels before new ones)."""
        size = shape[0] * shape[1]
        kept = self._buffers.get(name)
        if kept is None or kept.size < size:
            kept = self._buffers[name] = self._k.array(size, np.complex64)
        return kept[:size].reshape(shape)

    def _twiddle_table(self, n: int, sign: float) -> cl_array.Array:
        """``exp(sign 2 pi i t / n)`` for ``t < n`` on the device (made once per length
        and direction)."""
        key = (n, sign > 0)
        if key not in self._twiddles:
            table = np.exp(np.copysign(2.0, sign) * 1j * np.pi * np.arange(n) / n)
            self._twiddles[key] = self._k.to_device(table.astype(np.complex64))
        return self._twiddles[key]


#: The FFT route measured per device, FFT box and where the volumes are (device ``True``
#: or host): ``"device"`` or ``"host"``, with the seconds of each, for the process's life.
_MEASURED: dict[tuple, tuple[str, float, float]] = {}
_MEASURE_LOCK = threading.Lock()
#: The routes measured on this machine, kept for every later process (docs/design.md
#: §7.5, "Which side correlates").
KEPT_ROUTES = KeptChoices("fft_routes", "PIV's FFT route (host or device)")
ROUTES = ("host", "device")


def is_route(value) -> bool:
    """Whether a kept ``value`` names a route, with its two measured seconds as numbers
    (a hand-edited file may hold anything)."""
    return (isinstance(value, dict) and value.get("route") in ROUTES
            and all(is_number(value.get(k)) for k in ("host_s", "device_s")))


def forget_measured_routes() -> None:
    """Forget this process's routes, as a new process starts: the next call per key
    reads the kept file (:data:`KEPT_ROUTES`) or measures again."""
    with _MEASURE_LOCK:
        _MEASURED.clear()


def measured_routes() -> dict[tuple, tuple[str, float, float]]:
    """Every FFT route this process has chosen by measurement, its own or kept from an
    earlier process (:data:`KEPT_ROUTES`): ``(device name, box, where the volumes are,
    padded)`` to ``(route, host seconds, device seconds)`` (the seconds of the measurement
    that chose it); the volumes ``"host"``, ``"device"`` or ``"both"`` (host volumes with
    device copies, ``on_device``); padded: whether the windows are zero-padded into the
    box."""
    with _MEASURE_LOCK:
        return dict(_MEASURED)


class FFTRoute:
    """Where a PIV run's FFT correlations go: the host's FFT or :class:`DeviceCorrelation`.

    Parameters
    ----------
    fft
        ``"fftw"`` or ``"scipy"``: the host with that backend (as before the device
        path); ``"device"``: the device wherever its FFT lengths allow; ``None``: for each
        device, FFT box and residence of the volumes, whichever of the device and the
        host's default backend correlated the first such call faster, the device by a
        clear margin (:data:`DEVICE_GAIN`). The measurement runs each route twice on
        the first :data:`MEASURED_WINDOWS` windows of the first such call (the first run
        of each warms it) and is kept on this machine (:data:`KEPT_ROUTES`): every later
        call and process takes the same route, so reruns agree to the bit
        (:func:`measured_routes`). Every call returns the chosen route's result.
    queue
        The device (``None``: the host only).
    workers
        The host FFT's threads.

    Attributes
    ----------
    used : set of str
        The routes taken so far (``"host"``, ``"device"``).
    """

    def __init__(self, fft: str | None, queue=None, workers: int = -1) -> None:
        self.fft, self.workers = fft, workers
        self.backend = fft if fft in BACKENDS else None
        #: The device's correlation (also what gathers the windows of device volumes for
        #: the host's FFT); ``None`` without a queue.
        self.device = None if queue is None else DeviceCorrelation(queue)
        self.used: set[str] = set()

    def correlate(self, vol_a, vol_b, grid: WindowGrid, *, pad: bool = False,
                  weight: np.ndarray | None = None, select: np.ndarray | None = None,
                  on_device: tuple | None = None) -> Correlation:
        """:func:`plenocl.piv.correlation.correlate` of host or device volumes, on the
        route chosen (the host's FFT options from this object). ``on_device``: device
        copies of host volumes (the same values, on this route's context), which the
        device's route reads instead of uploading the volumes; the host's reads the host
        volumes."""
        options = {"pad": pad, "weight": weight, "select": select}
        route = (self.route(vol_a, grid, pad, on_device)
                 or self._measure(vol_a, vol_b, grid, options, on_device))
        self.used.add(route)
        if route == "host":
            return self._host(vol_a, vol_b, grid, options)
        return self._device(vol_a, vol_b, grid, options, on_device)

    def _device(self, vol_a, vol_b, grid: WindowGrid, options: dict,
                on_device: tuple | None) -> Correlation:
        """The device's FFT, of the volumes' device copies where given."""
        return self.device.correlate(*(on_device or (vol_a, vol_b)), grid, **options)

    def _host(self, vol_a, vol_b, grid: WindowGrid, options: dict) -> Correlation:
        """The host's FFT; of device volumes only the windows come to the host (of a
        :class:`DeviceVolume`, the volume: its windows overlap)."""
        vol_a, vol_b = host_volume(vol_a), host_volume(vol_b)
        windows = None
        if isinstance(vol_a, cl_array.Array):
            def windows(vol, lows):
                return self.device.windows(vol, lows, grid.size)
        return correlate(vol_a, vol_b, grid, workers=self.workers, backend=self.backend,
                         windows=windows, **options)

    def route(self, vol_a, grid: WindowGrid, pad: bool, on_device: tuple | None = None
              ) -> str | None:
        """``"host"`` or ``"device"`` for volumes like ``vol_a`` (with device copies
        ``on_device`` or not) and ``grid``'s windows; ``None`` where it is still to be
        measured."""
        if self.device is None or self.fft in BACKENDS or not self.device.supports(grid, pad):
            return "host"
        if self.fft == "device":
            return "device"
        key = self._key(vol_a, grid, pad, on_device)
        with _MEASURE_LOCK:
            known = _MEASURED.get(key)
        if known is None:
            known = self._kept(key, KEPT_ROUTES.get(self._kept_key(key), is_route))
        return None if known is None else known[0]

    def _kept_key(self, key: tuple) -> tuple:
        """The kept file's key of a measurement's ``key``: the device's platform and
        driver, plenocl's version, the FFT kernels' source digest and the host's FFT
        backend beside it (another of any of them measures again: a checkout whose FFT
        kernels changed without a new version too)."""
        device = self.device.queue.device
        name, box, resident, pad = key
        return (device.platform.name.strip(), name, device.driver_version.strip(),
                __version__, source_digest(PROGRAM), self.backend or default_backend(),
                *box, resident, "padded" if pad else "unpadded")

    @staticmethod
    def _kept(key: tuple, value: dict | None) -> tuple[str, float, float] | None:
        """A kept ``value`` as this process's choice for ``key`` (``None``: none kept)."""
        if value is None:
            return None
        known = (value["route"], float(value["host_s"]), float(value["device_s"]))
        with _MEASURE_LOCK:
            return _MEASURED.setdefault(key, known)

    def _key(self, vol_a, grid: WindowGrid, pad: bool, on_device: tuple | None) -> tuple:
        resident = ("device" if isinstance(vol_a, cl_array.Array)
                    else "host" if on_device is None else "both")
        box = tuple(int(n) for n in fft_shape_of(grid, pad))
        return self.device.queue.device.name.strip(), box, resident, bool(pad)

    def _measure(self, vol_a, vol_b, grid: WindowGrid, options: dict,
                 on_device: tuple | None) -> str:
        """The route kept on the machine for this call's key (:data:`KEPT_ROUTES`: another
        process's, where one measured first), else measured (:meth:`_timed`) and kept."""
        key = self._key(vol_a, grid, options["pad"], on_device)
        value = KEPT_ROUTES.choose(self._kept_key(key),
                                   lambda: self._timed(vol_a, vol_b, grid, options, on_device),
                                   is_route)
        return self._kept(key, value)[0]

    def _timed(self, vol_a, vol_b, grid: WindowGrid, options: dict,
               on_device: tuple | None) -> dict:
        """Time both routes on up to :data:`MEASURED_WINDOWS` of this call's windows,
        each run twice (the first run warms it: the device's buffers and twiddles, the
        host's FFT plans) and the second timed; choose the device where it took at most
        :data:`DEVICE_GAIN` of the host's time, else the host: ``{"route", "host_s",
        "device_s"}``."""
        todo = np.ones(grid.count, bool) if options["select"] is None else options["select"]
        sample = np.zeros(grid.count, bool)
        sample.flat[np.flatnonzero(todo)[:MEASURED_WINDOWS]] = True
        trial = {**options, "select": sample}
        routes = {"host": lambda: self._host(vol_a, vol_b, grid, trial),
                  "device": lambda: self._device(vol_a, vol_b, grid, trial, on_device)}
        seconds = {}
        for name, run in routes.items():
            run()
            start = time.perf_counter()
            run()
            seconds[name] = time.perf_counter() - start
        route = "device" if seconds["device"] <= DEVICE_GAIN * seconds["host"] else "host"
        return {"route": route, "host_s": seconds["host"], "device_s": seconds["device"]}
