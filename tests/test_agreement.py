"""Cross-device agreement (plenocl.bench.agreement, ``plenocl devices --agree``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np

from plenocl.bench.agreement import TOLERANCES, agreement, agreement_table, stage_difference
from plenocl.opencl.device import get_queue


def test_differences_detect_changes():
    rng = np.random.default_rng(0)
    a = rng.random((20, 30)).astype(np.float32)
    for stage, (_, tol) in TOLERANCES.items():
        assert stage_difference(stage, a, a.copy()) == 0.0
        b = a.copy()
        b[3:8, 4:10] += 0.05 * a.max()  # a change well beyond float32 rounding
        assert stage_difference(stage, a, b) > tol, stage
        c = a.copy()
        c[0, 0] = np.nan  # a NaN (no sample) on one device only
        assert stage_difference(stage, a, c) == float("inf")


def test_two_queues_on_one_device_agree(queue):
    """Two contexts on the same device: the machinery compares real results (all five
    stages produce non-trivial output) and finds them equal."""
    other = get_queue(queue.device)  # a new context on the same device
    rows = agreement([queue, other])
    assert [r.stage for r in rows] == list(TOLERANCES)
    assert all(r.ok and r.difference == 0.0 for r in rows)
    table = agreement_table(rows, "dev")
    assert table.count("\n| ") == len(rows) + 1 and "NO" not in table


def _building_devices(env: dict) -> list[str]:
    """The devices that build plenocl's kernels under ``env``, probed independently of
    ``devices --agree`` (one build each, in a fresh process)."""
    probe = ("from plenocl.opencl.device import building_devices\n"
             "for d in building_devices()[0]:\n"
             "    print(d.name.strip())")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return [line for line in out.stdout.splitlines() if line]


def test_every_driver_and_pocls_two_drivers_agree(tmp_path):
    """PoCL's threaded and serial drivers as two devices, beside every other driver
    present (Intel's CPU runtime of the cpu extra; a GPU where there is one): every
    stage of each device that builds kernels within tolerance of the first such device.
    A device whose driver cannot build (PoCL's wheel on a CPU its LLVM does not know, a
    Zen 5) is named as skipped with the driver's reason, never taken as the reference."""
    env = {**os.environ, "POCL_DEVICES": "pthread basic"}
    env.pop("PYOPENCL_CTX", None)
    out = subprocess.run([sys.executable, "-m", "plenocl", "devices", "--agree"], env=env,
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "basic" in out.stdout and "pthread" in out.stdout
    building = _building_devices(env)
    assert building, "no device builds plenocl's kernels"
    listed = re.findall(r"builds plenocl's kernels: (yes|NO)", out.stdout)
    assert listed.count("NO") == len(listed) - len(building)
    assert out.stdout.count("its driver cannot build kernels") == listed.count("NO")
    if len(building) < 2:
        assert f"{len(building)} OpenCL device(s) build plenocl's kernels" in out.stdout
        return
    assert f"reference device: {building[0]}" in out.stdout
    done = re.search(r"(\d+) of (\d+) comparisons within tolerance", out.stdout)
    assert done and done.group(1) == done.group(2)
    assert int(done.group(2)) == (len(building) - 1) * len(TOLERANCES)
