"""Make OpenCL CPU runtimes that pip installed visible to the OpenCL loader.

pyopencl's wheels carry their own ICD loader (ocl-icd). It reads the ICD files of
``/etc/OpenCL/vendors`` (or of the folder ``OCL_ICD_VENDORS`` names) and those next to
itself, which is how the PoCL wheel registers. Intel's CPU runtime from PyPI
(``intel-opencl-rt``, the ``intel`` extra) installs its library into the environment but
its ICD file names the path of the machine it was built on, so the loader never finds it.

:func:`register_pip_runtimes` writes a vendors folder that holds the ICD files the
loader would have read (the system's and the environment's own) and one naming each
pip-installed runtime by its real path, and points
``OCL_ICD_VENDORS`` at it. It must run before the process first lists OpenCL platforms
(the loader reads its configuration once); :mod:`plenocl.opencl.device` calls it before every
listing, so plenocl's own entry points need nothing else. A user's own
``OCL_ICD_VENDORS`` is respected and left alone; ``PLENOCL_PIP_RUNTIMES=0`` turns the
registration off.
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

#: Set to ``0`` to keep plenocl from registering pip-installed runtimes.
SWITCH = "PLENOCL_PIP_RUNTIMES"

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
    """Point the OpenCL loader at pip-installed runtimes; return the libraries registered.

    Does nothing (returns ``[]``) when ``OCL_ICD_VENDORS`` is already set, when
    ``PLENOCL_PIP_RUNTIMES=0``, or when no such runtime is installed. Idempotent.
    """
    global _registered
    if _registered is not None:
        return _registered
    _registered = []
    if os.environ.get("OCL_ICD_VENDORS") or os.environ.get(SWITCH, "1") == "0":
        return _registered
    libraries = pip_runtime_libraries()
    if libraries:
        os.environ["OCL_ICD_VENDORS"] = str(write_vendors(vendor_files(libraries)))
        _registered = libraries
    return _registered
