"""Make OpenCL CPU runtimes that pip installed, and GPU drivers installed without their
ICD file, visible to the OpenCL loader.

pyopencl's wheels carry their own ICD loader (ocl-icd). It reads the ICD files of
``/etc/OpenCL/vendors`` (or of the folder ``OCL_ICD_VENDORS`` names) and those next to
itself, which is how the PoCL wheel registers. Intel's CPU runtime from PyPI
(``intel-opencl-rt``, the ``intel`` extra) installs its library into the environment but
its ICD file names the path of the machine it was built on, so the loader never finds it.

:func:`register_pip_runtimes` writes a vendors folder that holds the ICD files the
loader would have read (the system's and the environment's own), one naming each
pip-installed runtime by its real path and one naming each GPU vendor's OpenCL library
found on the machine that no ICD file names (:func:`gpu_libraries`: a container given
NVIDIA's driver libraries without ``/etc/OpenCL/vendors/nvidia.icd``, as the lent H200
of 2026-12-04 was, would otherwise run every kernel on a CPU), and points
``OCL_ICD_VENDORS`` at it. It must run before the process first lists OpenCL platforms
(the loader reads its configuration once); :mod:`plenocl.opencl.device` calls it before every
listing, so plenocl's own entry points need nothing else. A user's own
``OCL_ICD_VENDORS`` is respected and left alone; ``PLENOCL_PIP_RUNTIMES=0`` turns the
registration off (the name is older than the GPU libraries: it turns both off), and
``PLENOCL_GPU_LIBRARIES=0`` the GPU libraries' alone.

A GPU library counts as registered when any ICD file of those folders names a library of
its name (in any folder or version, or by bare file name, which the loader then looks
up itself); the ICD files the loader may read elsewhere (one beside the loader itself,
``OCL_ICD_FILENAMES``) are not looked at, so a library named only there could be listed
twice.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from importlib import metadata
from pathlib import Path

#: The ICD folders a loader reads by default, which ``OCL_ICD_VENDORS`` replaces once
#: it is set: the system's, and the environment's own (conda's loader reads that one).
SYSTEM_VENDORS = (Path("/etc/OpenCL/vendors"), Path(sys.prefix) / "etc" / "OpenCL" / "vendors")

#: pip distributions that carry an OpenCL runtime library, and that library's file name.
PIP_RUNTIMES = {"intel-opencl-rt": "libintelocl.so"}

#: GPU vendors' OpenCL libraries by the file name their drivers install.
GPU_LIBRARIES = {"NVIDIA": "libnvidia-opencl.so.1", "AMD": "libamdocl64.so",
                 "Intel GPU": "libigdrcl.so"}

#: Folders searched for :data:`GPU_LIBRARIES` after ``LD_LIBRARY_PATH``'s: the NVIDIA
#: container toolkit's, ROCm's and the distributions' library folders. Only a library
#: built for this interpreter's word size and processor is taken (the toolkit's
#: ``/usr/local/nvidia/lib`` holds 32-bit ones).
GPU_LIBRARY_FOLDERS = (Path("/usr/local/nvidia/lib64"), Path("/opt/rocm/lib"),
                       Path("/usr/lib/x86_64-linux-gnu"), Path("/usr/lib/aarch64-linux-gnu"),
                       Path("/usr/lib64"), Path("/usr/lib"))

#: Set to ``0`` to keep plenocl from registering any runtime or driver.
SWITCH = "PLENOCL_PIP_RUNTIMES"

#: Set to ``0`` to keep plenocl from registering GPU libraries (pip's runtimes still are).
GPU_SWITCH = "PLENOCL_GPU_LIBRARIES"

_registered: list[Path] | None = None


def pip_runtime_libraries() -> list[Path]:
    """The OpenCL runtime libraries installed by pip into this environment."""
    found = []
    for dist_name, lib_name in PIP_RUNTIMES.items():
        try:
            dist = metadata.distribution(dist_name)
        except metadata.PackageNotFoundError:
            continue
        for entry in dist.files or ():
            path = Path(dist.locate_file(entry)).resolve()
            if entry.name == lib_name and path.is_file():
                found.append(path)
    return found


def vendor_files(libraries: list[Path], folders=SYSTEM_VENDORS) -> dict[str, str]:
    """The ICD files a vendors folder needs: those of the default ``folders``, then one
    per library.

    Returns ``{file name: content}``. A file naming an absolute path that does not exist
    is left out (Intel's wheel installs one naming its build machine); a library already
    registered (same content) is not listed twice.
    """
    files: dict[str, str] = {}
    for folder in [Path(f) for f in ([folders] if isinstance(folders, (str, Path))
                                     else folders)]:
        for icd in sorted(folder.glob("*.icd")) if folder.is_dir() else []:
            try:
                content = icd.read_text()
            except OSError:
                continue  # an unreadable vendor file: the loader would skip it too
            target = content.strip()
            if target.startswith("/") and not Path(target).exists():
                continue
            if content not in files.values():
                files[icd.name if icd.name not in files else f"{folder.name}-{icd.name}"] = \
                    content
    known = {content.strip() for content in files.values()}
    for lib in libraries:
        if str(lib) not in known:
            files[f"plenocl-pip-{lib.stem}.icd"] = f"{lib}\n"
    return files


def gpu_libraries(folders=None) -> list[Path]:
    """The GPU vendors' OpenCL libraries (:data:`GPU_LIBRARIES`) in ``folders`` (default:
    ``LD_LIBRARY_PATH``'s, then :data:`GPU_LIBRARY_FOLDERS`), each the first found that
    this interpreter could load (:func:`same_machine`), as an absolute path."""
    if folders is None:
        paths = os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep)
        folders = [Path(p) for p in paths if p] + list(GPU_LIBRARY_FOLDERS)
    found = []
    for name in GPU_LIBRARIES.values():
        hits = (Path(os.path.abspath(Path(folder) / name)) for folder in folders)
        first = next((hit for hit in hits if hit.is_file() and same_machine(hit)), None)
        if first is not None:
            found.append(first)
    return found


def same_machine(library: Path, reference: Path | None = None) -> bool:
    """Whether ``library`` is an ELF file of the word size and processor of
    ``reference`` (default: this Python's executable), which its process could load."""
    def header(path: Path) -> bytes:
        try:
            with open(path, "rb") as f:
                head = f.read(20)
        except OSError:
            return b""
        return head if head[:4] == b"\x7fELF" and len(head) == 20 else b""

    ours, theirs = header(Path(reference or sys.executable)), header(library)
    # byte 4: 32 or 64 bit, byte 5: byte order, bytes 18-19: the processor
    return bool(ours and theirs) and (ours[4:6], ours[18:20]) == (theirs[4:6], theirs[18:20])


def _library_key(text: str) -> str:
    """A library's name without folder and version (``libnvidia-opencl``), whether an ICD
    file names it by path or by file name."""
    return Path(text.strip()).name.split(".so")[0]


def unregistered(libraries: list[Path], files: dict[str, str]) -> list[Path]:
    """Those of ``libraries`` that no ICD file of ``files`` (``{name: content}``) names,
    in any folder or version."""
    named = {_library_key(content) for content in files.values()}
    return [lib for lib in libraries if _library_key(str(lib)) not in named]


def registered_gpu_libraries() -> list[Path]:
    """The GPU libraries :func:`register_pip_runtimes` registered because no ICD file
    named them (empty before it ran)."""
    return [lib for lib in _registered or [] if lib.name in GPU_LIBRARIES.values()]


def write_vendors(files: dict[str, str], root: Path | None = None) -> Path:
    """A vendors folder holding ``files``, named by their content (written once, atomically).

    It lives in a per-user folder of the system's temporary directory; a folder with the
    same content is reused, so repeated runs and worker processes share one.
    """
    digest = hashlib.sha256(repr(sorted(files.items())).encode()).hexdigest()[:16]
    base = root or Path(tempfile.gettempdir()) / f"plenocl-icd-{os.getuid()}"
    target = base / digest
    if target.is_dir():
        return target
    base.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=base))
    for name, content in files.items():
        (staging / name).write_text(content)
    try:
        staging.rename(target)
    except OSError:  # another process wrote the same folder first
        for f in staging.iterdir():
            f.unlink()
        staging.rmdir()
    return target


def register_pip_runtimes() -> list[Path]:
    """Point the OpenCL loader at pip-installed runtimes and at GPU libraries no ICD
    file names; return the libraries registered.

    Does nothing (returns ``[]``) when ``OCL_ICD_VENDORS`` is already set, when
    ``PLENOCL_PIP_RUNTIMES=0``, or when there is nothing to add. Idempotent.
    """
    global _registered
    if _registered is not None:
        return _registered
    _registered = []
    if os.environ.get("OCL_ICD_VENDORS") or os.environ.get(SWITCH, "1") == "0":
        return _registered
    libraries = pip_runtime_libraries()
    files = vendor_files(libraries)
    gpus = ([] if os.environ.get(GPU_SWITCH, "1") == "0"
            else unregistered(gpu_libraries(), files))
    if libraries or gpus:
        files.update({f"plenocl-gpu-{_library_key(str(lib))}.icd": f"{lib}\n"
                      for lib in gpus})
        os.environ["OCL_ICD_VENDORS"] = str(write_vendors(files))
        _registered = libraries + gpus
    return _registered
