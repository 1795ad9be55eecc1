"""A short time-resolved boundary-layer experiment, end to end through ``plenocl run``
(``plenocl demo time-series --out DIR``).

It writes what a user brings from the laboratory: a white image, raw image pairs
(``raw/frame_000.tif``, ``frame_001.tif``, ...) of the small camera of the
boundary-layer demo (:mod:`plenocl.demo.boundary_layer`), each pair a fresh seeding of the
same turbulent boundary layer, and the ``experiment.toml`` that processes them: the
camera calibrated from the white image, the pairs ``1+2, 3+4, ...``, ``dt`` and the pair
interval. It then runs :func:`plenocl.batch.run` on it and writes ``summary.json``: the
run's pairs, seconds per pair and stage split, and the velocity error of every pair
against the truth (RMS, % of U∞, per component) and of the ensemble mean.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.atomic import write_json
from ..io.files import write_tiff
from ..io.tomlfile import write_toml
from ..simulate import seeded_beyond_view, simulate_image, simulate_white_image
from .boundary_layer import (
    DT,
    U_INF,
    CameraFrameFlow,
    chain_settings,
    measured_and_true,
    scenario,
    seed_particles,
    sensor_options,
)

#: The camera preset of each scenario (``plenocl.camera.PRESETS``).
PRESET = {"small": "synthetic", "paper": "paper"}

#: Time between successive pairs (s): a 10 Hz double-pulsed laser.
PAIR_INTERVAL = 0.1


def run_time_series(out_dir: str | Path, pairs: int = 6, queue=None, seed: int = 0,
                    workers: int | None = None, log: Callable[[str], None] = print,
                    progress: bool = True, size: str = "small") -> dict:
    """Write the experiment (skipped where its files exist), run it, measure it.

    ``size``: ``"small"`` (850 x 850 px camera, seconds per pair) or ``"paper"`` (the
    16 MP camera and 300 x 200 x 150 voxel grid of the paper, minutes per pair on 2
    cores).

    Returns
    -------
    dict
        What ``summary.json`` holds.
    """
    from ..batch import run

    if pairs < 2:
        raise ValueError(f"a time series needs at least 2 pairs, got {pairs}")
    out = Path(out_dir)
    sc = scenario(size)
    flow = CameraFrameFlow(sc, seed)
    write_experiment(out, sc, flow, pairs, seed, queue, log)
    summary = run(out / "experiment.toml", out / "results", queue=queue, log=log,
                  workers=workers, progress=progress)
    doc = {"pairs": pairs, "processed": len(summary.processed) + len(summary.skipped),
           "failed": summary.failed, "seconds_per_pair": summary.seconds_per_pair,
           "stage_seconds_per_pair": {k: v / max(1, len(summary.processed))
                                      for k, v in summary.stage_seconds.items()},
           "u_inf_m_s": U_INF, **errors(out / "results", sc, flow)}
    write_json(out / "summary.json", doc, sort_keys=True)
    return doc


def write_experiment(out: Path, sc, flow, pairs: int, seed: int, queue, log) -> None:
    """White image, raw pairs and ``experiment.toml`` in ``out``."""
    (out / "raw").mkdir(parents=True, exist_ok=True)
    if not (out / "white.tif").is_file():
        sensor = {k: v for k, v in sensor_options(seed + 101).items() if k != "blur_px"}
        white = simulate_white_image(sc.physical_camera, intensity=3e4, vignetting=0.3,
                                     queue=queue, **sensor)
        write_tiff(out / "white.tif", white)
    for k in range(pairs):
        names = [out / "raw" / f"frame_{2 * k + j:03d}.tif" for j in (0, 1)]
        if all(n.is_file() for n in names):
            continue
        pos_a, pos_b, inten = seed_particles(sc, flow, seed + 1000 * (k + 1))
        for j, (name, pos) in enumerate(zip(names, (pos_a, pos_b))):
            with seeded_beyond_view():  # the margin the flow carries into view
                img = simulate_image(sc.physical_camera, pos, inten, sc.rays, queue=queue,
                                     **sensor_options(seed + 10 * k + j))
            write_tiff(name, img)
        log(f"pair {k}: {len(inten)} particles imaged")
    sc.grid.to_toml(out / "grid.toml")
    chain = chain_settings(sc)  # the boundary-layer demo's chain, as an experiment file
    write_toml(out / "experiment.toml", {
        "camera": {"preset": PRESET[sc.size], "white": "white.tif"},
        "grid": {"file": "grid.toml"},
        "images": {"folder": "raw", "pattern": "frame_*.tif", "pairing": "sequence",
                   "dt_s": DT, "pair_interval_s": PAIR_INTERVAL},
        "reconstruction": {"method": chain.reconstruction.method,
                           "iterations": chain.reconstruction.iterations},
        "piv": {"windows": list(chain.piv.windows), "ensemble": True},
        "output": {"folder": "results"}})


def errors(results: Path, sc, flow) -> dict:
    """Velocity error of every pair, of the ensemble mean of their vectors and of the
    ensemble correlation against the truth (valid vectors; RMS as a fraction of U∞; the
    demo's flow is steady, so every pair and both ensembles share one truth)."""
    per_pair, sums, counts, truth = [], 0.0, 0, None
    for npz in sorted((results / "pairs").glob("pair_*.npz")):
        meas, true, valid, _ = measured_and_true(npz, sc, flow)
        err = meas - true
        per_pair.append({c: float(np.sqrt(np.mean(err[i][valid] ** 2)) / U_INF)
                         for i, c in enumerate("xyz")}
                        | {"valid_fraction": float(valid.mean())})
        sums = sums + np.where(valid, meas, 0.0)
        counts = counts + valid
        truth = true
    if not per_pair:
        return {"per_pair": []}
    mean = sums / np.maximum(counts, 1)
    seen = counts > 0
    extra = {}
    if (results / "ensemble.npz").is_file():   # the ensemble correlation's mean field
        meas, true, valid, _ = measured_and_true(results / "ensemble.npz", sc, flow)
        extra["ensemble_correlation_rms_error"] = {
            c: float(np.sqrt(np.mean((meas[i] - true[i])[valid & seen] ** 2)) / U_INF)
            for i, c in enumerate("xyz")}
        extra["ensemble_correlation_valid_fraction"] = float(valid.mean())
    return {"per_pair": per_pair,
            "rms_error": {c: float(np.mean([p[c] for p in per_pair])) for c in "xyz"},
            "valid_fraction": float(np.mean([p["valid_fraction"] for p in per_pair])),
            "ensemble_mean_rms_error": {c: float(np.sqrt(np.mean(
                (mean[i] - truth[i])[seen] ** 2)) / U_INF) for i, c in enumerate("xyz")},
            **extra}
