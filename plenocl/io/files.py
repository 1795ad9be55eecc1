"""File input and output: raw images (TIFF/PNG/NPY), particle lists, volumes; every write
is atomic (:func:`plenocl.io.atomic.atomic_path`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .npzfile import load_npy, open_npz


def write_tiff(path: str | Path, image: np.ndarray, metadata: dict | None = None,
               pixel_mm: tuple[float, float] | None = None) -> None:
    """Write an image or image stack as TIFF, atomically; ``metadata`` (JSON-able, e.g.
    each page's depth) goes into the file's image description as JSON; ``pixel_mm``
    ``(rows, columns)``: a pixel's size, in the resolution tags (viewers then draw
    pixels that are not square at their aspect)."""
    import tifffile

    description = None if metadata is None else json.dumps(metadata)
    size = {} if pixel_mm is None else {
        "resolution": (10.0 / float(pixel_mm[1]), 10.0 / float(pixel_mm[0])),
        "resolutionunit": "CENTIMETER"}  # pixels per cm along x, y
    with atomic_path(path) as tmp:
        # minisblack: a stack of 3 or 4 planes is a stack, not an RGB(A) image
        tifffile.imwrite(tmp, np.asarray(image), photometric="minisblack",
                         description=description, metadata=None, **size)


def read_tiff_metadata(path: str | Path) -> dict:
    """The JSON metadata :func:`write_tiff` stored (``{}`` when there is none)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        text = tif.pages[0].description or ""
    try:
        meta = json.loads(text)
    except ValueError:
        return {}
    return meta if isinstance(meta, dict) else {}


#: What ``channel=`` accepts for a colour image: one plane, or the Rec. 709 luminance.
CHANNELS = ("r", "g", "b", "luminance")
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _read_tiff(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A TIFF page as stored, and its colour map when it is a palette (indexed) image."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        palette = page.photometric == tifffile.PHOTOMETRIC.PALETTE
        return page.asarray(), np.asarray(page.colormap) if palette else None


def _through_palette(data: np.ndarray, cmap: np.ndarray, path: Path) -> np.ndarray:
    """A palette image as the intensities a grey palette stands for; a colour palette is
    refused (its indices are not light)."""
    if not (np.array_equal(cmap[0], cmap[1]) and np.array_equal(cmap[0], cmap[2])):
        raise ValueError(f"{path} is a colour palette (indexed) image: its pixel values are "
                         "palette indices, not light; export the raw sensor image as "
                         "monochrome (grey) TIFF")
    return cmap[0][data]


def _read_any(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The stored array, and a TIFF palette's colour map (else ``None``)."""
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        return _read_tiff(path)
    if suffix == ".npy":
        return load_npy(path, "an image"), None
    import imageio.v3 as iio

    return iio.imread(path), None  # a PNG palette comes back through its palette


def _one_channel(image: np.ndarray, path: Path, channel: str | None) -> np.ndarray:
    """A colour image as one monochrome image: ``channel`` picks a plane or the
    luminance; without it, only an image whose colour planes are identical is taken (a
    grey image stored as colour). Alpha is dropped (:func:`read_alpha` reads it)."""
    planes = image[..., :3]
    if channel is None:
        if all(np.array_equal(planes[..., 0], planes[..., i]) for i in (1, 2)):
            return planes[..., 0]
        raise ValueError(f"{path} is a colour image with different red, green and blue "
                         "values; plenocl needs the raw monochrome sensor image. Choose "
                         f"what to use: channel= / --channel one of {CHANNELS}")
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")
    if channel == "luminance":
        return (planes.astype(np.float64) @ _LUMINANCE).astype(np.float32)
    return planes[..., "rgb".index(channel)]


def read_alpha(path: str | Path) -> np.ndarray | None:
    """The alpha channel of an RGBA image as a mask (``True``: pixel rendered, alpha > 0),
    or ``None`` for an image without one."""
    image = _read_any(Path(path))[0]
    return image[..., 3] > 0 if image.ndim == 3 and image.shape[-1] == 4 else None


def read_image(path: str | Path, channel: str | None = None) -> np.ndarray:
    """Read a raw image (TIFF, PNG or ``.npy``) as a 2-D array, with clear errors.

    Parameters
    ----------
    path
        The file. TIFF in any of the usual codecs (LZW, Deflate, ...); a grey palette is
        applied, a colour one refused.
    channel
        For a colour image: ``"r"``, ``"g"``, ``"b"`` or ``"luminance"`` (Rec. 709).
        Without it a colour image is read only when its three planes are identical.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such image file: {path}")
    if path.stat().st_size == 0:
        raise ValueError(f"{path} is empty (0 bytes): the file was not written completely; "
                         "copy or export it again")
    try:
        image, cmap = _read_any(path)
    except (OSError, ValueError, RuntimeError) as exc:
        raise ValueError(f"cannot read {path} as an image ({exc}); plenocl reads TIFF, PNG "
                         "and .npy files") from None
    if cmap is not None:
        image = _through_palette(image, cmap, path)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        image = _one_channel(image, path, channel)
    if image.ndim != 2:
        raise ValueError(f"{path} holds an array of shape {image.shape}; expected one 2-D image")
    return image


def write_particles(path: str | Path, positions: np.ndarray, intensities: np.ndarray) -> None:
    """Write particles as CSV with a header ``x_mm,y_mm,z_mm,intensity``, atomically."""
    data = np.column_stack([np.asarray(positions, float).reshape(-1, 3),
                            np.asarray(intensities, float).reshape(-1)])
    with atomic_path(path) as tmp:
        np.savetxt(tmp, data, delimiter=",", header="x_mm,y_mm,z_mm,intensity", comments="",
                   fmt="%.9g")


def read_particles(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a particle CSV: columns ``x_mm,y_mm,z_mm`` and optionally ``intensity``, in
    any order, read by their names in the header (``x``, ``x_mm``, ``x [mm]`` alike).

    Returns positions ``(N, 3)`` and intensities ``(N,)`` (1000 counts each when the
    file has no intensity column).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such particle file: {path}")
    header = _particle_header(path)
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: expected CSV rows 'x_mm,y_mm,z_mm[,intensity]' after one "
                         f"header line ({exc})") from None
    if data.shape[1] not in (3, 4) or data.shape[0] == 0:
        raise ValueError(f"{path}: expected 3 or 4 columns 'x_mm,y_mm,z_mm[,intensity]' and at "
                         f"least one row, got shape {data.shape}")
    order = _particle_columns(path, header, data.shape[1])
    intens = data[:, order[3]] if len(order) == 4 else np.full(len(data), 1000.0)
    return data[:, order[:3]], intens


#: A particle file's column names (lower case, spaces removed) and what each holds.
PARTICLE_COLUMNS = {**{name: axis for axis in "xyz"
                       for name in (axis, f"{axis}_mm", f"{axis}[mm]", f"{axis}(mm)")},
                    "intensity": "intensity", "intensity[counts]": "intensity"}


def _particle_columns(path: Path, header: str, count: int) -> list[int]:
    """The columns of x, y, z (and the intensity) named by ``header``: refused where a
    name is another quantity or unit (a position in pixels, or z, y, x read as x, y, z,
    placed every particle elsewhere in silence)."""
    names = [n.strip() for n in header.lstrip("#").split(",")][:count]  # NumPy's "# "
    roles = [PARTICLE_COLUMNS.get(n.lower().replace(" ", "")) for n in names]
    want = ["x", "y", "z", "intensity"][:count]
    if len(names) != count or sorted(map(str, roles)) != sorted(want):
        raise ValueError(f"{path}: the header names the columns {names}; a particle file's "
                         f"columns are x_mm, y_mm, z_mm (positions in mm) and optionally "
                         "intensity, in any order: name them so (positions in other units, "
                         "pixels or voxels, converted to mm)")
    return [roles.index(role) for role in want]


def _particle_header(path: Path) -> str:
    """The first line, which must be the header, not a particle (it would be skipped
    silently)."""
    with path.open(encoding="utf-8", errors="replace") as fh:
        first = fh.readline().strip()
    try:
        [float(v) for v in first.split(",") if v.strip()]
    except ValueError:
        return first  # words: a header
    if first:
        raise ValueError(f"{path}: the first line {first!r} is a particle, not the header "
                         "'x_mm,y_mm,z_mm[,intensity]'; add the header line so that no "
                         "particle is lost")
    return first


#: The volume file formats by suffix (:func:`write_volume`).
VOLUME_FORMATS = {".npz": "NumPy, with the grid", ".npy": "NumPy, the array alone",
                  ".h5": "HDF5, with the grid", ".hdf5": "HDF5, with the grid"}


def write_volume(path: str | Path, vol: np.ndarray, meta: dict[str, np.ndarray]) -> None:
    """Write a volume atomically: ``.npy`` (the array alone), ``.npz`` or ``.h5`` (with
    the arrays of ``meta`` beside it; :mod:`plenocl.volumefile` puts the grid there).

    ``.h5`` needs h5py (``pip install h5py``).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix == ".npy":
            with tmp.open("wb") as fh:
                np.save(fh, vol)
        elif suffix == ".npz":
            with tmp.open("wb") as fh:
                np.savez_compressed(fh, volume=vol, **meta)
        elif suffix in (".h5", ".hdf5"):
            _save_h5(tmp, vol, meta)
        else:
            raise ValueError(f"unknown volume format {suffix!r}: use .npy, .npz or .h5")


def _save_h5(tmp: Path, vol: np.ndarray, meta: dict) -> None:
    try:
        import h5py
    except ImportError:
        raise ImportError("writing .h5 needs h5py: pip install h5py (or use .npz)") from None
    with h5py.File(tmp, "w") as fh:
        data = fh.create_dataset("volume", data=vol, compression="gzip")
        data.attrs["axes"] = "z, y, x (vol[iz, iy, ix])"
        data.attrs["units"] = "reconstructed intensity (image counts)"
        for key, value in meta.items():
            fh.attrs[key] = value


def read_volume(path: str | Path) -> tuple[np.ndarray, dict]:
    """A volume written by :func:`write_volume` and the arrays stored beside it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such volume file: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        vol, meta = load_npy(path, "a volume"), {}
    elif suffix == ".npz":
        with open_npz(path, "a volume (plenocl.save_volume)") as data:
            vol, meta = data["volume"], {k: data[k] for k in data.files if k != "volume"}
    elif suffix in (".h5", ".hdf5"):
        import h5py

        try:
            fh = h5py.File(path, "r")
        except OSError as exc:  # not HDF5, or damaged: name the file
            raise ValueError(f"{path} cannot be read as HDF5 ({exc}): a volume written by "
                             "plenocl.save_volume, or a damaged copy") from None
        with fh:
            if "volume" not in fh:
                raise ValueError(f"{path} holds no 'volume' dataset (it holds "
                                 f"{sorted(fh.keys())[:6]}...): not a volume plenocl "
                                 "wrote (a vector field: plenocl.vectorfield.read_npz "
                                 "reads it, plenocl plot draws fields from their .npz)")
            vol, meta = fh["volume"][...], dict(fh.attrs)
    else:
        raise ValueError(f"unknown volume format {suffix!r}: use .npy, .npz or .h5")
    if vol.ndim != 3:
        raise ValueError(f"{path} holds an array of shape {vol.shape}, not a 3-D volume")
    return vol, meta


def write_volumes(path: str | Path, vol_a: np.ndarray, vol_b: np.ndarray,
                  metadata: dict | None = None) -> None:
    """Save a pair's two volumes to one compressed ``.npz`` (``vol_a``, ``vol_b``, and
    ``metadata``, a JSON-ready dict, when given), atomically."""
    extra = {} if metadata is None else {"metadata": np.asarray(json.dumps(metadata))}
    with atomic_path(Path(path)) as tmp, tmp.open("wb") as fh:
        np.savez_compressed(fh, vol_a=np.asarray(vol_a, np.float32),
                            vol_b=np.asarray(vol_b, np.float32), **extra)


def read_volumes(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The two volumes written by :func:`write_volumes`."""
    with open_npz(path, "a pair's volumes") as data:
        return data["vol_a"], data["vol_b"]


def volumes_metadata(path: str | Path) -> dict:
    """The ``metadata`` written with :func:`write_volumes` (``{}`` without any), without
    reading the volumes."""
    with open_npz(path, "a pair's volumes") as data:
        return json.loads(str(data["metadata"])) if "metadata" in data.files else {}
