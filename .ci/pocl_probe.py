"""Exit 0 when plenocl's default OpenCL device compiles a kernel, 1 otherwise.

The PoCL wheel from PyPI (PoCL 3.0, LLVM 14) cannot compile for processors its LLVM does
not know (e.g. AMD Zen 5: "unknown target CPU 'generic'"); .ci/run then installs the
distribution's PoCL, as docs/errors.md tells users to.
"""

import sys

from plenocl import get_queue
from plenocl.program import KernelBuildError, build_program

try:
    queue = get_queue()
    build_program(queue.context, "deform.cl", ["-DORDER=1"])
except KernelBuildError as exc:
    print(f"pocl probe: {queue.device.name.strip()} cannot build kernels:\n{exc}")
    sys.exit(1)
print(f"pocl probe: {queue.device.name.strip()} builds kernels")
