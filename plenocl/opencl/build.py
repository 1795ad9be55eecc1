"""Find and build the OpenCL programs in ``kernels/``, once per context.

Sources are real ``.cl`` files. They are found next to the package in an installed
wheel (``plenocl/kernels``) and in the top-level ``kernels/`` folder of a source
checkout. The folder is always passed as ``-I`` so kernels use ``#include``. Each
program is built once per (context, file, options). This module needs no device
choice, so :mod:`plenocl.opencl.device` can use it to check that a device builds kernels.
"""

from __future__ import annotations

import functools
import hashlib
import re
import warnings
import weakref
from collections.abc import Sequence
from pathlib import Path

import pyopencl as cl

from .icd import pip_runtime_libraries


class KernelBuildError(RuntimeError):
    """An OpenCL program failed to build; the message carries file, options and log.

    Attributes
    ----------
    log : str
        The driver's own error text (the compiler log).
    """

    def __init__(self, message: str, log: str = "") -> None:
        super().__init__(message)
        self.log = log


def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources (installed wheel first, then checkout)."""
    here = Path(__file__).resolve().parent.parent  # the plenocl package
    for candidate in (here / "kernels", here.parent / "kernels"):
        if (candidate / "common.h").is_file():
            return candidate
    raise FileNotFoundError(
        f"plenocl's OpenCL sources were not found next to {here}; reinstall plenocl"
    )


@functools.cache
def source_digest(filename: str) -> str:
    """A digest (16 hex digits) of ``kernels/<filename>`` and every header it includes,
    however deep: what a choice measured on that program's kernels is kept under, so
    that a changed kernel is measured again (:mod:`plenocl.io.kept`). Read once per
    process, as the programs are built once."""
    folder, digest = kernel_dir(), hashlib.sha256()
    todo, seen = [filename], set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        text = (folder / name).read_text()
        digest.update(f"{name}\0{text}\0".encode())
        todo += re.findall(r'^\s*#\s*include\s+"([^"]+)"', text, re.MULTILINE)
    return digest.hexdigest()[:16]


# Programs per context; an entry goes when its context is garbage collected.
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def build_program(
    context: cl.Context, filename: str, options: Sequence[str] = (),
    source: str | None = None,
) -> cl.Program:
    """Build ``kernels/<filename>`` for ``context`` once and cache it.

    ``source``: that file's text from elsewhere (a benchmark building a git revision's
    kernel against today's; its ``#include`` still finds today's headers), cached by its
    text.

    Raises
    ------
    KernelBuildError
        With the file, the build options and the compiler log.
    """
    programs = _CACHE.setdefault(context, {})
    key = (filename, tuple(options), source)
    if key in programs:
        return programs[key]
    folder = kernel_dir()
    if source is None:
        source = (folder / filename).read_text()
    opts = [f"-I{folder}", "-cl-fp32-correctly-rounded-divide-sqrt", *options]
    try:
        program = _compile(context, source, opts)
    except (cl.RuntimeError, cl.LogicError) as exc:
        raise KernelBuildError(
            f"building {folder / filename} failed\n  options: {' '.join(opts)}\n"
            f"  compiler log:\n{exc}{build_hint(str(exc))}", log=str(exc)
        ) from exc
    programs[key] = program
    return program


def _compile(context: cl.Context, source: str, options: list[str]) -> cl.Program:
    """Build through pyopencl's binary cache; without it where that cache fails."""
    with warnings.catch_warnings():
        # Some compilers log progress on success (Intel's "Compilation started"):
        # a build that succeeds has nothing to tell a user.
        warnings.simplefilter("ignore", cl.CompilerWarning)
        try:
            return cl.Program(context, source).build(options=options)
        except KeyError:
            # pyopencl's cache reads PYOPENCL_CACHE_FAILURE_FATAL unguarded when a build
            # fails other than by a compile error (Intel's runtime: an invalid option);
            # building without the cache raises the driver's own error.
            return cl.Program(context, source).build(options=options, cache_dir=False)


#: What a compiler log says when PoCL's LLVM does not know the CPU it runs on.
UNKNOWN_CPU = "unknown target CPU"


def build_hint(log: str) -> str:
    """A fix for the build failures a user can mend without touching plenocl; where
    the fix, Intel's CPU runtime from pip, is installed already, only that it serves."""
    if UNKNOWN_CPU not in log:
        return ""
    if pip_runtime_libraries():
        return ("\n  note: this PoCL's LLVM does not know this processor (the PoCL 3.0 wheel "
                "on an AMD Zen 5 CPU, say); Intel's CPU runtime, installed (the cpu extra), "
                "builds plenocl's kernels and is the default here (`plenocl devices`)")
    return ("\n  hint: this PoCL's LLVM does not know this processor (the PoCL 3.0 wheel "
            "from PyPI, LLVM 14, on an AMD Zen 5 CPU, say) and so cannot compile any "
            "kernel. Install Intel's CPU runtime with pip, no root needed: "
            "pip install \"plenocl[cpu]\" (or intel-opencl-rt intel-cmplr-lib-rt), which "
            "plenocl registers and prefers by itself; or a PoCL built with a newer LLVM "
            "(apt install pocl-opencl-icd). `plenocl devices` shows which devices build "
            "plenocl's kernels; docs/errors.md")


def probe_build(context: cl.Context) -> str | None:
    """Build one of plenocl's kernels for ``context``: ``None`` if it builds, else why not.

    The probe is the deformation kernel (small, and built by every PIV run), so a
    context that passes and is kept (:func:`plenocl.opencl.device.create_context` keeps the
    default device's) keeps its program in the cache.
    """
    try:
        build_program(context, "deform.cl", ["-DORDER=1"])
    except KernelBuildError as exc:
        lines = [line.strip() for line in exc.log.splitlines() if line.strip()]
        errors = [line for line in lines if "error" in line.lower()] or lines or ["no log"]
        parts = dict.fromkeys(part.strip() for part in errors[0].split(" - "))  # pyopencl
        return " - ".join(parts)[:200]                          # repeats its message per device
    return None
