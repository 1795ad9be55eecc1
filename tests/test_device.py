"""Device selection, capability probing, program building and kernel discovery."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import plenocl
from plenocl.opencl import device
from plenocl.opencl.program import (
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


def test_no_platform_names_the_cpu_extra(monkeypatch):
    monkeypatch.setattr(cl, "get_platforms", lambda: [])
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    with pytest.raises(plenocl.NoOpenCLError, match=r'pip install "plenocl\[cpu\]"'):
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


def test_unknown_cpu_build_failure_names_the_fix(monkeypatch):
    """The fix, Intel's runtime from pip, is suggested only where it is missing; where it
    is installed the note says it serves instead."""
    import plenocl.opencl.build as build

    log = "error: unknown target CPU 'generic'\nDevice pthread-AMD EPYC failed to build"
    monkeypatch.setattr(build, "pip_runtime_libraries", lambda: [])
    hint = build_hint(log)
    assert "plenocl[cpu]" in hint and "intel-opencl-rt" in hint and "plenocl devices" in hint
    assert build_hint("error: use of undeclared identifier 'x'") == ""
    monkeypatch.setattr(build, "pip_runtime_libraries", lambda: ["libintelocl.so"])
    note = build_hint(log)
    assert "pip install" not in note and "Intel's CPU runtime, installed" in note


def test_kernels_found_from_installed_package_and_from_checkout():
    assert (kernel_dir() / "simulate.cl").is_file()
    checkout = Path(__file__).resolve().parents[1]
    # the checkout first; the rest of the path kept (pyopencl may live elsewhere)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        filter(None, [str(checkout), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, "-c",
                          "import plenocl.opencl.program as p; print(p.kernel_dir())"],
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
    ks = KernelSet(queue, "solver.cl", ["row_extent", "partial_sums"],
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
        KernelSet(queue, "solver.cl", ["row_extent"], looping=["ratio"])



def test_an_upload_copies_now_and_does_not_wait_for_the_queue(queue):
    """``arrays.upload`` copies the host array as its buffer is made: it returns while
    the queue is held by an unfinished event (pyopencl's blocking write would wait for
    it), changing the host array afterwards changes nothing on the device, and the copy
    keeps the array's shape and dtype, any layout made contiguous."""
    import threading

    from plenocl.opencl.arrays import upload

    own = cl.CommandQueue(queue.context, queue.device)
    held = cl.UserEvent(queue.context)
    cl.enqueue_barrier(own, wait_for=[held])
    host = np.arange(60, dtype=np.float64).reshape(3, 4, 5)  # contiguous: its own memory
    want = host.copy()
    done = {}
    worker = threading.Thread(target=lambda: done.setdefault("dev", upload(own, host)))
    try:
        worker.start()
        worker.join(timeout=20)
        assert "dev" in done, "the upload waited for the queue"
        host[...] = -1.0
    finally:
        held.set_status(cl.command_execution_status.COMPLETE)
        worker.join()
    dev = done["dev"]
    assert dev.shape == want.shape and dev.dtype == want.dtype
    assert np.array_equal(dev.get(), want)
    # any layout and shape, a 0-d array's included, as pyopencl's own copy keeps them
    for other in (want[:, ::2], want.T, np.float32(2.5) * np.ones(()), np.arange(4) > 1):
        dev = upload(queue, other)
        assert dev.shape == other.shape and dev.dtype == other.dtype
        assert np.array_equal(dev.get(), other)


def test_kept_uploads_go_up_again_only_when_an_array_changes(queue):
    """``KeptUpload`` returns device copies of what it is given, converted to its type;
    given equal arrays again (a new object, another type) it returns the kept copies
    without an upload; a changed value, shape, ``None`` or count of arrays uploads anew."""
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.opencl.arrays import KeptUpload

    kept = KeptUpload(queue, np.float64)
    a, b = np.arange(6, dtype=np.float32).reshape(2, 3), np.array([0.5, -2.0])
    first = kept(a, None, b)
    assert first[1] is None and first[0].dtype == np.float64
    assert np.array_equal(first[0].get(), a) and np.array_equal(first[2].get(), b)
    with OpenCLProfile() as prof:
        again = kept(a.astype(np.int64), None, b.copy())
    assert all(x is y for x, y in zip(again, first)) and not prof.calls
    changed_b = b.copy()
    changed_b[1] = 3.0
    for given in [(a, None, changed_b), (a.reshape(3, 2), None, b), (a, b, b), (a, None),
                  (a, None, b)]:
        got = kept(*given)
        assert got[0] is not first[0]  # uploaded anew
        for g, h in zip(got, given, strict=True):
            assert (g is None) == (h is None)
            assert h is None or np.array_equal(g.get(), h)


def test_queue_kept_tables_go_up_once_per_queue_and_name(queue):
    """``queue_kept`` gives every caller of one name the same device copy while the values
    are equal (NaN equal to NaN: a missing lens), without an upload; changed values, a
    new type or another name upload anew, and the name's copy is then the new one."""
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.opencl.arrays import queue_kept

    lenses = np.arange(12, dtype=np.float32).reshape(2, 3, 2)
    lenses[1, 2] = np.nan
    first = queue_kept(queue, "test.lenses", lenses)
    np.testing.assert_array_equal(first.get(), lenses)
    with OpenCLProfile() as prof:
        again = queue_kept(queue, "test.lenses", lenses.copy())
    assert again is first and not prof.calls
    changed = lenses.copy()
    changed[0, 0, 0] = -1.0
    for name, given in [("test.lenses", changed), ("test.lenses", changed.astype(np.float64)),
                        ("test.other", changed.astype(np.float64))]:
        got = queue_kept(queue, name, given)
        assert got is not first and got.dtype == given.dtype
        np.testing.assert_array_equal(got.get(), given)
        assert queue_kept(queue, name, given) is got


def test_reading_several_arrays_waits_once_and_gives_what_get_gives(queue):
    """``arrays.read`` returns each device array's ``.get()`` (any dtype and shape, an
    empty one and a leading slice included), waiting for the queue once for all of them
    (three ``.get()`` calls wait three times); a strided array is refused by name."""
    from plenocl.bench.clprofile import OpenCLProfile
    from plenocl.opencl.arrays import read, upload
    from plenocl.pipeline import StageClock

    hosts = [np.arange(7 * 5, dtype=np.float64).reshape(7, 5), np.array([3, -1], np.int32),
             np.zeros(0, np.float32), np.arange(10, dtype=np.float32)]
    devs = [upload(queue, h) for h in hosts]
    devs[-1] = devs[-1][2:6]
    devs[0] *= 2.0  # a kernel still in the array's events
    clock = StageClock()
    with OpenCLProfile() as prof, clock.stage("read"):
        got = read(*devs)
    for g, d in zip(got, devs, strict=True):
        want = d.get()
        assert g.dtype == want.dtype and np.array_equal(g, want)
    assert np.array_equal(got[0], 2 * hosts[0])
    assert prof.split(clock.spans)["read"].waits == 1
    with pytest.raises(ValueError, match="contiguous"):
        read(devs[0][:, ::2])


def test_kernels_are_fetched_once_per_thread_and_never_shared_across_threads(queue):
    """Two sets of one program in one thread share its kernel objects (fetched once);
    another thread launching the same set gets its own, and two threads adding into
    their own arrays at once through one set each get NumPy's sums; an unknown name is
    refused by name."""
    import threading

    import pyopencl.array as cla

    from plenocl.opencl.program import fetch_kernels

    first = KernelSet(queue, "solver.cl", ["add_into"])
    second = KernelSet(queue, "solver.cl", ["add_into", "row_extent"])
    assert first.kernel("add_into") is second.kernel("add_into")
    program = build_program(queue.context, "solver.cl")
    assert fetch_kernels(program, ["add_into"])["add_into"] is first.kernel("add_into")
    seen, sums = {}, {}

    def work(k: int) -> None:
        queue_k = cl.CommandQueue(queue.context, queue.device)
        seen[k] = first.kernel("add_into")
        n = 1000 + 7 * k
        a = cla.to_device(queue_k, np.zeros(n, np.float32))
        b = cla.to_device(queue_k, np.arange(n, dtype=np.float32))
        for _ in range(50):
            first.kernel("add_into")(queue_k, (n,), None, a.data, b.data, np.int32(n))
        sums[k] = a.get(queue_k)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen[0] is not seen[1] and first.kernel("add_into") not in (seen[0], seen[1])
    for k in range(2):
        np.testing.assert_array_equal(sums[k], 50 * np.arange(1000 + 7 * k, dtype=np.float32))
    with pytest.raises(KeyError, match="not among"):
        first.launch("ratio", (1,))

def test_a_kernel_set_builds_a_source_text_against_todays_headers(queue):
    """``source=`` builds a file's text from elsewhere (a revision a benchmark compares),
    its ``#include`` served by today's headers, cached by its text: another text under the
    same name is another program."""
    from plenocl.opencl.build import kernel_dir

    text = (kernel_dir() / "sightline.cl").read_text()
    doubled = text.replace("out[2 * p] = total;", "out[2 * p] = 2.0f * total;")
    assert doubled != text
    vol = np.ones((4, 4, 4), np.float32)
    sums = []
    for source in (text, doubled):
        ks = KernelSet(queue, "sightline.cl", ["tube_sums"], ["-DPL_GROUP=1"],
                       looping=["tube_sums"], source=source)
        out = ks.array(2)
        ks.launch("tube_sums", (1,), ks.to_device(vol), np.int32(4), np.int32(4),
                  np.int32(4), ks.to_device(np.full(3, 1.5, np.float32)),
                  ks.to_device(np.eye(3, dtype=np.float32)),
                  ks.to_device(np.zeros((1, 3), np.float32)), np.int32(1), out,
                  local_size=(1,))
        sums.append(out.get()[0])
    assert sums == [1.0, 2.0]


# ---- the default device: preference order, build probe, fallback -------------------------
class FakePlatform:
    def __init__(self, name: str) -> None:
        self.name = name


class FakeDevice:
    """What the default choice reads of a device: type, name, platform name."""

    def __init__(self, name: str, kind: int, platform: str) -> None:
        self.name, self.type, self.platform = name, kind, FakePlatform(platform)


GPU, CPU = cl.device_type.GPU, cl.device_type.CPU
POCL, INTEL = "Portable Computing Language", "Intel(R) OpenCL"


def _fake_devices(monkeypatch, devices, broken):
    monkeypatch.setattr(device, "all_devices", lambda: list(devices))
    monkeypatch.setattr(device, "build_problem",
                        lambda d: "unknown target CPU 'generic'" if d.name in broken else None)


def test_preference_puts_gpus_first_then_cpu_runtimes_in_measured_order():
    devs = [FakeDevice("acc", cl.device_type.ACCELERATOR, "X"), FakeDevice("p", CPU, POCL),
            FakeDevice("other", CPU, "Some CPU"), FakeDevice("i", CPU, INTEL),
            FakeDevice("g", GPU, "NVIDIA CUDA")]
    order = [d.name for d in sorted(devs, key=device.preference)]
    ranked = [p for p in device.CPU_PLATFORMS if p in (POCL, INTEL)]
    cpus = ["i" if p == INTEL else "p" for p in ranked]
    assert order == ["g", *cpus, "other", "acc"]


def test_default_passes_over_a_device_that_cannot_build_and_says_so_once(monkeypatch):
    """A GPU that cannot build, passed over for a CPU: one line, once per process."""
    first, second = FakeDevice("gpu", GPU, "NVIDIA CUDA"), FakeDevice("cpu", CPU, POCL)
    _fake_devices(monkeypatch, [second, first], broken={first.name})
    monkeypatch.setattr(device, "_SAID", set())
    monkeypatch.setattr(device, "_FALLBACK", {"note": None})
    with pytest.warns(device.DeviceFallbackWarning) as record:
        chosen = device._default_device()
        assert device._default_device() is chosen and device._default_device() is chosen
    assert chosen is second and len(record) == 1
    text = str(record[0].message)
    assert first.name in text and "cannot build" in text and "unknown target CPU" in text
    assert f"plenocl uses {second.name}" in text and "\n" not in text  # one line
    assert device.fallback_note() == text


def test_the_documented_cpu_fallback_is_not_warned_about(monkeypatch):
    """PoCL's wheel that cannot compile on this CPU, Intel's runtime chosen: the expected
    choice (README, "Choosing a device"), kept for -v but not warned about."""
    first, second = (FakeDevice(n, CPU, p) for n, p in
                     sorted([("pocl-cpu", POCL), ("intel-cpu", INTEL)],
                            key=lambda np_: device.CPU_PLATFORMS.index(np_[1])))
    _fake_devices(monkeypatch, [second, first], broken={first.name})
    monkeypatch.setattr(device, "_SAID", set())
    monkeypatch.setattr(device, "_FALLBACK", {"note": None})
    with warnings.catch_warnings():
        warnings.simplefilter("error", device.DeviceFallbackWarning)
        assert device._default_device() is second
    assert first.name in device.fallback_note() and "cannot build" in device.fallback_note()


def test_default_without_a_building_device_names_every_reason_and_the_fix(monkeypatch):
    devs = [FakeDevice("a", CPU, POCL), FakeDevice("b", GPU, "G")]
    _fake_devices(monkeypatch, devs, broken={"a", "b"})
    with pytest.raises(plenocl.NoOpenCLError) as err:
        device._default_device()
    text = str(err.value)
    assert "a on " in text and "b on " in text and 'pip install "plenocl[cpu]"' in text


def test_every_device_is_probed_and_the_default_is_named():
    text = plenocl.describe_devices()
    assert text.count("builds plenocl's kernels:") == len(device.all_devices())
    default = device._default_device()
    assert f"default: {default.name.strip()} on {default.platform.name.strip()}" in text
    assert device.build_problem(default) is None


def test_a_gpu_library_plenocl_registered_is_named_in_the_listing(monkeypatch):
    lib = Path("/usr/local/nvidia/lib64/libnvidia-opencl.so.1")
    listed = plenocl.describe_devices().count("registered by plenocl: ")
    assert listed == len(device.registered_gpu_libraries())
    monkeypatch.setattr(device, "registered_gpu_libraries", lambda: [lib])
    line = [t for t in plenocl.describe_devices().splitlines() if str(lib) in t]
    assert len(line) == 1 and line[0].startswith("registered by plenocl: ")


def test_queue_keeps_its_context_alive():
    """Intel's CPU runtime invalidates a context whose last handle is released although
    a queue still uses it: the queue plenocl makes holds its context."""
    import gc

    q = device.get_queue(device.all_devices()[0])
    gc.collect()
    assert q.context == q.plenocl_context and q.context.devices[0] == q.device


def test_every_choice_of_a_device_shares_its_one_context(monkeypatch):
    """A device chosen by name, as a Device, through PYOPENCL_CTX or by default gets the
    process's one context on it (a GPU driver gives every context its own memory and
    programs: a new one per piv3d call ran NVIDIA's driver out of memory)."""
    default = device.get_queue()
    dev = default.device
    platform = cl.get_platforms().index(dev.platform)
    monkeypatch.setenv("PYOPENCL_CTX", f"{platform}:{dev.platform.get_devices().index(dev)}")
    queues = [device.get_queue(), device.get_queue(), device.get_queue(dev),
              device.get_queue(profiling=True)]
    assert all(q.context == default.context for q in queues)
    assert len({q.int_ptr for q in queues}) == len(queues)  # still a new queue per call
    by_name = device.get_queue(dev.name.strip())  # the first device of that name
    assert by_name.context == device.get_queue(by_name.device).context


def _run(code: str, **env) -> subprocess.CompletedProcess:
    full = {**os.environ, **env}
    full.pop("PYOPENCL_CTX", None)
    return subprocess.run([sys.executable, "-c", code], env=full, capture_output=True,
                          text=True, timeout=300)


def test_a_driver_that_cannot_build_is_reported_with_a_real_failure(tmp_path):
    """PoCL made to fail every build (an invalid option through POCL_EXTRA_BUILD_FLAGS,
    as its LLVM fails on an unknown CPU) with no other driver: plenocl refuses with the
    reason and the fix instead of failing later in a kernel build."""
    code = ("import plenocl\ntry:\n    plenocl.get_queue()\nexcept plenocl.NoOpenCLError "
            "as e:\n    print('REFUSED', e)")
    out = _run(code, POCL_EXTRA_BUILD_FLAGS="-plenocl-test-bad-option",
               OCL_ICD_VENDORS=str(tmp_path), PLENOCL_PIP_RUNTIMES="0")
    assert "REFUSED" in out.stdout, out.stdout + out.stderr
    assert "cannot build its kernels" in out.stdout and "plenocl[cpu]" in out.stdout


def test_pocl_that_cannot_build_falls_back_to_intels_runtime_quietly(tmp_path):
    """The Zen 5 case as far as this machine can show it: PoCL fails every build, the
    system's drivers are hidden, and Intel's runtime from the cpu extra takes over, the
    documented choice: no warning, however many queues a script makes; without that
    runtime plenocl refuses."""
    code = ("import warnings, plenocl\nwarnings.simplefilter('always')\n"
            "try:\n    q = [plenocl.get_queue() for _ in range(4)][0]\n"
            "    print('USING', q.device.platform.name)\n"
            "except plenocl.NoOpenCLError as e:\n    print('REFUSED', e)")
    out = _run(code, POCL_EXTRA_BUILD_FLAGS="-plenocl-test-bad-option",
               OCL_ICD_VENDORS="", PLENOCL_PIP_RUNTIMES="1")
    from plenocl.opencl.icd import pip_runtime_libraries

    if pip_runtime_libraries():
        assert "USING Intel(R) OpenCL" in out.stdout, out.stdout + out.stderr
        assert "DeviceFallbackWarning" not in out.stderr, out.stderr
    else:
        assert "REFUSED" in out.stdout and "plenocl[cpu]" in out.stdout, out.stdout


def test_the_per_particle_group_size_is_a_checked_power_of_two(queue):
    """One rule for the per-particle reductions' work-groups (the fit's sums, the tube
    sums): 1 item on a CPU, GPU_GROUP elsewhere, a given size only if a power of two."""
    from plenocl.opencl.program import GPU_GROUP, group_size
    from plenocl.piv.tube import DeviceTubeSums

    cpu = bool(queue.device.type & cl.device_type.CPU)
    assert group_size(queue) == (1 if cpu else GPU_GROUP) and group_size(queue, 8) == 8
    for bad in (0, 3, 12):
        with pytest.raises(ValueError, match="power of two"):
            group_size(queue, bad)
    with pytest.raises(ValueError, match="power of two"):
        DeviceTubeSums(queue, 6)


def test_fill_sets_whole_arrays_and_leading_slices_only(queue):
    """``plenocl.opencl.arrays.fill`` (the driver's fill): a whole array, a slice along
    the first axis (its neighbours untouched), float32 and int32, NaN; a non-contiguous
    view is refused by name."""
    import pyopencl.array as cla

    from plenocl.opencl.arrays import fill

    vol = cla.to_device(queue, np.arange(7 * 5 * 3, dtype=np.float32).reshape(7, 5, 3))
    want = vol.get()
    fill(vol[2:5], 1.5)
    want[2:5] = 1.5
    np.testing.assert_array_equal(vol.get(), want)
    assert np.isnan(fill(vol, np.nan).get()).all()
    counts = fill(cla.empty(queue, 11, np.int32), 0)
    np.testing.assert_array_equal(counts.get(), np.zeros(11, np.int32))
    fill(vol[3:3], 2.0)  # empty: nothing enqueued
    with pytest.raises(ValueError, match="contiguous device array"):
        fill(vol[:, 1], 0.0)


def test_copy_region_cuts_numpys_box_on_the_device(queue):
    """``copy_region``: a box of one device volume written into another at a corner is
    NumPy's slice assignment, bit for bit; a box past either volume is refused by name."""
    import pyopencl.array as cla

    from plenocl.opencl.arrays import copy_region

    rng = np.random.default_rng(8)
    src = rng.random((6, 9, 11)).astype(np.float32)
    out = rng.random((4, 5, 13)).astype(np.float32)
    want = out.copy()
    want[1:4, 0:5, 6:13] = src[2:5, 3:8, 1:8]
    dev = cla.to_device(queue, out)
    copy_region(dev, (1, 0, 6), cla.to_device(queue, src), (2, 3, 1), (3, 5, 7))
    assert np.array_equal(dev.get(), want)
    with pytest.raises(ValueError, match="does not fit in the source"):
        copy_region(dev, (0, 0, 0), cla.to_device(queue, src), (4, 0, 0), (3, 5, 7))
    with pytest.raises(ValueError, match="does not fit in the target"):
        copy_region(dev, (2, 0, 0), cla.to_device(queue, src), (0, 0, 0), (3, 5, 7))


@pytest.mark.parametrize("out_depth, vol_depth", [(2, 3), (5, 1), (9, 9)])
def test_copy_slabbed_is_numpys_box_whatever_the_slabs(queue, out_depth, vol_depth):
    """``copy_slabbed``: a box of a volume held in depth slabs of one size, written into
    a volume held in slabs of another at a corner, is NumPy's slice assignment on the
    whole volumes, bit for bit, where the box crosses slab edges on both sides."""
    import pyopencl.array as cla

    from plenocl.opencl.arrays import copy_slabbed

    def slabbed(vol, depth):
        slabs = [(z, min(z + depth, len(vol))) for z in range(0, len(vol), depth)]
        return slabs, [cla.to_device(queue, np.ascontiguousarray(vol[a:b])) for a, b in slabs]

    rng = np.random.default_rng(out_depth + vol_depth)
    src, out = (rng.random((9, 6, 8)).astype(np.float32) for _ in range(2))
    want = out.copy()
    want[3:8, 1:5, 0:6] = src[1:6, 2:6, 2:8]
    (vol_slabs, vol), (out_slabs, dev) = slabbed(src, vol_depth), slabbed(out, out_depth)
    copy_slabbed(dev, out_slabs, (3, 1, 0), vol, vol_slabs, (1, 2, 2), (5, 4, 6))
    assert np.array_equal(np.concatenate([d.get() for d in dev]), want)


@pytest.mark.parametrize("shape,corner", [((6, 7, 9), (1, 2, 3)), ((3, 4, 5), (0, 0, 0)),
                                          ((9, 4, 13), (2, 0, 6))])
def test_inside_zeros_is_numpys_padding(queue, shape, corner):
    """``plenocl.opencl.arrays.inside_zeros``: a host or device volume placed at
    ``corner`` inside zeros is ``np.pad``'s constant padding, bit for bit (the fill reused
    over a stale buffer)."""
    import pyopencl.array as cla

    from plenocl.opencl.arrays import inside_zeros

    vol = np.random.default_rng(sum(shape)).random((3, 4, 5)).astype(np.float32)
    pads = [(c, n - c - v) for c, n, v in zip(corner, shape, vol.shape)]
    want = np.pad(vol, pads)
    for source in (vol, cla.to_device(queue, vol)):
        got = inside_zeros(queue, source, shape, corner)
        assert got.dtype == np.float32 and got.shape == shape
        assert np.array_equal(got.get(), want)


class _FakeDevice:
    """Enough of a ``pyopencl.Device`` for :func:`spread_device`: name, type, platform."""

    def __init__(self, name: str, kind, platform: str) -> None:
        self.name, self.type = name, kind
        self.platform = type("Platform", (), {"name": platform})()


def test_workers_spread_over_the_devices_a_name_or_the_default_gives(monkeypatch):
    """Worker k takes the k-th (in turn) of the building devices a name matches; by
    default every GPU in turn, and on a machine without one the default device (never
    several CPU runtimes of one CPU); a name matching none, ``PYOPENCL_CTX`` and device
    objects stay as they are."""
    from plenocl.opencl import device as device_module
    from plenocl.opencl.device import spread_device

    gpus = [_FakeDevice("H100", cl.device_type.GPU, "NVIDIA CUDA") for _ in range(2)]
    cpus = [_FakeDevice("EPYC", cl.device_type.CPU, p) for p in ("Portable", "Intel")]
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setattr(device_module, "building_devices", lambda: (gpus + cpus, []))
    monkeypatch.setattr(device_module, "all_devices", lambda: gpus + cpus)
    assert [spread_device(None, k) for k in range(5)] == [gpus[0], gpus[1]] * 2 + [gpus[0]]
    assert [spread_device("cpu", k) for k in range(3)] == [cpus[0], cpus[1], cpus[0]]
    assert [spread_device("intel", k) for k in range(2)] == [cpus[1], cpus[1]]
    assert spread_device("nothing like it", 3) == "nothing like it"
    assert spread_device(cpus[1], 0) is cpus[1]
    monkeypatch.setattr(device_module, "all_devices", lambda: cpus)
    monkeypatch.setattr(device_module, "building_devices", lambda: 1 / 0)  # not probed
    assert spread_device(None, 1) is None  # the default device
    monkeypatch.setattr(device_module, "all_devices", lambda: gpus + cpus)
    monkeypatch.setattr(device_module, "building_devices", lambda: (gpus[1:] + cpus, []))
    assert spread_device(None, 1) is gpus[1]  # a GPU that cannot build is passed over
    monkeypatch.setenv("PYOPENCL_CTX", "0")
    assert spread_device(None, 1) is None  # PYOPENCL_CTX's rules


def test_a_dask_workers_number_comes_from_its_name():
    from plenocl.batch.cluster import worker_number

    assert [worker_number(n) for n in (0, 7, "3", "SLURMCluster-12", "tcp://a:1/", "x")] \
        == [0, 7, 3, 12, 0, 0]


def test_device_labels_tell_devices_apart():
    from plenocl.opencl.device import all_devices, device_label

    devices = all_devices()
    labels = [device_label(d) for d in devices]
    assert len(set(labels)) == len(devices)
    assert all(d.name.strip() in label for d, label in zip(devices, labels, strict=True))
