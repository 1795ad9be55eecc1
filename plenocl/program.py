"""Find, build and cache the OpenCL programs in ``kernels/``.

Sources are real ``.cl`` files. They are found next to the package in an installed
wheel (``plenocl/kernels``) and in the top-level ``kernels/`` folder of a source
checkout. The folder is always passed as ``-I`` so kernels use ``#include``.
Each program is built once per (context, file, options) and each kernel fetched
once with ``cl.Kernel``.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from pathlib import Path

import pyopencl as cl


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
            f"  compiler log:\n{exc}"
        ) from exc
    programs[key] = program
    return program


def fetch_kernels(program: cl.Program, names: Sequence[str]) -> dict[str, cl.Kernel]:
    """Fetch each named kernel once (``cl.Kernel(prg, name)``)."""
    return {name: cl.Kernel(program, name) for name in names}
