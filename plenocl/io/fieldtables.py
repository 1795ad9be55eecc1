"""A vector field as a table, one row per vector: Tecplot ASCII (``.dat``) and CSV.

The rows run over the vector grid with x fastest, then y, then z (the order of the
arrays ``(nz', ny', nx')`` flattened), and both formats hold the same columns:

- ``x [mm]``, ``y [mm]``, ``z [mm]``: the vector's position, in the grid's frame as the
  ``.vti`` file gives it; on a grid turned about the optical axis (``rotation_deg``) also
  ``x_object [mm]``, ``y_object [mm]``, the position in object space, the frame of the
  velocity below (the Tecplot file's ``#`` lines give the turn);
- ``u [m/s]``, ``v [m/s]``, ``w [m/s]``: the velocity in object space (only in fields
  written with ``dt``);
- ``u_voxel [voxel]``, ``v_voxel [voxel]``, ``w_voxel [voxel]``: the displacement along
  the grid's axes;
- ``valid``, ``outlier``, ``masked``: the flags as 1 or 0;
- then, for a field with an uncertainty (``PIVResult.sigma_u``), ``u_sigma [m/s]``, ...
  (with ``dt``) and ``u_sigma_voxel [voxel]``, ...: the standard uncertainties.

Outliers hold their replaced values (``outlier`` 1, ``valid`` 0). Masked vectors have no
value: the CSV gives them as ``nan`` (NumPy and pandas read it as NaN), the Tecplot file
as 0 with ``masked`` 1 and ``valid`` 0, since Tecplot reads NaN poorly; blank them there
by ``valid``. The Tecplot file is one ``ORDERED`` zone (``I``, ``J``, ``K`` = the vector
counts along x, y, z; ``DATAPACKING=POINT``), its ``#`` lines say the same.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["field_columns", "write_csv", "write_tecplot"]

#: Number formats: ten significant digits for values, integers for the flags.
_FLOAT, _FLAG = "%.10g", "%d"


def field_columns(arrays: dict[str, np.ndarray]) -> list[tuple[str, np.ndarray, str]]:
    """The table's columns (see the module notes) from a field's arrays: ``(header,
    values flattened x fastest, number format)``."""
    z, y, x = np.meshgrid(*(np.asarray(arrays[f"{a}_mm"], float) for a in "zyx"),
                          indexing="ij")
    cols = [(f"{a} [mm]", c.ravel(), _FLOAT) for a, c in zip("xyz", (x, y, z))]
    turn = _turn(arrays)
    if turn:  # the velocities' frame: positions turned as Grid.to_world turns vectors
        c, s = np.cos(np.radians(turn)), np.sin(np.radians(turn))
        cols += [("x_object [mm]", (c * x - s * y).ravel(), _FLOAT),
                 ("y_object [mm]", (s * x + c * y).ravel(), _FLOAT)]
    if "velocity" in arrays:
        cols += [(f"{a} [m/s]", np.asarray(c, float).ravel(), _FLOAT)
                 for a, c in zip("uvw", arrays["velocity"])]
    cols += [(f"{a}_voxel [voxel]", np.asarray(c, float).ravel(), _FLOAT)
             for a, c in zip("uvw", arrays["displacement"])]
    cols += [(flag, np.asarray(arrays[flag], bool).ravel().astype(np.int64), _FLAG)
             for flag in ("valid", "outlier", "masked")]
    # the uncertainties last: the columns before keep their places (2026-12-02)
    for name, unit, key in (("sigma", "m/s", "velocity_uncertainty"),
                            ("sigma_voxel", "voxel", "displacement_uncertainty")):
        if key in arrays:
            cols += [(f"{a}_{name} [{unit}]", np.asarray(c, float).ravel(), _FLOAT)
                     for a, c in zip("uvw", arrays[key])]
    return cols


def _turn(arrays: dict[str, np.ndarray]) -> float:
    """The grid's turn about the optical axis (degrees; 0 for a field without one)."""
    return float(np.asarray(arrays.get("rotation_deg", 0.0)))


def write_csv(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write the field as CSV (one header line of ``name [unit]``, then one row per
    vector; masked vectors as ``nan``), atomically."""
    cols = field_columns(arrays)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, np.column_stack([c[1] for c in cols]), delimiter=",",
                   fmt=[c[2] for c in cols], header=",".join(c[0] for c in cols),
                   comments="")


#: An uncertainty the field does not know (NaN: invalid, outlier or masked vectors) in
#: the Tecplot file, which reads NaN poorly: negative, so no reader takes it for a
#: perfect vector (0 did).
UNKNOWN_SIGMA = -1.0


def write_tecplot(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write the field as a Tecplot ASCII ``.dat`` file (one ordered zone, point data;
    masked vectors as 0 with ``valid`` 0 and ``masked`` 1, an unknown uncertainty as
    :data:`UNKNOWN_SIGMA`), atomically."""
    cols = field_columns(arrays)
    nz, ny, nx = np.shape(arrays["displacement"])[1:]
    values = np.column_stack([
        np.nan_to_num(c[1], nan=UNKNOWN_SIGMA if "sigma" in c[0] else 0.0) for c in cols])
    head = "\n".join([
        "# plenocl vector field: one row per vector, x fastest, then y, then z",
        "# masked vectors are written as 0 with valid = 0 and masked = 1; outliers hold "
        "their replaced values",
        *([f"# an uncertainty not known (invalid, outlier or masked vectors) is written "
           f"as {UNKNOWN_SIGMA:g}"] if any("sigma" in c[0] for c in cols) else []),
        *([f"# the grid is turned {_turn(arrays):.6g} deg about the optical axis: x, y [mm] "
           "along its axes, u, v [m/s] in object space, at x_object, y_object [mm]"]
          if _turn(arrays) else []),
        'TITLE = "plenocl vector field"',
        "VARIABLES = " + " ".join(f'"{c[0]}"' for c in cols),
        f'ZONE T="field", I={nx}, J={ny}, K={nz}, DATAPACKING=POINT'])
    with atomic_path(path) as tmp:
        np.savetxt(tmp, values, fmt=[c[2] for c in cols], header=head, comments="")
