"""Launch the OpenCL kernels of ``kernels/``: fetch each once, bind them to a queue.

Programs are found and built by :mod:`plenocl.opencl.build` (once per context, file and
options); each kernel is fetched once per thread with ``cl.Kernel``.

:class:`KernelSet` is the one kernel-launch layer of plenocl: the kernels of one
program bound to a queue. It unwraps ``pyopencl.array.Array`` arguments (the one
buffer type of the package), knows whether the device is a CPU and applies the CPU
work-group rule there (see :meth:`KernelSet.launch`).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Sequence

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from . import pool
from .arrays import upload
from .build import UNKNOWN_CPU, KernelBuildError, build_hint, build_program, kernel_dir
from .device import is_cpu

__all__ = ["GPU_GROUP", "UNKNOWN_CPU", "KernelBuildError", "KernelSet", "build_hint",
           "build_program", "fetch_kernels", "group_size", "kernel_dir"]

#: Work-items per particle of the per-particle reductions (``kernels/groupreduce.h``) on
#: a GPU, where a group's items share one particle's work; a power of two.
GPU_GROUP = 64


#: Per thread: the kernels fetched from each program (weakly keyed: they go with it).
_FETCHED = threading.local()


def fetch_kernels(program: cl.Program, names: Sequence[str]) -> dict[str, cl.Kernel]:
    """Each named kernel of ``program``, fetched once per thread (``cl.Kernel(prg,
    name)``; fetching one costs 0.2-0.7 ms on a CPU runtime, and its launcher is
    generated again with it). Threads do not share a kernel object, which holds its
    arguments between setting them and the launch; within a thread every launch sets
    them all, so the solvers and stages of a thread share it."""
    kernels = _fetched(program)
    for name in names:
        if name not in kernels:
            kernels[name] = cl.Kernel(program, name)
    return {name: kernels[name] for name in names}


def _fetched(program: cl.Program) -> dict[str, cl.Kernel]:
    """The calling thread's kernels fetched from ``program`` so far, by name (looked up
    first: every launch asks)."""
    try:
        return _FETCHED.programs[program]
    except AttributeError:
        _FETCHED.programs = weakref.WeakKeyDictionary()
    except KeyError:
        pass
    return _FETCHED.programs.setdefault(program, {})


def group_size(queue: cl.CommandQueue, group: int | None = None) -> int:
    """The work-group size ``PL_GROUP`` of a per-particle reduction on ``queue``'s device:
    ``group`` where given (a power of two), else 1 on a CPU (one item loops over the
    particle) and :data:`GPU_GROUP` elsewhere."""
    size = (1 if is_cpu(queue.device) else GPU_GROUP) if group is None else int(group)
    if size < 1 or size & (size - 1):
        raise ValueError(f"group must be a power of two, got {group!r}")
    return size


class KernelSet:
    """The kernels of ``kernels/<filename>`` built for ``queue``'s context and bound to it.

    Parameters
    ----------
    queue
        The command queue every launch is enqueued on.
    filename, names, options
        The source file, the kernels to fetch (each once) and the build options
        (``-D`` defines of a variant).
    looping
        Kernels whose work-items each run a long loop (a light-field row, a block of
        rays, a chunk of a reduction). On a CPU they get work-groups of one item, so
        that PoCL spreads the items over all cores instead of running a group as one
        thread; element-wise kernels keep the driver's choice.
    source
        The file's text from elsewhere (:func:`plenocl.opencl.build.build_program`).

    Attributes
    ----------
    queue : pyopencl.CommandQueue
    is_cpu : bool
        Whether the device is a CPU (probed once).
    """

    def __init__(self, queue: cl.CommandQueue, filename: str, names: Sequence[str],
                 options: Sequence[str] = (), looping: Sequence[str] = (),
                 source: str | None = None) -> None:
        unknown = set(looping) - set(names)
        if unknown:
            raise ValueError(f"looping kernels {sorted(unknown)} are not among {list(names)}")
        self.queue = queue
        self.is_cpu = is_cpu(queue.device)
        self._program = build_program(queue.context, filename, options, source)
        fetch_kernels(self._program, names)  # every name checked here
        self._names, self._looping = frozenset(names), frozenset(looping)

    def launch(self, name: str, global_size: Sequence[int], *args,
               local_size: Sequence[int] | None = None) -> cl.Event:
        """Enqueue kernel ``name`` over ``global_size`` with ``args``; return its event.

        ``pyopencl.array.Array`` arguments are passed as their buffers; NumPy scalars as
        they are. Without ``local_size``, a :attr:`looping` kernel on a CPU runs in
        work-groups of one item; every other launch lets the driver choose.
        """
        if local_size is None and self.is_cpu and name in self._looping:
            local_size = (1,) * len(global_size)
        args = [a.data if isinstance(a, cl_array.Array) else a for a in args]
        return self.kernel(name)(self.queue, tuple(global_size), local_size, *args)

    def kernel(self, name: str) -> cl.Kernel:
        """The calling thread's kernel ``name`` (:func:`fetch_kernels`: a set made in one
        thread and launched from others gives each its own kernel object)."""
        if name not in self._names:
            raise KeyError(f"kernel {name!r} is not among {sorted(self._names)}")
        kernel = _fetched(self._program).get(name)
        return kernel if kernel is not None else fetch_kernels(self._program, (name,))[name]

    def array(self, shape, dtype=np.float32) -> cl_array.Array:
        """An uninitialised device array on this queue, its memory from the queue's
        pool (:func:`.pool.empty`)."""
        return pool.empty(self.queue, shape, dtype)

    def to_device(self, host: np.ndarray) -> cl_array.Array:
        """A device copy of a host array on this queue (:func:`.arrays.upload`: the host
        does not wait for the queue)."""
        return upload(self.queue, host)

    def on_device(self, data, dtype=np.float32) -> cl_array.Array:
        """``data`` on this queue's device: a device array as it is (a volume uploaded
        once for several kernels), a host array copied as ``dtype``."""
        if isinstance(data, cl_array.Array):
            return data
        return self.to_device(np.asarray(data, dtype))
