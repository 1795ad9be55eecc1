"""OpenCL device selection and capability probing.

A device is chosen explicitly (a :class:`pyopencl.Device`, ``Context`` or
``CommandQueue``, or a name/type substring such as ``"gpu"``, ``"cpu"`` or
``"NVIDIA"``), else from the ``PYOPENCL_CTX`` environment variable, else by
default: the first device, in :func:`preference` order (GPUs, then PoCL, then Intel's
CPU runtime), that builds plenocl's kernels. A device passed over because it cannot
build them is named in a one-line :class:`DeviceFallbackWarning`, once per process,
unless the fallback is the documented one between CPU runtimes
(:func:`expected_fallback`; :func:`fallback_note` keeps it). There is no global
"current device": every object that runs kernels takes a queue or builds one here.

CPU runtimes installed by pip (Intel's, the ``intel`` extra), and GPU drivers' OpenCL
libraries that no ICD file names, are registered with the OpenCL loader before platforms
are first listed (:mod:`plenocl.opencl.icd`).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import pyopencl as cl

from .build import probe_build
from .icd import register_pip_runtimes, registered_gpu_libraries

DeviceLike = None | str | cl.Device | cl.Context | cl.CommandQueue

# Intel's CPU runtime logs progress on every successful build, which pyopencl turns into
# a CompilerWarning without content for each of its own element-wise kernels. Hidden;
# PYOPENCL_COMPILER_OUTPUT=1 still shows every log (as a differently worded warning).
warnings.filterwarnings("ignore", message="Non-empty compiler output encountered",
                        category=cl.CompilerWarning)

NO_OPENCL_HELP = (
    "no OpenCL platform was found on this machine. Install the CPU runtimes with: "
    'pip install "plenocl[cpu]"  (or install your GPU vendor\'s OpenCL driver)'
)

#: CPU platforms by preference; platforms not named come after. ``benchmarks/drivers.py``
#: found PoCL and Intel's runtime equally fast on plenocl's kernels (docs/results.md,
#: "Performance"), so the open one comes first and Intel's runtime serves where PoCL's
#: wheel cannot compile (AMD Zen 5: its LLVM 14 does not know the CPU).
CPU_PLATFORMS = ("Portable Computing Language", "Intel(R) OpenCL")


class NoOpenCLError(RuntimeError):
    """Raised when no OpenCL platform or no matching device is available."""


class DeviceFallbackWarning(UserWarning):
    """A preferred device was passed over because it cannot build plenocl's kernels."""


@dataclass(frozen=True)
class DeviceInfo:
    """What plenocl needs to know about a device, probed once."""

    name: str
    platform: str
    type: str
    global_mem_bytes: int
    max_alloc_bytes: int
    opencl_version: str
    fp64: bool
    int64_atomics: bool
    compute_units: int

    @classmethod
    def probe(cls, device: cl.Device) -> DeviceInfo:
        """Read the capabilities of ``device``."""
        ext = device.extensions.split()
        return cls(
            name=device.name.strip(),
            platform=device.platform.name.strip(),
            type=cl.device_type.to_string(device.type),
            global_mem_bytes=int(device.global_mem_size),
            max_alloc_bytes=int(device.max_mem_alloc_size),
            opencl_version=device.version.strip(),
            fp64="cl_khr_fp64" in ext,
            int64_atomics="cl_khr_int64_base_atomics" in ext,
            compute_units=int(device.max_compute_units),
        )


def _platforms() -> list[cl.Platform]:
    register_pip_runtimes()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:  # pyopencl raises LogicError when the ICD finds nothing
        raise NoOpenCLError(NO_OPENCL_HELP) from exc
    if not platforms:
        raise NoOpenCLError(NO_OPENCL_HELP)
    return platforms


def all_devices() -> list[cl.Device]:
    """Every OpenCL device on every platform."""
    devices = []
    for platform in _platforms():
        try:
            devices.extend(platform.get_devices())
        except cl.Error:
            continue  # a platform with no devices
    if not devices:
        raise NoOpenCLError(NO_OPENCL_HELP)
    return devices


def describe_devices() -> str:
    """A human-readable table of platforms and devices (``plenocl devices``)."""
    lines = []
    for i, platform in enumerate(_platforms()):
        lines.append(f"platform {i}: {platform.name.strip()} ({platform.version.strip()})")
        try:
            devices = platform.get_devices()
        except cl.Error:
            devices = []
        for j, dev in enumerate(devices):
            info = DeviceInfo.probe(dev)
            lines.append(
                f"  [{i}:{j}] {info.name}\n"
                f"        type {info.type}, {info.compute_units} compute units, "
                f"memory {info.global_mem_bytes / 2**30:.1f} GiB "
                f"(max buffer {info.max_alloc_bytes / 2**30:.1f} GiB)\n"
                f"        {info.opencl_version}; fp64 {'yes' if info.fp64 else 'no'}; "
                f"64-bit atomics {'yes' if info.int64_atomics else 'no'}\n"
                f"        builds plenocl's kernels: {_build_status(dev)}"
            )
    for lib in registered_gpu_libraries():
        lines.append(f"registered by plenocl: {lib} (a GPU driver's OpenCL library that no "
                     "ICD file named; if no platform above comes from it, the loader "
                     "could not use it: OCL_ICD_DEBUG=7 shows why, "
                     "PLENOCL_GPU_LIBRARIES=0 leaves it out)")
    lines.append(f"default: {_describe(_default_device())}")
    lines.append("choose one with PYOPENCL_CTX='<platform>:<device>' or device='<name or type>'")
    return "\n".join(lines)


def _build_status(device: cl.Device) -> str:
    problem = build_problem(device)
    return "yes" if problem is None else f"NO ({problem})"


def _describe(device: cl.Device) -> str:
    return f"{device.name.strip()} on {device.platform.name.strip()}"


def _matches(device: cl.Device, key: str) -> bool:
    """Whether a device-name or type substring ``key`` names ``device``."""
    key_l = key.lower()
    kind = cl.device_type.to_string(device.type).lower()
    return (key_l in device.name.lower() or key_l in kind
            or key_l in device.platform.name.lower())


def _match(devices: list[cl.Device], key: str) -> cl.Device:
    for dev in devices:
        if _matches(dev, key):
            return dev
    names = ", ".join(d.name.strip() for d in devices)
    raise NoOpenCLError(f"no OpenCL device matches {key!r}; available: {names}")


def device_label(device: cl.Device) -> str:
    """``device``'s name and platform, and where the machine has several alike its
    number among them (``"NVIDIA H100 on NVIDIA CUDA #1"``): what a run's summary counts
    its pairs by."""
    alike = [d for d in all_devices() if _describe(d) == _describe(device)]
    number = next((k for k, d in enumerate(alike) if d == device), 0)
    return _describe(device) + (f" #{number}" if len(alike) > 1 else "")


def spread_device(device: DeviceLike, index: int) -> DeviceLike:
    """The device of a run's worker number ``index`` (its Dask worker name): a name or
    type substring ``device`` takes the ``index mod n``-th of the ``n`` devices it names
    that build plenocl's kernels (``"gpu"``: every GPU of the machine in turn); ``None``
    (no ``PYOPENCL_CTX``) every GPU that builds them in turn, or the default where there
    is none (never several CPU runtimes of one CPU); anything else as it is."""
    if device is None and not any(d.type & cl.device_type.GPU for d in all_devices()):
        return None  # no GPU: the default device (no device probed here)
    if isinstance(device, str) or (device is None and not os.environ.get("PYOPENCL_CTX")):
        building = building_devices()[0]
        named = [d for d in building if (_matches(d, device) if isinstance(device, str)
                                         else d.type & cl.device_type.GPU)]
        if named:
            return named[index % len(named)]
    return device


def preference(device: cl.Device) -> tuple[int, int]:
    """Sort key of the default choice: GPUs first, then CPUs in :data:`CPU_PLATFORMS`
    order, then anything else."""
    if device.type & cl.device_type.GPU:
        return (0, 0)
    if device.type & cl.device_type.CPU:
        name = device.platform.name.strip()
        rank = CPU_PLATFORMS.index(name) if name in CPU_PLATFORMS else len(CPU_PLATFORMS)
        return (1, rank)
    return (2, 0)


# Per device, probed once a process: the context its probe built in (kept, so that the
# default choice reuses it and its built programs), or why it cannot build kernels.
_PROBED: dict[cl.Device, cl.Context | str] = {}


def _probe(device: cl.Device) -> cl.Context | str:
    if device not in _PROBED:
        try:
            ctx = cl.Context([device])
        except cl.Error as exc:  # the driver cannot even make a context
            _PROBED[device] = f"no context: {exc}"
        else:
            problem = probe_build(ctx)
            _PROBED[device] = ctx if problem is None else problem
    return _PROBED[device]


def build_problem(device: cl.Device) -> str | None:
    """Why ``device`` cannot build plenocl's kernels, or ``None`` when it can (probed
    once per process by building one kernel)."""
    probed = _probe(device)
    return probed if isinstance(probed, str) else None


def devices_by_preference() -> list[cl.Device]:
    """Every OpenCL device, in the order the default choice tries them."""
    return sorted(all_devices(), key=preference)


def building_devices() -> tuple[list[cl.Device], list[tuple[cl.Device, str]]]:
    """The devices that build plenocl's kernels, in preference order, and those that
    cannot, each with its driver's reason (:func:`build_problem`)."""
    building, failing = [], []
    for dev in devices_by_preference():
        problem = build_problem(dev)
        if problem is None:
            building.append(dev)
        else:
            failing.append((dev, problem))
    return building, failing


# The default choice's note when it passed a device over (None: it did not), and the
# notes already warned about: each is said once per process.
_FALLBACK: dict[str, str | None] = {"note": None}
_SAID: set[str] = set()


def fallback_note() -> str | None:
    """What this process's default device choice passed over and why (``None``: the
    first device built), also where no warning said it (``plenocl -v`` prints it)."""
    return _FALLBACK["note"]


def expected_fallback(chosen: cl.Device, passed_over: list[cl.Device]) -> bool:
    """Whether passing ``passed_over`` for ``chosen`` is the documented choice: CPU
    runtimes of :data:`CPU_PLATFORMS` only (PoCL's wheel cannot compile on a CPU its
    LLVM does not know, AMD Zen 5 say, and Intel's runtime serves: README, "Choosing a
    device"), which is not warned about."""
    def known_cpu(dev: cl.Device) -> bool:
        return is_cpu(dev) and dev.platform.name.strip() in CPU_PLATFORMS

    return known_cpu(chosen) and all(known_cpu(dev) for dev in passed_over)


def _say_fallback(chosen: cl.Device, passed_over: list[cl.Device], reasons: list[str]) -> None:
    """Record the fallback; warn once per process unless it is the expected one."""
    note = f"plenocl uses {_describe(chosen)}: " + "; ".join(reasons)
    _FALLBACK["note"] = note
    if note in _SAID or expected_fallback(chosen, passed_over):
        return
    _SAID.add(note)
    warnings.warn(note, DeviceFallbackWarning, stacklevel=5)


def _default_device() -> cl.Device:
    passed, skipped = [], []
    for dev in devices_by_preference():
        problem = build_problem(dev)
        if problem is None:
            if passed:
                _say_fallback(dev, skipped, passed)
            return dev
        skipped.append(dev)
        passed.append(f"{_describe(dev)} cannot build its kernels ({problem})")
    raise NoOpenCLError(
        "no OpenCL device here builds plenocl's kernels: " + "; ".join(passed)
        + '. Install a CPU runtime that does with: pip install "plenocl[cpu]" '
        "(docs/errors.md, 'cannot build its kernels')")


def create_context(device: DeviceLike = None) -> cl.Context:
    """Create an OpenCL context for an explicit device, ``PYOPENCL_CTX`` or the default.

    Parameters
    ----------
    device
        ``None`` (use ``PYOPENCL_CTX`` if set, else a GPU, else a CPU), a device-name or
        type substring (``"gpu"``, ``"cpu"``, ``"pthread"``), a ``pyopencl.Device``,
        ``Context`` or ``CommandQueue``.
    """
    if isinstance(device, cl.CommandQueue):
        return device.context
    if isinstance(device, cl.Context):
        return device
    if isinstance(device, cl.Device):
        return device_context(device)
    if isinstance(device, str):
        return device_context(_match(all_devices(), device))
    if device is not None:
        raise TypeError(f"device must be a name, Device, Context or CommandQueue, not {device!r}")
    if os.environ.get("PYOPENCL_CTX"):
        _platforms()  # a clear error first if nothing is installed
        chosen = cl.choose_devices(interactive=False)
        return device_context(chosen[0]) if len(chosen) == 1 else cl.Context(chosen)
    return device_context(_default_device())


def device_context(device: cl.Device) -> cl.Context:
    """The process's one context on ``device``: the one its build probe made, so every
    queue plenocl makes there shares it and its built programs.

    A GPU driver gives each context its own device memory and compiled programs: a
    context per call (``piv3d`` without a queue, in a loop) would build every kernel
    again and, on NVIDIA's driver, runs out of memory after a few dozen. A device whose
    probe failed gets a new context, so that its first build reports the driver's error.
    """
    probed = _probe(device)
    return probed if isinstance(probed, cl.Context) else cl.Context([device])


def get_queue(queue: DeviceLike = None, profiling: bool = False) -> cl.CommandQueue:
    """Return ``queue`` if it is a command queue, else a new queue on the chosen device."""
    if isinstance(queue, cl.CommandQueue) and not profiling:
        return queue
    ctx = create_context(queue)
    props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
    new = cl.CommandQueue(ctx, properties=props)
    # Some drivers (Intel's CPU runtime) invalidate a context once its last handle is
    # released, although a queue still uses it: the queue holds its context's handle.
    new.plenocl_context = ctx
    return new


def is_cpu(device: cl.Device) -> bool:
    """Whether ``device`` is a CPU: the one test plenocl uses to pick CPU code paths."""
    return bool(device.type & cl.device_type.CPU)


def device_info(queue: cl.CommandQueue) -> DeviceInfo:
    """Capabilities of the device behind ``queue``."""
    return DeviceInfo.probe(queue.device)


def check_fits(queue: cl.CommandQueue, nbytes: int, what: str) -> None:
    """Fail before starting when ``nbytes`` of buffers cannot fit on the device."""
    info = device_info(queue)
    if nbytes > info.global_mem_bytes:
        raise MemoryError(
            f"{what} needs {nbytes / 2**30:.2f} GiB of device memory but {info.name} has "
            f"{info.global_mem_bytes / 2**30:.2f} GiB; use a smaller grid or a larger device"
        )
