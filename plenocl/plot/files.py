"""``plenocl plot``: a figure of a file plenocl wrote, told apart by its content (a
vector field, a volume, tracks, a batch's store) through :mod:`plenocl.io`'s readers."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..io.plotting import check_figure_path

#: The views of each kind of file; the first is the default.
VIEWS = {"field": ("slices", "profile", "vectors", "vorticity", "iso"),
         "volume": ("projection", "slices"),
         "tracks": ("tracks",),
         "store": ("mean", "profile", "probe", "valid")}


@dataclass(frozen=True)
class PlotOptions:
    """What a figure shows (``plenocl plot``'s options).

    Attributes
    ----------
    view
        One of :data:`VIEWS` for the file's kind (``None``: its first).
    axis
        The axis normal to the slices, or along which the profile runs.
    component
        ``u``, ``v``, ``w`` or ``speed``: the colour of slices, vectors, iso-surfaces.
    at
        Positions (mm) along ``axis`` of the slices (the nearest vector planes).
    probe
        The probe's point ``(x, y, z)`` mm (default: the grid's centre).
    max_arrows
        The 3-D vectors' cap.
    """

    view: str | None = None
    axis: str = "z"
    component: str = "speed"
    at: Sequence[float] | None = None
    probe: Sequence[float] | None = None
    max_arrows: int = 300


def read_any(path: Path):
    """``(kind, content)`` of a file or store plenocl wrote (module notes)."""
    if not path.exists():
        raise FileNotFoundError(f"no such file or store: {path}")
    if path.is_dir():
        from ..io.zarrstore import read_store

        arrays, attrs = read_store(path)
        if "position" in arrays:
            return "tracks", (arrays["position"], arrays["velocity"])
        if "u_mean" in arrays:
            return "store", (arrays, attrs)
        raise ValueError(f"{path} is a Zarr store plenocl cannot plot (neither a batch's "
                         "timeseries.zarr nor a tracking run's tracks.zarr)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _read_npz(path)
    if suffix in (".npy", ".h5", ".hdf5"):
        from ..volumefile import load_volume

        return "volume", load_volume(path)  # an HDF5 field: named there (read_volume)
    raise ValueError(f"cannot plot {path.name!r}: plenocl plot reads a vector field or "
                     "tracks (.npz), a volume (.npz, .npy, .h5) or a batch's store (.zarr)"
                     + ("; open a .vti in ParaView, or plot the field's .npz"
                        if suffix == ".vti" else ""))


def _read_npz(path: Path):
    """The kind of an ``.npz`` (by the arrays it holds) and its contents, read by that
    kind's reader, so that a damaged file of a known kind is named as damaged (each
    reader was tried in turn and a damaged field read "holds no vector field")."""
    from ..io.npzfile import open_npz
    from ..ptv import Tracks
    from ..volumefile import load_volume
    from .data import read_vector_field
    from .tracks import tracks_with_speeds

    with open_npz(path, "a vector field, tracks or a volume plenocl wrote") as data:
        names = set(data.files)
    if {"positions", "velocities"} <= names:
        return "tracks", tracks_with_speeds(Tracks.load(path))
    if "displacement" in names:
        return "field", read_vector_field(path)
    if "volume" in names:
        return "volume", load_volume(path)
    raise ValueError(f"{path} holds no vector field, tracks or volume plenocl wrote "
                     "(save_field, Tracks.save, save_volume)")


def default_output(path: Path, view: str) -> Path:
    """``NAME_VIEW.png`` beside the input (a store's name without ``.zarr``)."""
    return path.with_name(f"{path.stem}_{view}.png")


def plot_file(path: str | Path, out: str | Path | None = None,
              options: PlotOptions | None = None) -> Path:
    """Draw a figure of ``path`` (a field, volume, tracks file or batch store) and write
    it to ``out`` (``.png`` or ``.pdf``; default :func:`default_output`).

    Returns
    -------
    pathlib.Path
        The figure written.
    """
    path, options = Path(path), options or PlotOptions()
    if out is not None:
        check_figure_path(out)
    kind, content = read_any(path)
    view = options.view or VIEWS[kind][0]
    if view not in VIEWS[kind]:
        raise ValueError(f"{path.name} is a {kind}; its views are {', '.join(VIEWS[kind])}, "
                         f"not {view!r}")
    out = Path(out) if out is not None else default_output(path, view)
    return _DRAW[kind](out, content, view, options)


def _field(out: Path, data, view: str, opt: PlotOptions) -> Path:
    from .derivatives import vorticity_magnitude
    from .profiles import profile_figure
    from .slices import DERIVATIVE_GAPS, slices_figure
    from .vectors3d import default_levels, isosurface_figure, vectors_figure

    if view == "slices":
        return slices_figure(out, data, opt.axis, opt.component, opt.at)
    if view == "profile":
        return profile_figure(out, data, opt.axis)
    if view == "vectors":
        return vectors_figure(out, data, opt.component, opt.max_arrows)
    if view == "vorticity":
        if data.unit != "m/s":
            raise ValueError("vorticity needs velocities: write the field with dt "
                             "(plenocl piv --dt)")
        mag = vorticity_magnitude(data.velocity, data.valid, data.x, data.y, data.z)
        return slices_figure(out, data, opt.axis, at=opt.at, values=mag,
                             value_label="vorticity magnitude |ω| (1/s)",
                             gap_note=DERIVATIVE_GAPS)
    values = data.component(opt.component)
    return isosurface_figure(out, data, values, default_levels(values),
                             data.label(opt.component))


def _volume(out: Path, content, view: str, opt: PlotOptions) -> Path:
    from .volume import volume_figure

    vol, grid = content
    return volume_figure(out, vol, grid, view, opt.axis, opt.at)


def _tracks(out: Path, content, view: str, opt: PlotOptions) -> Path:
    from .tracks import tracks_figure

    return tracks_figure(out, *content)


def _store(out: Path, content, view: str, opt: PlotOptions) -> Path:
    from .data import store_field
    from .profiles import profile_figure
    from .slices import slices_figure
    from .timeseries import probe_figure, valid_fraction_figure

    arrays, attrs = content
    if view == "probe":
        return probe_figure(out, arrays, attrs, opt.probe)
    if view == "valid":
        return valid_fraction_figure(out, arrays, attrs)
    mean = store_field(arrays, rotation_deg=float(attrs.get("rotation_deg", 0.0)))
    if not mean.valid.any():
        raise ValueError("the store's mean field has no valid vector to draw")
    if view == "profile":
        return profile_figure(out, mean, opt.axis)
    return slices_figure(out, mean, opt.axis, opt.component, opt.at)


_DRAW = {"field": _field, "volume": _volume, "tracks": _tracks, "store": _store}

__all__ = ["VIEWS", "PlotOptions", "default_output", "plot_file", "read_any"]
