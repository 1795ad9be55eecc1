"""Report section: cross-device agreement (:mod:`plenocl.bench.agreement`)."""

from __future__ import annotations

import os
import subprocess
import sys

from ..opencl.device import all_devices, get_queue
from .agreement import TOLERANCES, agreement, agreement_table
from .core import BenchRun

#: PoCL's threaded and serial CPU drivers, as two devices of a child process.
POCL_PAIR = "pthread basic"


def section_devices(run: BenchRun) -> str:
    """Every stage on every visible OpenCL device against the report's device; with PoCL
    alone, its two CPU drivers compared in a child process."""
    others = [d for d in all_devices() if d != run.queue.device]
    head = ("## Cross-device agreement\n\nThe simulator, projector, refocusing and MLEM "
            "(20 iterations) on a 12 x 10-lens camera, run on each device and compared with "
            "the first. Tolerances (see `plenocl/bench/agreement.py` for why): "
            + ", ".join(f"{s} {t:.0e}" for s, (_, t) in TOLERANCES.items()) + ".\n\n")
    if others:
        rows = agreement([run.queue, *(get_queue(d) for d in others)], log=run.log)
        bad = sum(not r.ok for r in rows)
        return (head + agreement_table(rows, run.queue.device.name.strip())
                + f"\n\n{len(rows) - bad} of {len(rows)} comparisons within tolerance.\n")
    if "Portable Computing Language" not in run.queue.device.platform.name:
        return head + ("Only one device is visible, so there is nothing to compare. "
                       "`plenocl devices --agree` compares every device it sees.\n")
    return head + _pocl_pair(run)


def _pocl_pair(run: BenchRun) -> str:
    """``plenocl devices --agree`` in a child process that sees PoCL's two CPU drivers."""
    env = {**os.environ, "POCL_DEVICES": POCL_PAIR}
    env.pop("PYOPENCL_CTX", None)
    run.log(f"  cross-device: POCL_DEVICES='{POCL_PAIR}' in a child process")
    out = subprocess.run([sys.executable, "-m", "plenocl", "devices", "--agree"], env=env,
                         capture_output=True, text=True, timeout=900)
    table = out.stdout[out.stdout.find("reference device:"):].strip()
    status = "" if out.returncode == 0 else f" (exit status {out.returncode})"
    return ("Only PoCL is visible here, so the comparison is between its threaded and its "
            f"serial driver (`POCL_DEVICES='{POCL_PAIR}' plenocl devices --agree`{status}): "
            "the same compiler, different work-group scheduling. A GPU, where present, "
            "joins the comparison.\n\n" + (table or out.stdout + out.stderr) + "\n")
