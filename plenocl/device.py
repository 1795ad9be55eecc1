"""OpenCL device selection and capability probing.

A device is chosen explicitly (a :class:`pyopencl.Device`, ``Context`` or
``CommandQueue``, or a name/type substring such as ``"gpu"``, ``"cpu"`` or
``"NVIDIA"``), else from the ``PYOPENCL_CTX`` environment variable, else by
default: a GPU if one is present, otherwise a CPU. There is no global "current
device": every object that runs kernels takes a queue or builds one here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import pyopencl as cl

DeviceLike = None | str | cl.Device | cl.Context | cl.CommandQueue

NO_OPENCL_HELP = (
    "no OpenCL platform was found on this machine. Install the portable CPU "
    'implementation with: pip install "plenocl[pocl]"  (or install your GPU vendor\'s '
    "OpenCL driver)"
)


class NoOpenCLError(RuntimeError):
    """Raised when no OpenCL platform or no matching device is available."""


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
                f"64-bit atomics {'yes' if info.int64_atomics else 'no'}"
            )
    lines.append("choose one with PYOPENCL_CTX='<platform>:<device>' or device='<name or type>'")
    return "\n".join(lines)


def _match(devices: list[cl.Device], key: str) -> cl.Device:
    key_l = key.lower()
    for dev in devices:
        kind = cl.device_type.to_string(dev.type).lower()
        if key_l in dev.name.lower() or key_l in kind or key_l in dev.platform.name.lower():
            return dev
    names = ", ".join(d.name.strip() for d in devices)
    raise NoOpenCLError(f"no OpenCL device matches {key!r}; available: {names}")


def _default_device() -> cl.Device:
    devices = all_devices()
    for dev in devices:
        if dev.type & cl.device_type.GPU:
            return dev
    for dev in devices:
        if dev.type & cl.device_type.CPU:
            return dev
    return devices[0]


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
        return cl.Context([device])
    if isinstance(device, str):
        return cl.Context([_match(all_devices(), device)])
    if device is not None:
        raise TypeError(f"device must be a name, Device, Context or CommandQueue, not {device!r}")
    if os.environ.get("PYOPENCL_CTX"):
        _platforms()  # a clear error first if nothing is installed
        return cl.create_some_context(interactive=False)
    return cl.Context([_default_device()])


def get_queue(queue: DeviceLike = None, profiling: bool = False) -> cl.CommandQueue:
    """Return ``queue`` if it is a command queue, else a new queue on the chosen device."""
    if isinstance(queue, cl.CommandQueue) and not profiling:
        return queue
    ctx = create_context(queue)
    props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
    return cl.CommandQueue(ctx, properties=props)


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
