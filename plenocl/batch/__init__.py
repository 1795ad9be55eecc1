"""A configured, resumable batch of image pairs: ``plenocl run experiment.toml``.

- :mod:`.config`: the experiment file, its checks, the image pairs;
- :mod:`.worker`: one pair from file paths to a written field (:class:`PairProcessor`);
- :mod:`.cluster`: the pairs on a Dask cluster (worker plugin, local cluster);
- :mod:`.run`: :func:`run`: order, resume, progress, Ctrl-C, the time series, summary;
- :mod:`.trackconfig`, :mod:`.tracking`, :mod:`.trackstore`: a time-resolved experiment
  (``[tracking]``) tracked instead, its tracks and their binned field in ``tracks.zarr``;
- :mod:`.prepare`: what every run makes first (camera, grid, the record of the run).
"""

from .config import Experiment, image_pairs, load_experiment
from .run import RunSummary, run
from .trackconfig import TrackingOptions
from .tracking import TrackingSummary
from .worker import PairOutcome, PairProcessor, PairTask, RunSettings

__all__ = ["Experiment", "PairOutcome", "PairProcessor", "PairTask", "RunSettings", "RunSummary",
           "TrackingOptions", "TrackingSummary", "image_pairs", "load_experiment", "run"]
