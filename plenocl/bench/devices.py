"""Report section: cross-device agreement (:mod:`plenocl.agreement`)."""

from __future__ import annotations

from ..agreement import TOLERANCES, agreement, agreement_table
from ..device import all_devices, get_queue
from .core import _Run


def section_devices(run: _Run) -> str:
    """Every stage on every visible OpenCL device against the report's device."""
    others = [d for d in all_devices() if d != run.queue.device]
    head = ("## Cross-device agreement\n\nThe simulator, projector, refocusing and MLEM "
            "(20 iterations) on a 12 x 10-lens camera, run on every OpenCL device this "
            "process sees and compared with the report's device. Tolerances (see "
            "`plenocl/agreement.py` for why): "
            + ", ".join(f"{s} {t:.0e}" for s, (_, t) in TOLERANCES.items()) + ".\n\n")
    if not others:
        return head + ("Only one device is visible, so there is nothing to compare here. "
                       "`POCL_DEVICES='pthread basic' plenocl devices --agree` compares "
                       "PoCL's threaded and serial drivers; on a machine with a GPU, "
                       "`plenocl devices --agree` compares it with PoCL.\n")
    rows = agreement([run.queue, *(get_queue(d) for d in others)], log=run.log)
    bad = sum(not r.ok for r in rows)
    return (head + agreement_table(rows, run.queue.device.name.strip())
            + f"\n\n{len(rows) - bad} of {len(rows)} comparisons within tolerance.\n")
