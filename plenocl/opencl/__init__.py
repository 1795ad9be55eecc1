"""plenocl's OpenCL layer: which device runs (:mod:`.device`: ``get_queue``, the build
probe, ``PYOPENCL_CTX``; :mod:`.icd`: the CPU runtimes pip installs, registered with the
ICD loader), the kernels found, built once per context and bound to a queue
(:mod:`.build`, :mod:`.program`: ``KernelSet``, the one launch layer), and how many host
threads the host paths use (:mod:`.threads`). The stages import it; it imports no stage.
"""
