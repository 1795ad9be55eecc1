"""Files: raw images, particle lists, volumes, vector fields, TOML; all written atomically.

- atomic writes (:mod:`.atomic`: any file, JSON, text) and TOML files (:mod:`.tomlfile`);
- :mod:`.files`: images (TIFF/PNG/NPY), particle CSVs, volumes (NPZ/NPY/HDF5);
- :mod:`.fields`: PIV fields' arrays (VTK ``.vti``, ``.npz``, ``.h5``, and the tables of
  :mod:`.fieldtables`, Tecplot ``.dat`` and ``.csv``; a :class:`plenocl.PIVResult` as a
  file: :mod:`plenocl.vectorfield`);
- :mod:`.outputs`: an output path's format and folder, checked before any work;
- :mod:`.timeseries`, :mod:`.zarrstore`: Zarr stores that xarray opens (a batch's time
  series; named arrays with their dimensions, e.g. a tracking run's ``tracks.zarr``);
- :mod:`.plotting`, :mod:`.progress`: figures and progress bars for the user.
"""

from .atomic import atomic_path, write_json, write_text
from .fieldformat import read_field, write_field
from .files import (
    read_image,
    read_particles,
    read_volume,
    write_particles,
    write_tiff,
    write_volume,
)
from .tomlfile import read_toml, write_toml

__all__ = ["atomic_path", "read_field", "read_image", "read_particles", "read_toml",
           "read_volume", "write_field", "write_json", "write_particles", "write_volume",
           "write_text", "write_tiff", "write_toml"]
