"""Registration of pip-installed OpenCL runtimes with the loader (plenocl.opencl.icd)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from plenocl.opencl import icd


def test_vendor_files_keep_the_system_drivers_and_add_each_library_once(tmp_path):
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    (system / "notes.txt").write_text("not an ICD file")
    lib = tmp_path / "lib" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    files = icd.vendor_files([lib], system)
    assert files == {"pocl.icd": "libpocl.so.2\n", "plenocl-pip-libintelocl.icd": f"{lib}\n"}
    (system / "intel.icd").write_text(f"{lib}\n")  # the system registers it already
    assert sorted(icd.vendor_files([lib], system)) == ["intel.icd", "pocl.icd"]
    assert icd.vendor_files([], tmp_path / "absent") == {}


def test_vendors_folder_is_written_once_per_content_and_reused(tmp_path):
    files = {"a.icd": "/x/liba.so\n", "b.icd": "libb.so\n"}
    first = icd.write_vendors(files, tmp_path)
    assert {p.name: p.read_text() for p in first.iterdir()} == files
    assert icd.write_vendors(dict(reversed(files.items())), tmp_path) == first
    other = icd.write_vendors({"a.icd": "/y/liba.so\n"}, tmp_path)
    assert other != first and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def _platforms_in_child(**env) -> dict:
    code = ("import json, os, pyopencl as cl\nfrom plenocl.opencl import icd\n"
            "libs = [str(p) for p in icd.register_pip_runtimes()]\n"
            "gpus = [str(p) for p in icd.registered_gpu_libraries()]\n"
            "print(json.dumps({'libs': libs, 'gpus': gpus, "
            "'vendors': os.environ.get('OCL_ICD_VENDORS'), "
            "'platforms': [p.name.strip() for p in cl.get_platforms()]}))")
    # this process registered already (OCL_ICD_VENDORS set by plenocl): start clean
    full = {k: v for k, v in os.environ.items() if k not in ("OCL_ICD_VENDORS", "PYOPENCL_CTX")}
    out = subprocess.run([sys.executable, "-c", code], env={**full, **env}, capture_output=True,
                         text=True, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_pip_runtimes_become_platforms_and_a_users_folder_is_respected(tmp_path):
    """Each pip-installed runtime is registered and listed by the loader; a user's own
    OCL_ICD_VENDORS (here an empty folder) is left alone, and so nothing is added."""
    expected = [str(p) for p in icd.pip_runtime_libraries()]
    mine = _platforms_in_child(OCL_ICD_VENDORS=str(tmp_path))
    assert mine["libs"] == [] and mine["vendors"] == str(tmp_path)
    assert "Intel(R) OpenCL" not in mine["platforms"]
    off = _platforms_in_child(PLENOCL_PIP_RUNTIMES="0")
    assert off["libs"] == [] and off["vendors"] is None
    auto = _platforms_in_child()
    assert auto["libs"] == expected + auto["gpus"]  # a GPU library no ICD file names too
    if expected:  # the cpu extra installs Intel's runtime: it must become a platform
        assert "Intel(R) OpenCL" in auto["platforms"]
        folder = Path(auto["vendors"])
        assert any(expected[0] in p.read_text() for p in folder.glob("*.icd"))


def test_the_environments_own_vendors_are_kept_and_dangling_ones_dropped(tmp_path):
    """A conda-like environment folder of ICD files is kept beside the system's; a file
    naming a library that does not exist (Intel's wheel ships one naming its build
    machine) is dropped."""
    system, env = tmp_path / "etc", tmp_path / "env"
    system.mkdir()
    env.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    real = tmp_path / "libreal.so"
    real.write_bytes(b"")
    (env / "real.icd").write_text(f"{real}\n")
    (env / "intel-cpu.icd").write_text("/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so\n")
    (env / "pocl.icd").write_text("libpocl.so.2\n")  # the same driver: once
    files = icd.vendor_files([], (system, env))
    assert sorted(files.values()) == sorted(["libpocl.so.2\n", f"{real}\n"])


def _library(folder: Path, name: str, bits: int = 0) -> Path:
    """A file named like a library whose ELF header is this Python's (``bits`` 32: a
    32-bit one's): taken for one it could load, which the loader cannot."""
    folder.mkdir(parents=True, exist_ok=True)
    head = bytearray(Path(sys.executable).read_bytes()[:20])
    if bits == 32:
        head[4] = 1
    (folder / name).write_bytes(bytes(head) + bytes(44))
    return folder / name


def test_gpu_libraries_are_found_in_the_first_folder_holding_each(tmp_path):
    """... of this interpreter's word size (the NVIDIA container toolkit's 32-bit folder
    comes first on its images' LD_LIBRARY_PATH) and not a file that is no library."""
    lib32, first, second = tmp_path / "lib", tmp_path / "first", tmp_path / "second"
    _library(lib32, "libnvidia-opencl.so.1", bits=32)
    (first / "libamdocl64.so").parent.mkdir()
    (first / "libamdocl64.so").write_text("not a library")
    nvidia = _library(first, "libnvidia-opencl.so.1")
    _library(second, "libnvidia-opencl.so.1")
    amd = _library(second, "libamdocl64.so")
    _library(second, "libnvidia-opencl.so.580.1")  # another version's file: not asked for
    assert icd.gpu_libraries([lib32, first, second]) == [nvidia, amd]
    assert icd.gpu_libraries([tmp_path / "absent"]) == []
    assert not icd.same_machine(lib32 / "libnvidia-opencl.so.1")


def test_a_gpu_library_is_registered_only_where_no_icd_file_names_it(tmp_path):
    """An ICD file naming the library by file name, by another folder's path or by
    another version keeps it out; a file naming another library does not."""
    lib = _library(tmp_path / "lib64", "libnvidia-opencl.so.1")
    assert icd.unregistered([lib], {"pocl.icd": "libpocl.so.2\n"}) == [lib]
    for named in ("libnvidia-opencl.so.1\n", "/usr/lib/libnvidia-opencl.so.1\n",
                  "libnvidia-opencl.so.580.159.04\n"):
        assert icd.unregistered([lib], {"nvidia.icd": named}) == []


def test_a_gpu_library_no_icd_names_is_registered_and_listing_survives_it(tmp_path):
    """A driver library found on LD_LIBRARY_PATH but named by no ICD file (here a file
    the loader cannot load) is put in plenocl's vendors folder and reported; the loader
    skips it, so the platforms listed are the same, none twice. PLENOCL_GPU_LIBRARIES=0
    leaves it out."""
    lib = _library(tmp_path / "driver", "libnvidia-opencl.so.1")
    path = os.pathsep.join([str(lib.parent)] + [p for p in
                                                [os.environ.get("LD_LIBRARY_PATH")] if p])
    plain = _platforms_in_child(PLENOCL_PIP_RUNTIMES="0")
    given = _platforms_in_child(LD_LIBRARY_PATH=path)
    assert given["gpus"][0] == str(lib) and str(lib) in given["libs"]
    names = {p.name: p.read_text() for p in Path(given["vendors"]).glob("*.icd")}
    assert names["plenocl-gpu-libnvidia-opencl.icd"] == f"{lib}\n"
    assert [p for p in given["platforms"] if p != "Intel(R) OpenCL"] == plain["platforms"]
    off = _platforms_in_child(LD_LIBRARY_PATH=path, PLENOCL_GPU_LIBRARIES="0")
    assert off["gpus"] == [] and str(lib) not in off["libs"]
