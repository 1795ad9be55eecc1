"""Where a chain's time goes between the host and the OpenCL device (issue 46).

:class:`OpenCLProfile` records, while active, every OpenCL call the process makes through
pyopencl: kernel launches (``enqueue_nd_range_kernel``, which every pyopencl kernel call
and array operation goes through), copies (``enqueue_copy``: bytes each way; and the
buffers plenocl makes from host arrays, :func:`plenocl.opencl.arrays.buffer_from_host`,
as copies to the device), fills and
the waits (``CommandQueue.finish``, ``Event.wait``, ``wait_for_events``), each with the
wall time spent inside the call. :meth:`OpenCLProfile.split` then attributes them to
stages by their time spans (:attr:`plenocl.pipeline.PairResult.spans`): per stage the
wall time, the time inside OpenCL calls (launching, copying, waiting for the device; with
several threads, the time any of them was inside one), the host's own work outside them
(the stage's wall time less that: NumPy, SciPy and
Python, what a faster device cannot shorten), the kernels' device seconds from their
profiling events (on a queue made with profiling enabled; ``None`` otherwise) and the
bytes moved each way. With ``sites=True`` it also keeps, for each copy to or from the
host, the plenocl function that made it (:meth:`OpenCLProfile.bytes_by_site`): where the
bytes beyond the raw images and the vectors come from.

It wraps pyopencl's module functions for the duration of a ``with`` block only and puts
them back after, so nothing outside a benchmark sees it.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyopencl as cl
from pyopencl import _cl

from ..opencl import arrays
from ..pipeline import process_pair

__all__ = ["OpenCLProfile", "StageProfile", "copy_site", "covered", "kernel_lines",
           "profiled_pair", "site_lines", "split_lines", "total_profile"]

#: plenocl's package folder (as imported, and with links resolved: a frame's file name
#: may be either), and the folders of its OpenCL layer and of this profile, whose frames
#: :func:`copy_site` passes over.
PACKAGE = Path(__file__).parents[1]
_ROOTS = tuple({str(PACKAGE) + os.sep, str(PACKAGE.resolve()) + os.sep})
_PASSED = tuple(root + sub + os.sep for root in _ROOTS for sub in ("opencl", "bench"))


@dataclass
class _Call:
    """One OpenCL call: its kind, wall span, bytes moved, event and whether the host
    waited in it for the queue (a wait, or a blocking copy)."""

    kind: str  # "kernel", "h2d", "d2h", "d2d", "fill", "wait"
    start: float
    end: float
    nbytes: int = 0
    event: object = None
    waits: bool = False
    kernel: object = None  # the launched cl.Kernel (its name read when reported)
    site: str = ""  # the plenocl function that made a copy (with ``sites=True``)


@dataclass
class StageProfile:
    """One stage's split (seconds; bytes)."""

    wall: float
    opencl: float = 0.0
    kernel: float | None = None
    launches: int = 0
    h2d_bytes: int = 0
    d2h_bytes: int = 0
    waits: int = 0
    calls: dict[str, int] = field(default_factory=dict)

    @property
    def host(self) -> float:
        """The host's own work: wall time outside OpenCL calls."""
        return max(self.wall - self.opencl, 0.0)


def _direction(dest, src) -> str:
    """``h2d``, ``d2h`` or ``d2d`` of an ``enqueue_copy``."""
    dev_dest = isinstance(dest, cl.MemoryObjectHolder)
    dev_src = isinstance(src, cl.MemoryObjectHolder)
    return "d2d" if dev_dest and dev_src else ("h2d" if dev_dest else "d2h")


def _host_bytes(obj) -> int:
    """Bytes of a host buffer (an array or anything with the buffer protocol)."""
    try:
        return int(np.asarray(obj).nbytes)
    except (TypeError, ValueError):
        return 0


class OpenCLProfile:
    """Record the process's OpenCL calls inside a ``with`` block (module docstring)."""

    def __init__(self, sites: bool = False) -> None:
        """``sites``: also record which plenocl function made each copy to or from the
        host (:meth:`bytes_by_site`; a walk up the stack per copy, so leave it off when
        timing)."""
        self.sites = sites
        self.calls: list[_Call] = []
        self._saved: list[tuple[object, str, object]] = []

    def _record(self, kind: str, fn: Callable, nbytes: Callable | None = None) -> Callable:
        calls, sites = self.calls, self.sites

        def wrapped(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            call = _Call(kind, t0, time.perf_counter(),
                         event=out if isinstance(out, cl.Event) else None)
            if nbytes is not None:
                call.kind, call.nbytes = nbytes(*args, **kwargs)
            if kind == "kernel":
                call.kernel = args[1]  # enqueue_nd_range_kernel(queue, kernel, ...)
            if sites and call.kind in ("h2d", "d2h"):
                call.site = copy_site()
            call.waits = kind == "wait" or (kind == "copy" and call.kind != "d2d"
                                            and kwargs.get("is_blocking", True))
            calls.append(call)
            return out
        return wrapped

    def _patch(self, owner, name: str, kind: str, nbytes: Callable | None = None) -> None:
        fn = getattr(owner, name)
        self._saved.append((owner, name, fn))
        setattr(owner, name, self._record(kind, fn, nbytes))

    def __enter__(self) -> OpenCLProfile:
        def copy_bytes(queue, dest, src, **kwargs):
            way = _direction(dest, src)
            host = {"h2d": src, "d2h": dest}.get(way)
            return way, 0 if host is None else _host_bytes(host)

        self._patch(_cl, "enqueue_nd_range_kernel", "kernel")
        self._patch(cl, "enqueue_copy", "copy", copy_bytes)
        self._patch(cl, "enqueue_fill_buffer", "fill")
        self._patch(arrays, "buffer_from_host", "h2d",
                    lambda context, host: ("h2d", _host_bytes(host)))
        self._patch(cl, "wait_for_events", "wait")
        self._patch(cl.CommandQueue, "finish", "wait")
        self._patch(cl.Event, "wait", "wait")
        return self

    def __exit__(self, *exc) -> None:
        for owner, name, fn in reversed(self._saved):
            setattr(owner, name, fn)
        self._saved.clear()

    def split(self, spans: dict[str, tuple[float, float]]) -> dict[str, StageProfile]:
        """Each stage's :class:`StageProfile` from the calls that started within its
        span; call it after the device finished (the events' times are read here). A
        stage's time in OpenCL calls is the wall time during which at least one thread
        was inside one (:func:`covered`): two threads waiting at once count once, and a
        thread idle while another is inside a call is not host work."""
        out = {name: StageProfile(wall=end - start) for name, (start, end) in spans.items()}
        inside: dict[str, list[tuple[float, float]]] = {name: [] for name in spans}
        for call in self.calls:
            for name, (start, end) in spans.items():
                if start <= call.start < end:
                    self._add(out[name], call)
                    inside[name].append((call.start, call.end))
                    break
        for name, intervals in inside.items():
            out[name].opencl = covered(intervals)
        return out

    def kernel_seconds(self) -> dict[str, tuple[int, float]]:
        """Each kernel's launches and device seconds (from their events; 0 on a queue
        without profiling), by name, the most device time first; call it after the
        device finished."""
        out: dict[str, list] = {}
        for call in self.calls:
            if call.kind == "kernel":
                row = out.setdefault(call.kernel.function_name, [0, 0.0])
                row[0] += 1
                row[1] += _event_seconds(call.event) or 0.0
        return {name: (n, t) for name, (n, t) in
                sorted(out.items(), key=lambda item: -item[1][1])}

    def bytes_by_site(self) -> dict[str, dict[str, int]]:
        """The bytes copied each way (``"h2d"``, ``"d2h"``) by the plenocl function
        that made the copies (:func:`copy_site`; recorded with ``sites=True``), the most
        first."""
        out: dict[str, dict[str, int]] = {"h2d": {}, "d2h": {}}
        for call in self.calls:
            if call.kind in out and call.nbytes:
                way = out[call.kind]
                way[call.site] = way.get(call.site, 0) + call.nbytes
        return {k: dict(sorted(v.items(), key=lambda item: -item[1]))
                for k, v in out.items()}

    @staticmethod
    def _add(stage: StageProfile, call: _Call) -> None:
        stage.calls[call.kind] = stage.calls.get(call.kind, 0) + 1
        stage.waits += call.waits
        if call.kind == "h2d":
            stage.h2d_bytes += call.nbytes
        elif call.kind == "d2h":
            stage.d2h_bytes += call.nbytes
        elif call.kind == "kernel":
            stage.launches += 1
            seconds = _event_seconds(call.event)
            if seconds is not None:
                stage.kernel = (stage.kernel or 0.0) + seconds


def copy_site(frame=None) -> str:
    """The plenocl function that made a copy, as ``module.py:Class.function < its
    caller``: the innermost two functions of plenocl's package outside its OpenCL layer
    (``plenocl/opencl``) and the benchmarks' (``plenocl/bench``), from ``frame`` (default:
    the caller's) outwards, comprehensions and generator expressions counted as the
    function holding them (so Python versions that inline them agree); ``""`` where there
    is none (a copy made outside plenocl)."""
    frame = sys._getframe(1) if frame is None else frame
    names: list[str] = []
    while frame is not None and len(names) < 2:
        code = frame.f_code
        path = str(Path(code.co_filename))
        root = next((r for r in _ROOTS if path.startswith(r)), None)
        if root and not path.startswith(_PASSED) and not code.co_name.startswith("<"):
            module = Path(path[len(root):]).as_posix()
            names.append(f"{module}:{getattr(code, 'co_qualname', code.co_name)}")
        frame = frame.f_back
    return " < ".join(names)


def site_lines(by_site: dict[str, dict[str, int]], count: int = 12) -> list[str]:
    """:meth:`OpenCLProfile.bytes_by_site` as text lines: each way's total, then its
    ``count`` largest sites in MB."""
    rows = []
    for way, label in (("h2d", "to the device"), ("d2h", "back")):
        sites = by_site[way]
        rows.append(f"{label}: {sum(sites.values()) / 1e6:.2f} MB")
        rows += [f"  {b / 1e6:8.3f}  {site or '(outside plenocl)'}"
                 for site, b in list(sites.items())[:count]]
    return rows


def covered(intervals: list[tuple[float, float]]) -> float:
    """The length of the union of ``(start, end)`` intervals (seconds)."""
    total, reach = 0.0, -np.inf
    for start, end in sorted(intervals):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def _event_seconds(event) -> float | None:
    """A finished event's device seconds, ``None`` without profiling information."""
    try:
        return (event.profile.end - event.profile.start) * 1e-9
    except (AttributeError, cl.Error):
        return None


def total_profile(split: dict[str, StageProfile]) -> StageProfile:
    """The stages of ``split`` added up (kernel seconds ``None`` where no stage has
    them)."""
    stages = split.values()
    kernels = [st.kernel for st in stages if st.kernel is not None]
    return StageProfile(wall=sum(st.wall for st in stages),
                        opencl=sum(st.opencl for st in stages),
                        kernel=sum(kernels) if kernels else None,
                        launches=sum(st.launches for st in stages),
                        h2d_bytes=sum(st.h2d_bytes for st in stages),
                        d2h_bytes=sum(st.d2h_bytes for st in stages),
                        waits=sum(st.waits for st in stages))


def split_lines(split: dict[str, StageProfile]) -> list[str]:
    """The split as a table of text lines, one per stage and their total
    (:func:`total_profile`): wall, OpenCL calls, host, kernel seconds, launches, the
    calls in which the host waited for the queue (waits and blocking copies) and MB each
    way."""
    head = (f"{'stage':14s} {'wall s':>7s} {'in CL s':>8s} {'host s':>7s} {'kernel s':>9s} "
            f"{'launches':>8s} {'waits':>6s} {'MB in':>8s} {'MB out':>8s}")
    rows = [head]
    for name, st in {**split, "total": total_profile(split)}.items():
        kernel = "n/a" if st.kernel is None else f"{st.kernel:.3f}"
        rows.append(f"{name:14s} {st.wall:7.3f} {st.opencl:8.3f} {st.host:7.3f} "
                    f"{kernel:>9s} {st.launches:8d} {st.waits:6d} {st.h2d_bytes / 1e6:8.1f} "
                    f"{st.d2h_bytes / 1e6:8.1f}")
    return rows


def kernel_lines(seconds: dict[str, tuple[int, float]], count: int = 15) -> list[str]:
    """:meth:`OpenCLProfile.kernel_seconds` as text lines: the ``count`` kernels of most
    device time, their launches, seconds and share of all kernels' time."""
    total = sum(t for _, t in seconds.values()) or 1.0
    rows = [f"{'kernel':24s} {'launches':>8s} {'device s':>9s} {'share':>6s}"]
    for name, (n, t) in list(seconds.items())[:count]:
        rows.append(f"{name:24s} {n:8d} {t:9.4f} {t / total:6.1%}")
    return rows


def profiled_pair(raw_a, raw_b, projector) -> tuple[dict[str, float], object]:
    """One :func:`plenocl.process_pair` of the default chain (its vectors alone) under the
    profile: its ``waits``, ``host`` work outside OpenCL calls and ``wall`` seconds (the
    queue finished), the megabytes it sent to the device (``mb_in``), and its field
    (:class:`plenocl.PIVResult`): what the benchmarks that alternate two ways of the chain
    in one process compare."""
    with OpenCLProfile() as prof:
        pair = process_pair(raw_a, raw_b, projector, volumes=False)
        projector.queue.finish()
    total = total_profile(prof.split(pair.spans))
    return {"waits": total.waits, "host": total.host, "wall": total.wall,
            "mb_in": total.h2d_bytes / 1e6}, pair.piv
