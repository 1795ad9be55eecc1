"""Shared fixtures: the kernel tests run on every OpenCL device that builds plenocl's
kernels, one command queue per device for the whole session (like pyopencl's own tests).

Every test that takes the ``queue`` fixture (directly or through a module fixture) is
parametrized over the devices under test; its id names the device (``[Intel_OpenCL-...]``).
The devices under test are, in :func:`plenocl.opencl.device.devices_by_preference` order:

- ``PYOPENCL_TEST`` set (pyopencl's syntax, ``"0:0,1;intel"``): those devices;
- else ``PYOPENCL_CTX`` set: that one device (what :func:`plenocl.opencl.device.get_queue` picks);
- else every device whose driver builds plenocl's kernels.

An explicitly chosen device is tested even when it cannot build (the tests then fail and
say why). A device left out because it cannot build is named with its driver's reason in
the report header and in a short summary at the end of the run (shown under ``-q`` too):
never a silent skip. A test marked ``one_device`` (an end-to-end run: a batch, a demo, a
benchmark report) runs once, on PoCL when it is under test (:func:`baseline_index`): its
kernels are tested on every device by the others. With no building device at all, the
kernel tests fail with :class:`plenocl.opencl.device.NoOpenCLError`.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import tempfile

import pyopencl as cl
import pytest

from plenocl.io.kept import CACHE_VARIABLE
from plenocl.opencl.device import NoOpenCLError, building_devices, devices_by_preference, get_queue


@functools.cache
def devices_under_test() -> tuple[tuple[cl.Device, ...], tuple[str, ...]]:
    """The devices the kernel tests run on, and one line per device left out (with why)."""
    # each branch registers the pip-installed runtimes first, and raises NoOpenCLError
    # when there is no OpenCL at all
    if os.environ.get("PYOPENCL_TEST"):
        from pyopencl.tools import get_test_platforms_and_devices

        found = devices_by_preference()
        chosen = [d for _, devs in get_test_platforms_and_devices() for d in devs]
        return tuple(d for d in found if d in chosen), ()
    if os.environ.get("PYOPENCL_CTX"):
        return (get_queue().device,), ()
    building, failing = building_devices()
    left_out = tuple(f"{_describe(d)}: cannot build plenocl's kernels ({problem})"
                     for d, problem in failing)
    return tuple(building), left_out


def _describe(device: cl.Device) -> str:
    return f"{device.name.strip()} on {device.platform.name.strip()}"


def device_id(device: cl.Device) -> str:
    """A test id naming ``device``: its platform and name without punctuation."""
    platform, name = (re.sub(r"(\(R\)|\(TM\)|\W)+", "_", text).strip("_")
                      for text in (device.platform.name, device.name))
    return f"{platform}-{name}".replace("Portable_Computing_Language", "PoCL")


def _devices_or_none() -> tuple[list[cl.Device | None], list[str]]:
    try:
        devices = list(devices_under_test()[0])
    except NoOpenCLError:  # no OpenCL at all: the queue fixture raises the error
        return [None], ["no-device"]
    if not devices:  # none builds: the queue fixture raises NoOpenCLError with why
        return [None], ["no-device"]
    ids = [device_id(d) for d in devices]
    ids = [f"{i}_{n}" if ids.count(i) > 1 else i for n, i in enumerate(ids)]
    return devices, ids


def baseline_index(devices: list[cl.Device | None]) -> int:
    """The device a ``one_device`` test runs on: PoCL, the CPU driver every user has from
    pip, when it is under test, else the first (most preferred) device."""
    for n, device in enumerate(devices):
        if device is not None and "Portable Computing Language" in device.platform.name:
            return n
    return 0


def pytest_configure(config: pytest.Config) -> None:
    """Choices plenocl keeps between processes (the measured FFT routes,
    :mod:`plenocl.io.kept`) go to a folder of this test run's own, removed at its end
    (whatever ``PLENOCL_CACHE_DIR`` says: a run neither reads nor changes the user's kept
    choices, nor an earlier run's). xdist's workers, started after this, share the
    controller's folder; a worker keeps the one it was given."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        folder = tempfile.mkdtemp(prefix="plenocl-test-cache-")
        os.environ[CACHE_VARIABLE] = folder
        config.add_cleanup(lambda: shutil.rmtree(folder, ignore_errors=True))


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Run every test that needs a queue once per device under test; a test marked
    ``one_device`` (an end-to-end run whose kernels the other tests check on every device,
    and whose drivers ``tests/test_agreement.py`` compares) once, on the baseline device."""
    if "queue" in metafunc.fixturenames:
        devices, ids = _devices_or_none()
        if metafunc.definition.get_closest_marker("one_device"):
            keep = baseline_index(devices)
            devices, ids = devices[keep:keep + 1], ids[keep:keep + 1]
        metafunc.parametrize("queue", devices, ids=ids, indirect=True)


def _report_lines() -> list[str]:
    try:
        devices, left_out = devices_under_test()
    except NoOpenCLError as exc:  # reported; the kernel tests then fail
        return [f"OpenCL devices under test: none ({exc})"]
    names = "; ".join(_describe(d) for d in devices) or "none"
    return [f"OpenCL devices under test: {names}"] + [f"left out: {line}" for line in left_out]


def pytest_report_header(config: pytest.Config) -> list[str]:
    """Name the devices under test and those left out, with why."""
    return _report_lines()


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """Repeat the devices left out at the end (the header is hidden under ``-q``)."""
    lines = _report_lines()
    if len(lines) > 1 or "none" in lines[0]:
        terminalreporter.write_sep("-", "OpenCL devices")
        for line in lines:
            terminalreporter.write_line(line)


@pytest.fixture(scope="session")
def queue(request: pytest.FixtureRequest) -> cl.CommandQueue:
    """A command queue on one device under test, made once per session and device; never
    skipped. The default device's queue reuses the context its build probe made."""
    device = getattr(request, "param", None)
    default = get_queue()  # NoOpenCLError, with every driver's reason, if none builds
    return default if device is None or default.device == device else get_queue(device)


@pytest.fixture(scope="session")
def small_camera():
    """A small, fast plenoptic camera: 12 x 10 lenses of ~17 px, M = 1, f/2 (matched)."""
    from helpers import lens_camera

    return lens_camera(12, 10)
