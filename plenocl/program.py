"""Find, build and cache the OpenCL programs in ``kernels/``, and launch their kernels.

Sources are real ``.cl`` files. They are found next to the package in an installed
wheel (``plenocl/kernels``) and in the top-level ``kernels/`` folder of a source
checkout. The folder is always passed as ``-I`` so kernels use ``#include``.
Each program is built once per (context, file, options) and each kernel fetched
once with ``cl.Kernel``.

:class:`KernelSet` is the one kernel-launch layer of plenocl: the kernels of one
program bound to a queue. It unwraps ``pyopencl.array.Array`` arguments (the one
buffer type of the package), knows whether the device is a CPU and applies the CPU
work-group rule there (see :meth:`KernelSet.launch`).
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from .device import is_cpu


class KernelBuildError(RuntimeError):
    """An OpenCL program failed to build; the message carries file, options and log."""


def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources (installed wheel first, then checkout)."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "kernels", here.parent / "kernels"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"plenocl's OpenCL sources were not found next to {here}; reinstall plenocl"
    )


# Programs per context; an entry goes when its context is garbage collected.
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def build_program(
    context: cl.Context, filename: str, options: Sequence[str] = ()
) -> cl.Program:
    """Build ``kernels/<filename>`` for ``context`` once and cache it.

    Raises
    ------
    KernelBuildError
        With the file, the build options and the compiler log.
    """
    programs = _CACHE.setdefault(context, {})
    key = (filename, tuple(options))
    if key in programs:
        return programs[key]
    folder = kernel_dir()
    source = (folder / filename).read_text()
    opts = [f"-I{folder}", "-cl-fp32-correctly-rounded-divide-sqrt", *options]
    try:
        program = cl.Program(context, source).build(options=opts)
    except (cl.RuntimeError, cl.LogicError) as exc:
        raise KernelBuildError(
            f"building {folder / filename} failed\n  options: {' '.join(opts)}\n"
            f"  compiler log:\n{exc}{build_hint(str(exc))}"
        ) from exc
    programs[key] = program
    return program


#: What a compiler log says when PoCL's LLVM does not know the CPU it runs on.
UNKNOWN_CPU = "unknown target CPU"


def build_hint(log: str) -> str:
    """A fix for the build failures a user can mend without touching plenocl."""
    if UNKNOWN_CPU not in log:
        return ""
    return ("\n  hint: this PoCL's LLVM does not know this processor (e.g. the PoCL 3.0 wheel "
            "from PyPI, LLVM 14, on an AMD Zen 5 CPU) and so cannot compile any kernel. "
            "Install a PoCL built with a newer LLVM (Debian/Ubuntu: apt install "
            "pocl-opencl-icd; conda: conda install -c conda-forge pocl) and choose it with "
            "PYOPENCL_CTX or --device (`plenocl devices` lists them); docs/errors.md")


def fetch_kernels(program: cl.Program, names: Sequence[str]) -> dict[str, cl.Kernel]:
    """Fetch each named kernel once (``cl.Kernel(prg, name)``)."""
    return {name: cl.Kernel(program, name) for name in names}


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

    Attributes
    ----------
    queue : pyopencl.CommandQueue
    is_cpu : bool
        Whether the device is a CPU (probed once).
    """

    def __init__(self, queue: cl.CommandQueue, filename: str, names: Sequence[str],
                 options: Sequence[str] = (), looping: Sequence[str] = ()) -> None:
        unknown = set(looping) - set(names)
        if unknown:
            raise ValueError(f"looping kernels {sorted(unknown)} are not among {list(names)}")
        self.queue = queue
        self.is_cpu = is_cpu(queue.device)
        self._kernels = fetch_kernels(build_program(queue.context, filename, options), names)
        self._looping = frozenset(looping)

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
        return self._kernels[name](self.queue, tuple(global_size), local_size, *args)

    def array(self, shape, dtype=np.float32) -> cl_array.Array:
        """An uninitialised device array on this queue."""
        return cl_array.empty(self.queue, shape, dtype)

    def to_device(self, host: np.ndarray) -> cl_array.Array:
        """A device copy of a host array on this queue."""
        return cl_array.to_device(self.queue, np.ascontiguousarray(host))
