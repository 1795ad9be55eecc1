"""Benchmark report: sizes, run state, timing and table helpers."""

from __future__ import annotations

import dataclasses
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..grid import Grid
from ..particles import random_particles
from ..simulate import Simulator, simulate_image

SIZES = ("ci", "small", "paper")
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
# A type: (label, method, iterations, relax, options) of a reconstruction setting.
ReconSetting = tuple[str, str, int, float, dict]
#: The report's solver rows run on the voxels themselves: they compare methods, iteration
#: counts and skipping options on one grid (``reconstruct()``'s default is coarse-to-fine
#: on sub-voxels, docs/design.md §6.5).
VOXELS = {"supersample": 1}
#: The paper's method's rows name the paper's lens weights (the projector's default are
#: the extent weights, docs/design.md §6.4) and its image as it is (MART smooths it by
#: 1 px by default, docs/design.md §6.2).
PAPER_METHOD = {"lens_weights": "paper", "smooth_px": 0}


# ---- configuration ----------------------------------------------------------------------
BENCH_CUBE = Grid((20, 40, 40), x=(-2.5, 2.5), y=(-2.5, 2.5), z=(-2.5, 2.5))
_RECON_CI: tuple[ReconSetting, ...] = (
    ("MART (paper)", "mart", 15, 0.7, PAPER_METHOD),
    ("SMART", "smart", 30, 1.0, {}),
    ("MLEM", "mlem", 5, 1.0, {}),
    ("MLEM", "mlem", 10, 1.0, {}),
    ("MLEM", "mlem", 30, 1.0, {}),
    ("MLEM mlos start", "mlem", 10, 1.0, {"start": "mlos"}),
    ("MLEM mask 0.5", "mlem", 10, 1.0, {"mask_fraction": 0.5}),
    ("MLEM skip_empty off", "mlem", 10, 1.0, {"skip_empty": False}),
    ("MLEM tol 1e-3", "mlem", 60, 1.0, {"tol": 1e-3}),
)
_RECON_SMALL: tuple[ReconSetting, ...] = (
    *_RECON_CI[:5],
    ("MLEM", "mlem", 60, 1.0, {}),
    ("MLEM mlos start", "mlem", 30, 1.0, {"start": "mlos"}),
    ("MLEM mask 0.5", "mlem", 30, 1.0, {"mask_fraction": 0.5}),
    ("MLEM mlos + mask 0.5", "mlem", 30, 1.0, {"start": "mlos", "mask_fraction": 0.5}),
    ("SMART mlos + mask 0.5", "smart", 30, 1.0, {"start": "mlos", "mask_fraction": 0.5}),
    ("MLEM skip_empty off", "mlem", 30, 1.0, {"skip_empty": False}),
    ("MLEM tol 1e-3", "mlem", 100, 1.0, {"tol": 1e-3}),
)


def _with_iterations(settings, iterations) -> tuple[ReconSetting, ...]:
    """``settings`` with other iteration counts (the tiny ``test`` size's)."""
    return tuple((label, method, n, relax, opts)
                 for (label, method, _, relax, opts), n in zip(settings, iterations, strict=True))


#: The ``ci`` settings but MLEM's 30 iterations, each run a few iterations only.
_RECON_TEST = _with_iterations(_RECON_CI[:4] + _RECON_CI[5:], (3, 3, 2, 4, 2, 2, 2, 6))

_PIV_SETTINGS: tuple[tuple[str, dict], ...] = (
    ("48-32-24, cubic, 3 final, deformed passes direct (default)", {}),
    ("every pass by FFT (the reference)", {"correlation": "fft"}),
    ("32-24-16", {"windows": (32, 24, 16)}),
    ("32-16, 1 final", {"windows": (32, 16), "final_iterations": 1}),
    ("deform_order 1 (trilinear)", {"deform_order": 1}),
    ("deform_order 5 (quintic)", {"deform_order": 5}),
    ("final_iterations 1", {"final_iterations": 1}),
    ("final_iterations 5", {"final_iterations": 5}),
)
_PIV_TEST: tuple[tuple[str, dict], ...] = (
    ("24-16, 1 final", {"windows": (24, 16), "final_iterations": 1}),
    ("24-16, 1 final, by FFT", {"windows": (24, 16), "final_iterations": 1,
                                "correlation": "fft"}),
    ("16, deform_order 1", {"windows": (16,), "final_iterations": 2, "deform_order": 1}),
)


@dataclass(frozen=True)
class BenchSize:
    """What one report size runs (scenes, settings, repeats)."""

    name: str
    repeats: int                      # cheap stages: simulator, projector, scaling
    heavy_repeats: int                # reconstruction, skipping, PIV
    camera: str                       # "synthetic" (850 x 850) or "tiny" (12 x 12 lenses)
    grid: Grid                        # the reconstruction grid
    box: Box                          # where particles are seeded (mm)
    counts: tuple[int, ...]           # particles of the reconstruction scenes
    rays: int                         # rays per particle of the reconstruction images
    recon: tuple[ReconSetting, ...]
    sim: tuple[int, int, int]         # particles, kernel rays, reference rays per particle
    csr_grid: tuple[int, int, int]    # grid of the stored-matrix comparison
    skip_iterations: int
    skip_particles: int
    piv_shape: tuple[int, int, int]
    piv: tuple[tuple[str, dict], ...]
    openpiv: tuple[tuple[int, int], ...]   # (window, overlap) voxels
    scale_voxels: tuple[tuple[int, int, int], ...]
    scale_lenses: tuple[int, ...]          # square arrays of 17 px lenses
    scale_particles: tuple[int, ...]
    scale_rays: int
    scale_iterations: tuple[int, ...]
    paper: bool = False
    accuracy_lenses: tuple[int, int] = (48, 32)   # the error budget's microlenses
    accuracy_seeding: tuple[float, ...] = (0.05,)  # particles per microlens


def bench_sizes() -> dict[str, BenchSize]:
    """The report sizes (``test`` is internal: a tiny camera, for the test suite)."""
    ci = BenchSize(
        name="ci", repeats=3, heavy_repeats=2, camera="synthetic", grid=BENCH_CUBE,
        box=((-2.3, 2.3),) * 3, counts=(30,), rays=20000, recon=_RECON_CI,
        sim=(200, 20000, 2000), csr_grid=(10, 20, 20), skip_iterations=20,
        skip_particles=40, piv_shape=(48, 48, 48), piv=_PIV_SETTINGS, openpiv=((24, 12),),
        scale_voxels=((8, 16, 16), (16, 32, 32), (32, 64, 64)), scale_lenses=(25, 50, 100),
        scale_particles=(100, 1000, 10000), scale_rays=500, scale_iterations=(2, 4, 8, 16))
    small = dataclasses.replace(
        ci, name="small", repeats=5, heavy_repeats=3, counts=(20, 60, 150),
        recon=_RECON_SMALL, csr_grid=(20, 40, 40), skip_iterations=30,
        piv_shape=(96, 96, 96), openpiv=((32, 16), (24, 18)),
        scale_voxels=((8, 16, 16), (16, 32, 32), (32, 64, 64), (64, 128, 128)),
        scale_lenses=(25, 50, 100, 200), scale_particles=(100, 1000, 10000, 50000),
        scale_rays=1000, scale_iterations=(4, 8, 16, 32, 64), accuracy_lenses=(96, 64),
        accuracy_seeding=(0.02, 0.05, 0.1))
    test = BenchSize(
        name="test", repeats=2, heavy_repeats=1, camera="tiny",
        grid=Grid((6, 10, 10), x=(-0.6, 0.6), y=(-0.6, 0.6), z=(-0.6, 0.6)),
        box=((-0.5, 0.5),) * 3, counts=(6,), rays=2000, recon=_RECON_TEST,
        sim=(20, 1000, 200), csr_grid=(3, 6, 6), skip_iterations=4, skip_particles=8,
        piv_shape=(32, 32, 32), piv=_PIV_TEST, openpiv=((16, 8),),
        scale_voxels=((3, 6, 6), (6, 12, 12)), scale_lenses=(12, 16),
        scale_particles=(10, 40), scale_rays=200, scale_iterations=(1, 2, 4),
        accuracy_lenses=(24, 16))
    paper = dataclasses.replace(small, name="paper", paper=True,
                                accuracy_seeding=(0.01, 0.02, 0.05, 0.1, 0.2))
    return {"ci": ci, "small": small, "paper": paper, "test": test}


def camera_for(name: str, lenses: int | None = None) -> Camera:
    """The benchmark cameras: ``"synthetic"`` (the paper's 850 x 850 px), ``"tiny"`` (12 x 12
    lenses) or, with ``lenses``, a square array of that many 17 px lenses (M = 1, f/2)."""
    if lenses is None:
        lenses = {"synthetic": 50, "tiny": 12}[name]
    return Camera(50.0, 2.0, 1.0, 0.125, 0.5, (lenses, lenses), 0.0074, (17 * lenses,) * 2)


# ---- run state, timing, tables --------------------------------------------------------
@dataclass
class BenchRun:
    """The state one report run shares between its sections."""

    cfg: BenchSize
    queue: object
    out: Path
    log: Callable[..., None]
    repeats: int
    heavy: int
    notes: list[str] = field(default_factory=list)
    csr: tuple[float, float] | None = None  # CSR weights/s (forward + back), bytes per weight

    @property
    def camera(self) -> Camera:
        """The camera of the report size's scenes."""
        return camera_for(self.cfg.camera)


def hexagonal_cut(base: Camera, shift: float = 0.5) -> Camera:
    """``base`` with a hexagonal array of the same pitch and columns, as many rows as its
    sensor holds, the sensor's height cut to them (the outer rows' centres half a row
    inside its edges, as the columns' are half a pitch inside); odd rows ``shift``."""
    row_px = base.microlens_image_pitch_mm * 3**0.5 / 2 / base.pixel_pitch_mm
    rows = int((base.pixels[1] - 1) / row_px)
    return dataclasses.replace(base, ml_layout="hexagonal", ml_count=(base.ml_count[0], rows),
                               ml_odd_row_shift=shift, microlens_centers=None,
                               pixels=(base.pixels[0], int(rows * row_px) + 1))


def host_peak_bytes(fn: Callable[[], object]) -> int:
    """Peak host memory (bytes, ``tracemalloc``) newly allocated during one call of ``fn()``."""
    tracemalloc.start()
    try:
        fn()
        return int(tracemalloc.get_traced_memory()[1])
    finally:
        tracemalloc.stop()


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured Markdown table (cells as given, ``str()``-ed)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def pareto_front(cost, score, higher_is_better: bool = True) -> np.ndarray:
    """Which points no other point dominates (lower ``cost`` and better ``score``).

    A point is dominated when another costs no more and scores no worse, and is strictly
    better in one of the two. Points with a non-finite cost or score are never on the
    front.

    Parameters
    ----------
    cost
        Cost per point (e.g. run time), lower is better.
    score
        Quality per point (e.g. recovery, or an error with ``higher_is_better=False``).
    higher_is_better
        Whether a larger ``score`` is better.

    Returns
    -------
    numpy.ndarray
        Boolean mask, ``True`` on the front.
    """
    c = np.asarray(cost, float)
    s = np.asarray(score, float) * (1.0 if higher_is_better else -1.0)
    ok = np.isfinite(c) & np.isfinite(s)
    front = np.zeros(c.shape, bool)
    for i in np.flatnonzero(ok):
        better = (c < c[i]) | (s > s[i])
        front[i] = not np.any(ok & (c <= c[i]) & (s >= s[i]) & better)
    return front


def loglog_slope(n, y) -> float:
    """Least-squares slope of ``log y`` against ``log n`` (NaN with fewer than 2 points)."""
    n, y = np.asarray(n, float), np.asarray(y, float)
    ok = (n > 0) & (y > 0) & np.isfinite(y)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(n[ok]), np.log(y[ok]), 1)[0])


def reshaped(grid: Grid, shape: tuple[int, int, int]) -> Grid:
    """The same volume as ``grid`` on ``shape`` voxels."""
    return Grid(shape, x=grid.x, y=grid.y, z=grid.z)


def repeats_text(n: int) -> str:
    """``"1 run"`` or ``"n runs"``, for the report's text."""
    return "1 run" if n == 1 else f"{n} runs"


def mib(nbytes: float) -> str:
    """Bytes as MiB with two decimals, for the report's tables."""
    return f"{nbytes / 2**20:.2f}"


def bench_scene(run: BenchRun, count: int, seed: int, box: Box | None = None):
    """Particles (mm, intensities) in ``box`` and their noise-free raw image."""
    pos, inten = random_particles(box or run.cfg.box, count=count, seed=seed, intensity=1e4)
    img = Simulator(run.camera, run.queue).trace(pos, inten, run.cfg.rays, seed=seed)
    return pos, inten, img


#: Where the scripts' cube scenes place particles: the 5 mm cube, 0.2 mm from its faces.
CUBE_BOX: Box = ((-2.3, 2.3),) * 3


def particle_scene(camera: Camera, count: int, seed: int, box: Box = CUBE_BOX,
                   blur_px: float = 0.0, queue=None):
    """Particles (mm, intensities) in ``box`` and their noise-free raw image (20 000 rays
    per particle), the workload of ``benchmarks/reconstruct.py`` and
    ``benchmarks/cubic_recovery.py``."""
    pos, inten = random_particles(box, count=count, seed=seed, intensity=1e4)
    img = simulate_image(camera, pos, inten, 20000, seed=seed, blur_px=blur_px, queue=queue)
    return pos, inten, img
