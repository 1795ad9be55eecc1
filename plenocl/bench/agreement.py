"""Cross-device agreement: the same small workloads on every OpenCL device, compared.

``plenocl devices --agree`` (or :func:`agreement`) runs the simulator, the projector
(forward and back), refocusing and an MLEM reconstruction on each device and compares
every result with the first device's, against a stated tolerance:

=============  =============================================  =========
stage          difference                                     tolerance
=============  =============================================  =========
simulate       Σ|a - b| / Σ|a| (light moved between pixels)   1e-3
forward        max|a - b| / max|a|                            1e-5
back           max|a - b| / max|a|                            1e-5
refocus        max|a - b| / max|a|                            1e-5
mlem           ‖a - b‖ / ‖a‖ after 20 iterations              1e-3
=============  =============================================  =========

Why these: the projector kernels are gathers (or race-free scatters) with a fixed order
of float32 operations per output and FP contraction off, so devices can differ only by
their compilers' evaluation of the same expressions; the float32 result is within
1e-6 of the peak of a float64 evaluation (``tests/test_stress.py``), so two devices
agree within twice that, and 1e-5 leaves margin. The simulator's sums are exact
(64-bit fixed point), but its ray directions use ``sqrt``/``sin``/``cos``, which OpenCL
allows to differ by a few ulp between devices: a ray near a pixel edge may land in the
neighbour, moving a tiny fraction of the light. MLEM divides (OpenCL allows 2.5 ulp) and
iterates, which amplifies per-step differences; 1e-3 of the volume's norm is far below
what changes a recovered particle. The MLEM input is the first device's image, so only
the reconstruction is compared.

Without a second device, PoCL can provide one: ``POCL_DEVICES="pthread basic"`` gives
its multi-threaded and its serial driver (different work-group scheduling, the same
compiler); a GPU beside PoCL is the comparison that matters.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..camera import Camera
from ..grid import Grid
from ..opencl.device import device_info, devices_by_preference, get_queue
from ..opencl.program import KernelBuildError, build_hint

#: stage -> (description of the difference, tolerance)
TOLERANCES: dict[str, tuple[str, float]] = {
    "simulate": ("Σ abs(a - b) / Σ abs(a)", 1e-3),
    "forward": ("max abs(a - b) / max abs(a)", 1e-5),
    "back": ("max abs(a - b) / max abs(a)", 1e-5),
    "refocus": ("max abs(a - b) / max abs(a)", 1e-5),
    "mlem": ("norm(a - b) / norm(a)", 1e-3),
}


@dataclass(frozen=True)
class Agreement:
    """One stage on one device against the first device."""

    device: str
    stage: str
    difference: float
    tolerance: float

    @property
    def ok(self) -> bool:
        """Within the tolerance."""
        return self.difference <= self.tolerance


def _workload():
    """The small camera, grid, particles and random inputs every device runs."""
    camera = Camera(50.0, 2.0, 1.0, 0.125, 0.5, (12, 10), 0.0074, (204, 170))
    grid = Grid((6, 12, 12), x=(-0.7, 0.7), y=(-0.6, 0.6), z=(-1.5, 1.5))
    rng = np.random.default_rng(11)
    positions = np.column_stack([rng.uniform(-0.6, 0.6, 6), rng.uniform(-0.5, 0.5, 6),
                                 rng.uniform(-1.3, 1.3, 6)])
    volume = (rng.random(grid.shape) * (rng.random(grid.shape) < 0.3)).astype(np.float32)
    image = rng.random((camera.pixels[1], camera.pixels[0])).astype(np.float32)
    return camera, grid, positions, volume, image


def stage_outputs(queue: cl.CommandQueue, mlem_image: np.ndarray | None = None
                  ) -> dict[str, np.ndarray]:
    """Each stage's result on ``queue`` (MLEM reconstructs ``mlem_image`` when given,
    else this device's simulated image)."""
    from ..lightfield import LightField
    from ..projection.projector import Projector
    from ..reconstruction import reconstruct
    from ..simulate import simulate_image

    camera, grid, positions, volume, image = _workload()
    sim = simulate_image(camera, positions, 1e4, 4000, seed=5, queue=queue)
    proj = Projector(camera, grid, queue)
    calibrated = camera.with_centers(camera.microlens_centers)  # the ideal centres, known
    refocused = LightField(sim, calibrated, queue=queue).refocus(z_mm=0.5)
    target = sim if mlem_image is None else mlem_image
    return {"simulate": sim, "forward": proj.forward(volume), "back": proj.back(image),
            "refocus": refocused, "mlem": reconstruct(target, proj, "mlem", 20,
                                                      supersample=1)}


def stage_difference(stage: str, a: np.ndarray, b: np.ndarray) -> float:
    """The difference of one stage's outputs on two devices, in the units its tolerance
    (:data:`TOLERANCES`) is stated in."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(ok, np.isfinite(a) | np.isfinite(b)):
        return float("inf")  # NaN (no sample) on one device only
    a, b = a[ok], b[ok]
    if stage == "simulate":
        return float(np.abs(a - b).sum() / max(np.abs(a).sum(), 1e-30))
    if stage == "mlem":
        return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), 1e-30))
    return float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-30))


def agreement(queues: Sequence[cl.CommandQueue] | None = None,
              log: Callable[[str], None] | None = None) -> list[Agreement]:
    """Compare every stage on each of ``queues`` (default: one per OpenCL device, the
    default device first) with the first queue's results.

    Returns
    -------
    list of Agreement
        One row per stage and device after the first; empty with a single device.
    """
    queues = list(queues) if queues is not None else [get_queue(d) for d in devices_by_preference()]
    outputs = []  # (name, stage outputs) of the devices that build kernels
    for queue in queues:
        image = outputs[0][1]["simulate"] if outputs else None
        out = _outputs_or_skip(queue, image, log)
        if out is not None:
            outputs.append((device_info(queue).name, out))
    if not outputs:
        return []
    first = outputs[0][1]
    rows = []
    for name, other in outputs[1:]:
        for stage, (_, tol) in TOLERANCES.items():
            rows.append(Agreement(name, stage, stage_difference(stage, first[stage], other[stage]),
                                  tol))
    return rows


def _outputs_or_skip(queue: cl.CommandQueue, mlem_image: np.ndarray | None,
                     log: Callable[[str], None] | None):
    """The stage outputs on ``queue``, or ``None`` (said in ``log``) for a device whose
    driver cannot build kernels at all (e.g. PoCL's LLVM not knowing the CPU): such a
    device is unusable, not in disagreement."""
    name = device_info(queue).name
    if log:
        log(f"running the stages on {name}")
    try:
        return stage_outputs(queue, mlem_image=mlem_image)
    except KernelBuildError as exc:
        if log:
            log(f"skipped {name}: its driver cannot build kernels{build_hint(str(exc))}")
        return None


def agreement_table(rows: Sequence[Agreement], reference: str) -> str:
    """A Markdown table of :func:`agreement`'s rows against device ``reference``."""
    lines = [f"reference device: {reference}", "",
             "| device | stage | difference | measure | tolerance | ok |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.device} | {r.stage} | {r.difference:.2e} | "
                     f"{TOLERANCES[r.stage][0]} | {r.tolerance:.0e} | "
                     f"{'yes' if r.ok else 'NO'} |")
    return "\n".join(lines)
