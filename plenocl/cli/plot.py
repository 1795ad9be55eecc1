"""``plenocl plot``: a figure of a field, a volume, tracks or a batch's store
(:mod:`plenocl.plot`).

::

    plenocl plot results/pairs/pair_00000.npz --view slices --axis z --at -1 0 1
    plenocl plot results/timeseries.zarr --view probe --probe 0 0 0.5 --out probe.pdf
"""

from __future__ import annotations

import argparse


def plot_command(args: argparse.Namespace) -> int:
    """Draw the figure asked for and say where it went."""
    from ..plot import PlotOptions, plot_file

    options = PlotOptions(view=args.view, axis=args.axis, component=args.component,
                          at=args.at, probe=args.probe, max_arrows=args.max_arrows)
    path = plot_file(args.input, args.out, options)
    print(f"wrote {path}")
    return 0


def add_plot_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``plot``."""
    from ..plot.files import VIEWS

    views = "; ".join(f"{kind}: {', '.join(names)}" for kind, names in VIEWS.items())
    p = subparsers.add_parser(
        "plot", help="draw a figure (PNG or PDF) of a vector field (.npz), a volume, tracks "
                     "or a batch's store (.zarr)")
    p.add_argument("input", help="a field or tracks .npz, a volume (.npz, .npy, .h5), or a "
                                 "run's timeseries.zarr or tracks.zarr")
    p.add_argument("--view", default=None,
                   help=f"what to draw, by kind ({views}); default: the first of its kind")
    p.add_argument("--out", default=None,
                   help="the figure, .png or .pdf (default: INPUT_VIEW.png beside the input)")
    p.add_argument("--axis", default="z", choices=["x", "y", "z"],
                   help="the axis normal to the slices, or along which the profile runs")
    p.add_argument("--at", type=float, nargs="+", default=None, metavar="MM",
                   help="slice positions along --axis in mm (the nearest vector planes; "
                        "default: three spread over the field)")
    p.add_argument("--component", default="speed", choices=["u", "v", "w", "speed"],
                   help="what colours the slices, vectors and iso-surfaces")
    p.add_argument("--probe", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="a store's probe point in mm (default: the grid's centre)")
    p.add_argument("--max-arrows", type=int, default=300,
                   help="the 3-D vectors' cap: the field is thinned to at most this many")
    p.set_defaults(func=plot_command)
    return p
