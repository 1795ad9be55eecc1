"""The boundary layer in time, tracked (``plenocl demo tracking --out DIR``; issue 30).

The small boundary-layer experiment (:mod:`plenocl.demo.boundary_layer`: the 850 x 850 px
camera, a turbulent boundary layer with known truth) recorded at ``frames`` instants
``DT`` apart, as a high-speed plenoptic camera would: the particles are advected along
the flow from frame to frame, ray traced with the demo's sensor (blur, photon and read
noise, 16 bit). :func:`plenocl.track` follows them; their tracks are binned into the
windows of the pair chain (:func:`plenocl.bin_tracks`) and compared with the
window-averaged truth, beside :func:`plenocl.process_pair` on the middle pair of
frames. Writes ``tracks.npz``, ``tracks.vtu`` (ParaView), ``field_tracks.npz``,
``fig_tracks.png`` and ``summary.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..bench.tracking_section import track_errors
from ..flows import displace
from ..io.atomic import write_json
from ..particles import random_particles
from ..pipeline import TrackSettings, bin_tracks, process_pair, track
from ..plot.tracks import plot_tracks
from ..projection import Projector
from ..simulate import seeded_beyond_view, simulate_image
from ..vectorfield import save_field
from .boundary_layer import (
    DT,
    U_INF,
    CameraFrameFlow,
    chain_settings,
    lateral_depth_errors,
    scenario,
    sensor_options,
    window_averaged,
)

#: Frames of the recording.
FRAMES = 8


def run_tracking(out_dir: str | Path, frames: int = FRAMES, queue=None, seed: int = 0,
                 log: Callable[[str], None] = print,
                 settings: TrackSettings | None = None) -> dict:
    """Simulate the recording, track it (``settings``: :func:`plenocl.track`'s, by
    default its defaults), measure it; returns what ``summary.json`` holds."""
    if frames < 4:
        raise ValueError(f"the tracking demo needs at least 4 frames, got {frames}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = scenario("small")
    flow = CameraFrameFlow(sc, seed)
    truth, images = _recording(sc, flow, frames, seed, queue)
    log(f"  {truth.shape[0]} particles over {frames} frames {DT * 1e6:.0f} µs apart")
    proj = Projector(sc.camera, sc.grid, queue)
    t0 = time.perf_counter()
    tracks = track(images, proj, dt=DT, settings=settings)
    seconds = time.perf_counter() - t0
    tracks.save(out / "tracks.npz")
    tracks.save(out / "tracks.vtu", seconds=True)  # dt in s: m/s, as plenocl run writes
    plot_tracks(out / "fig_tracks.png", tracks)
    mid = frames // 2 - 1
    pair = process_pair(images[mid], images[mid + 1], proj, chain_settings(sc))
    field = bin_tracks(tracks, sc.grid, window=pair.piv.window, step=pair.piv.step)
    save_field(out / "field_tracks.npz", field, grid=sc.grid, dt=DT)
    summary = {"frames": frames, "particles": int(truth.shape[0]), "dt_s": DT,
               "u_inf_m_s": U_INF, "tracks": int(len(tracks.positions)),
               "seconds_per_frame": seconds / frames,
               "pair_seconds_per_frame": sum(pair.seconds.values()) / 2,
               "particles_per_step": track_errors(tracks, truth, sc.grid, seconds),
               "field_tracks": _field_errors(field, sc, flow),
               "field_pair": _field_errors(pair.piv, sc, flow)}
    write_json(out / "summary.json", summary, sort_keys=True)
    return summary


def _recording(sc, flow: CameraFrameFlow, frames: int, seed: int, queue):
    """True positions ``(n, frames, 3)`` mm and the raw images: particles seeded over
    the field of view and upstream of it by the distance the flow carries them."""
    g, cam = sc.grid, sc.camera
    travel = U_INF * 1e3 * DT * (frames - 1)
    box = (g.x, (g.y[0] - travel, g.y[1]), g.z)
    count = int(round(sc.particles_per_lens * cam.ml_count[0] * cam.ml_count[1]
                      * (box[1][1] - box[1][0]) / (g.y[1] - g.y[0])))
    pos, inten = random_particles(box, count=count, seed=seed, intensity=(2e4, 4e4))
    keep = pos[:, 2] < sc.z_wall - 1e-3
    path = [pos[keep]]
    for _ in range(frames - 1):
        path.append(displace(path[-1], flow, DT))
    truth = np.stack(path, axis=1)
    with seeded_beyond_view():  # the flow carries particles in and out of view
        images = [simulate_image(sc.physical_camera, truth[:, k], inten[keep], sc.rays,
                                 queue=queue, **sensor_options(seed + 10 + k))
                  for k in range(frames)]
    return truth, images


def _field_errors(res, sc, flow: CameraFrameFlow) -> dict:
    """A field's lateral and depth errors (voxels, % of U∞) against the window-averaged
    truth, and its share of valid vectors."""
    dz, dy, dx = sc.grid.spacing
    coords = res.positions_mm(sc.grid.spacing, (sc.grid.z[0] + dz / 2, sc.grid.y[0] + dy / 2,
                                                sc.grid.x[0] + dx / 2))
    meas = np.stack(res.velocity(sc.grid.spacing, DT))
    valid = res.valid & np.all(np.isfinite(meas), axis=0)
    true = window_averaged(res.window, coords, sc, flow)
    errors = lateral_depth_errors(meas, {"window_averaged": true}, valid, sc)
    return {**errors["window_averaged"], "valid": float(valid.mean())}
