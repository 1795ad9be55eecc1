"""Benchmark report section: PIV run time against error (and openpiv)."""

from __future__ import annotations

import os

import numpy as np

from ..flows import Flow, LambOseen, SolidBodyRotation, Uniform, centred_displacement, volume_pair
from ..piv.multipass import piv3d
from .core import BenchRun, md_table, pareto_front, repeats_text
from .timing import timed


# ---- PIV ----------------------------------------------------------------------------
def piv_flows(shape: tuple[int, int, int]) -> dict[str, Flow]:
    """Uniform shift, solid-body rotation and a Lamb-Oseen vortex (core radius 16 voxels,
    less in small volumes) in voxel units, about 3 voxels at most, as in
    ``benchmarks/piv.py``."""
    nz, ny, nx = shape
    centre = np.array([(nx - 1) / 2, (ny - 1) / 2, (nz - 1) / 2])
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    return {
        "uniform": Uniform((2.31, -1.47, 0.68)),
        "rotation": SolidBodyRotation(tuple(axis * 3.0 / (0.5 * min(shape))),
                                      tuple(centre)),
        "oseen": LambOseen.from_peak_velocity(3.0, min(16.0, min(shape) / 3),
                                              tuple(centre + [2.3, -1.7, 1.1]),
                                              tuple(axis)),
    }


def displacement_truth(flow: Flow, centres) -> np.ndarray:
    """The flow's mid-time displacement ``(3, nz', ny', nx')`` as (u, v, w) at window
    centres ``(z, y, x)`` (1-D, voxel index)."""
    zz, yy, xx = np.meshgrid(*centres, indexing="ij")
    pts = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    return centred_displacement(pts, flow, 1.0).T.reshape((3, *zz.shape))


def interior(shape, centres, margin: float) -> np.ndarray:
    """Where the window centres ``(z, y, x)`` lie at least ``margin`` voxels from every
    face of a volume of ``shape``."""
    zz, yy, xx = np.meshgrid(*centres, indexing="ij")
    inside = np.ones(zz.shape, bool)
    for c, n in zip((zz, yy, xx), shape):
        inside &= (c >= margin) & (c <= n - 1 - margin)
    return inside


def piv_error(disp: np.ndarray, centres, flow, shape) -> float:
    """Interior RMS vector error (voxels) of ``disp`` ``(3, nz', ny', nx')`` as (u, v, w)
    at window centres ``(z, y, x)``: centres at least ``min(16, n/4)`` voxels from every
    face, against the flow's mid-time displacement."""
    inside = interior(shape, centres, min(16, min(shape) // 4))
    err = (disp - displacement_truth(flow, centres))[:, inside]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=0)))) if err.size else float("nan")


def load_openpiv():
    """openpiv's 3-D module and version, or ``(None, reason)``."""
    os.environ.setdefault("TQDM_DISABLE", "1")  # openpiv's per-window progress bar
    try:
        import openpiv
        from openpiv import pyprocess3D
    except Exception as exc:  # noqa: BLE001 - any import failure means "not available"
        return None, f"{type(exc).__name__}: {exc}"
    return pyprocess3D, getattr(openpiv, "__version__", "?")


def _openpiv_run(p3, pair, ws: int, ov: int, repeats: int):
    """openpiv 3-D (single pass); its (u, v, w) are our (x, y, z) as (w, -u, v)."""
    def call():
        return p3.extended_search_area_piv3D(pair.vol_a, pair.vol_b, window_size=(ws,) * 3,
                                             overlap=(ov,) * 3, search_area_size=(ws,) * 3)

    (u, v, w), seconds = timed(call, repeats)
    centres = []
    for n in pair.vol_a.shape:  # openpiv's get_coordinates, per axis
        count = (n - ws) // (ws - ov) + 1
        shift = (n - 1 - ((count - 1) * (ws - ov) + ws - 1)) // 2
        centres.append(np.arange(count) * (ws - ov) + (ws - 1) / 2 + shift)
    return np.stack([w, -u, v]), tuple(centres), seconds


def _piv_flow_rows(run: BenchRun, p3, name: str, flow) -> list[dict]:
    shape = run.cfg.piv_shape
    pair = volume_pair(shape, flow, seed=2718)
    rows = []
    for label, kwargs in run.cfg.piv:
        res, t = timed(lambda k=kwargs: piv3d(pair.vol_a, pair.vol_b, **k), run.heavy)
        disp = np.stack([res.u, res.v, res.w])
        rows.append({"flow": name, "label": f"plenocl {label}", "seconds": t,
                     "rms": piv_error(disp, (res.z, res.y, res.x), flow, shape),
                     "vectors": res.u.size, "valid": float(res.valid.mean())})
    for ws, ov in (run.cfg.openpiv if p3 is not None else ()):
        disp, centres, t = _openpiv_run(p3, pair, ws, ov, run.heavy)
        rows.append({"flow": name, "label": f"openpiv {ws}^3, overlap {ov}", "seconds": t,
                     "rms": piv_error(disp, centres, flow, shape), "vectors": disp[0].size,
                     "valid": float("nan")})
    return rows


def _piv_table(rows: list[dict]) -> list[list]:
    """Table rows per flow; marks each row's Pareto front (time vs error) and number."""
    table = []
    for name in dict.fromkeys(r["flow"] for r in rows):
        sub = [r for r in rows if r["flow"] == name]
        front = pareto_front([r["seconds"] for r in sub], [r["rms"] for r in sub], False)
        for r, f in zip(sub, front):
            r["front"], r["number"] = bool(f), len(table) + 1
            table.append([r["number"], name, r["label"], f"{r['seconds']:.2f}", f"{r['rms']:.4f}",
                          r["vectors"], f"{1e3 * r['seconds'] / r['vectors']:.2f}",
                          "—" if np.isnan(r["valid"]) else f"{r['valid']:.3f}",
                          "*" if f else ""])
    return table


def section_piv(run: BenchRun) -> str:
    """PIV run time against RMS error per setting and flow; openpiv in the same run."""
    from .plots import plot_piv_pareto

    p3, version = load_openpiv()
    rows = []
    for name, flow in piv_flows(run.cfg.piv_shape).items():
        rows += _piv_flow_rows(run, p3, name, flow)
        run.log(f"  PIV: {name} done")
    table = _piv_table(rows)
    plot_piv_pareto(rows, run.out / "piv_pareto.png")
    about = (f"openpiv {version} (`extended_search_area_piv3D`, single pass, no validation) "
             "ran on the same volumes" if p3 is not None else
             f"openpiv is **not** importable here ({version}): no openpiv baseline in this "
             "run (`pip install openpiv` to add it)")
    return (f"## PIV: run time against error\n\nVolume pairs {run.cfg.piv_shape} (z, y, x) from "
            "`plenocl.flows.volume_pair` (Gaussian particles, σ 1 voxel, 0.004 per voxel, "
            "seed 2718); displacements up to about 3 voxels. Error: RMS of the vector error "
            "(voxels) over window centres at least min(16, n/4) voxels from the faces, "
            f"against the mid-time displacement. Medians of {repeats_text(run.heavy)}. {about}. "
            "front (*): on the Pareto front of time vs RMS error for that flow; the plot "
            "numbers points by the # column.\n\n"
            + md_table(["#", "flow", "setting", "time s", "RMS error (voxel)", "vectors",
                        "ms/vector", "valid", "front"], table)
            + "\n![time vs RMS error](piv_pareto.png)\n")
