"""Figures of a user's own results (``plenocl plot``, a batch's summary figures, the
demos'): matplotlib on the Agg backend, imported only when a figure is drawn.

- :mod:`.data`: :class:`VectorData`, a field ready to draw, read from a field file or a
  batch's store;
- :mod:`.planes`: the vector planes a slice shows, arrow thinning, reference arrows;
- :mod:`.derivatives`: vorticity with a smoothing the field's resolution supports;
- :mod:`.slices`: contour slices with in-plane vectors, measured beside true;
- :mod:`.profiles`: mean profiles along an axis;
- :mod:`.vectors3d`: 3-D vectors thinned so they read, iso-surfaces;
- :mod:`.timeseries`: a batch's probe, valid fraction per pair, its summary figures;
- :mod:`plenocl.plot.tracks`, :mod:`.volume`: tracks and reconstructed volumes;
- :mod:`.files`: :func:`plot_file`, a file told apart by its content and drawn.
"""

from .data import VectorData, read_vector_field
from .files import VIEWS, PlotOptions, plot_file
from .timeseries import SUMMARY_FIGURES, batch_figures

__all__ = ["SUMMARY_FIGURES", "VIEWS", "PlotOptions", "VectorData", "batch_figures",
           "plot_file", "read_vector_field"]
