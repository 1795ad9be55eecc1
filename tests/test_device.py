"""Device selection, capability probing, program building and kernel discovery."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import plenocl
from plenocl import device
from plenocl.program import (
    KernelBuildError,
    KernelSet,
    build_hint,
    build_program,
    kernel_dir,
)


def test_devices_are_listed_with_capabilities():
    text = plenocl.describe_devices()
    assert "fp64" in text and "64-bit atomics" in text and "GiB" in text
    info = device.DeviceInfo.probe(device.all_devices()[0])
    assert info.global_mem_bytes > 0 and info.opencl_version.startswith("OpenCL")


def test_explicit_choice_by_type_and_clear_error_for_no_match():
    dev = device.all_devices()[0]
    kind = cl.device_type.to_string(dev.type).split()[0].lower()
    assert device.create_context(kind).devices[0].type & dev.type
    with pytest.raises(plenocl.NoOpenCLError, match="no OpenCL device matches"):
        device.create_context("no-such-device-xyz")


def test_queue_passes_through_and_wraps_contexts(queue):
    assert device.get_queue(queue) is queue
    assert device.get_queue(queue.context).context == queue.context


def test_no_platform_names_the_pocl_extra(monkeypatch):
    monkeypatch.setattr(cl, "get_platforms", lambda: [])
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    with pytest.raises(plenocl.NoOpenCLError, match=r'pip install "plenocl\[pocl\]"'):
        device.create_context()


def test_memory_check_states_the_need(queue):
    with pytest.raises(MemoryError, match="GiB of device memory"):
        device.check_fits(queue, 1 << 50, "a test volume")


def test_program_is_built_once_per_context(queue):
    a = build_program(queue.context, "simulate.cl")
    assert build_program(queue.context, "simulate.cl") is a


def test_build_failure_reports_file_options_and_log(queue):
    with pytest.raises(KernelBuildError) as err:
        build_program(queue.context, "simulate.cl", ["-Dpl_hash=syntax error("])
    text = str(err.value)
    assert "simulate.cl" in text and "-Dpl_hash" in text and "compiler log" in text


def test_unknown_cpu_build_failure_names_the_fix():
    log = "error: unknown target CPU 'generic'\nDevice pthread-AMD EPYC failed to build"
    hint = build_hint(log)
    assert "pocl-opencl-icd" in hint and "PYOPENCL_CTX" in hint
    assert build_hint("error: use of undeclared identifier 'x'") == ""


def test_kernels_found_from_installed_package_and_from_checkout():
    assert (kernel_dir() / "simulate.cl").is_file()
    checkout = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    out = subprocess.run([sys.executable, "-c",
                          "import plenocl.program as p; print(p.kernel_dir())"],
                         cwd=checkout, env=env, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()) == checkout / "kernels"


def test_design_public_api_names_exist():
    """docs/design.md §9: the names tests and users rely on, at the top level."""
    for name in ("Camera", "Grid", "simulate_image", "simulate_white_image", "calibrate",
                 "Projector", "reconstruct", "piv3d"):
        assert callable(getattr(plenocl, name)), name
    for method in ("from_toml", "to_toml"):
        assert callable(getattr(plenocl.Camera, method))
    for method in ("forward", "back", "voxel_weights"):
        assert callable(getattr(plenocl.Projector, method))


def test_kernel_set_launches_with_arrays_and_the_cpu_rule(queue):
    """The launch layer unwraps device arrays, fetches each kernel once and runs it; the
    row extents it returns are the NumPy ones, on an awkward size."""
    ks = KernelSet(queue, "reconstruct.cl", ["row_extent", "partial_sums"],
                   looping=["partial_sums"])
    assert ks.is_cpu == bool(queue.device.type & cl.device_type.CPU)
    vol = np.zeros((3, 5, 7), np.float32)
    vol[1, 2, 3:6] = 1.0
    vol[2, 4, 0] = 2.0
    out = ks.array((3, 5, 2), np.int32)
    ks.launch("row_extent", (15,), ks.to_device(vol), np.int32(7), out, np.int32(15))
    ext = out.get()
    assert tuple(ext[1, 2]) == (3, 5) and tuple(ext[2, 4]) == (0, 0)
    assert tuple(ext[0, 0]) == (7, -1)
    with pytest.raises(ValueError, match="not among"):
        KernelSet(queue, "reconstruct.cl", ["row_extent"], looping=["ratio"])
