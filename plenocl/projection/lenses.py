"""Which microlenses an image lights: dark-microlens skipping in the pixel stages.

At PIV seeding densities most microlens images are dark: in the paper's synthetic case
(0.02 particles per microlens) about three quarters of the lenses see no particle. A
multiplicative solver never needs the projection at a dark pixel (its ratio ``I / P`` is
0 whatever ``P`` is), and the back projection of a ratio image reads only zeros there. A
:class:`LensSet` lists the lenses to project, grouped by the race-free colour classes of
the forward pixel kernel, and flags the lens rows holding any of them; the projector's
pixel stages (``fwd_pix``, ``back_pix``) then visit only those lenses and the row stages
(``fwd_y``, ``back_y``) skip dark rows.

Exactness: a lens is *lit* when any pixel of the square patch its aperture samples can
touch (``reach`` pixels around its rounded centre, a superset of its footprint) is above
the threshold. Every lens that sends light to a lit pixel is therefore lit, so the
forward projection is exact at every lit pixel, and the back projection is exact for
any image that is zero at the dark pixels.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array

from ..opencl.arrays import read, upload


def lens_reach(max_offset_px: float) -> int:
    """Half-width in pixels of the patch around a lens's rounded centre holding every
    pixel its aperture samples touch (bilinear taps included, one pixel of margin).

    Samples land at most ``max_offset_px`` pixels (per axis) from the lens's image centre
    (:meth:`plenocl.projection.weighting.ApertureGrid.pixel_offsets`), whose rounding remainder is
    at most half a pixel.
    """
    return int(np.floor(0.5 + max_offset_px)) + 2


def lit_lenses(image: np.ndarray, centres: np.ndarray, reach: int,
               threshold: float = 0.0) -> np.ndarray:
    """Bool per lens ``(rows, cols)``: does its patch hold a pixel above ``threshold``?

    Parameters
    ----------
    image
        The image ``(H, W)``.
    centres
        Rounded lens centres ``(rows * cols, 2)`` as pixel ``(col, row)``; lenses whose
        centre is missing (far outside the sensor, e.g. ``PL_NO_LENS``) are never lit.
    reach
        Patch half-width in pixels (:func:`lens_reach`).
    threshold
        Pixels at or below it are dark.

    Returns
    -------
    numpy.ndarray of bool, shape ``(n_lenses,)``
    """
    lit_px = np.asarray(image) > threshold
    h, w = lit_px.shape
    # lit pixels counted along each row (contiguous), then each lens's rows looked up:
    # half the time of a summed-area table over a 16 MP image, the same flags
    counts = np.zeros((h, w + 1), np.int32)
    np.cumsum(lit_px, axis=1, dtype=np.int32, out=counts[:, 1:])
    c = np.asarray(centres, np.int64)
    x0, x1 = np.clip(c[:, 0] - reach, 0, w), np.clip(c[:, 0] + reach + 1, 0, w)
    y0, y1 = np.clip(c[:, 1] - reach, 0, h), np.clip(c[:, 1] + reach + 1, 0, h)
    rows = y0[:, None] + np.arange(2 * reach + 1)
    inside = rows < y1[:, None]
    rows = np.minimum(rows, max(h - 1, 0))
    return np.any((counts[rows, x1[:, None]] != counts[rows, x0[:, None]]) & inside, axis=1)


def lit_lenses_on_device(kernels, image: cl_array.Array, centres: cl_array.Array,
                         reach: int, threshold: float = 0.0) -> np.ndarray:
    """:func:`lit_lenses` of a float32 device image ``(H, W)`` by ``kernels/lenses.cl``
    (``kernels``: its :class:`plenocl.opencl.program.KernelSet`), the centres an int32
    device array ``(n_lenses, 2)``: the same flags, only they come back. The
    threshold is taken to float32 as NumPy takes a Python float compared with a float32
    image (:func:`lit_lenses` on the host). The flags come back eight to a byte
    (``pack_flags``)."""
    height, width = image.shape
    n = centres.shape[0]
    out, packed = kernels.array(n, np.uint8), kernels.array(-(-n // 8), np.uint8)
    kernels.launch("lit_patches", (n,), image, np.int32(width), np.int32(height), centres,
                   np.int32(reach), np.float32(threshold), out)
    kernels.launch("pack_flags", packed.shape, out, np.int32(n), packed)
    return np.unpackbits(read(packed)[0], count=n, bitorder="little").astype(bool)


@dataclass(frozen=True)
class LensSet:
    """Device tables of the lenses a projection visits.

    Attributes
    ----------
    ids
        Flat lens indices ``ky * nkx + kx`` (int32, device), grouped by colour class.
    offsets
        ``offsets[c]:offsets[c + 1]`` are class ``c``'s entries (class ``cy * cs + cx``).
    rows
        uint8 per lens row (device): 1 when the row holds a listed lens.
    lit
        Host bool per lens ``(nky * nkx,)``: the listed lenses.
    """

    ids: cl_array.Array
    offsets: tuple[int, ...]
    rows: cl_array.Array
    lit: np.ndarray

    @property
    def count(self) -> int:
        """Number of listed lenses."""
        return self.offsets[-1]

    def fraction(self) -> float:
        """Listed lenses as a fraction of all lenses."""
        return self.count / max(self.lit.size, 1)


#: The queue attribute keeping its last lens sets (they live and go with the queue).
KEPT_ATTRIBUTE = "plenocl_lens_sets"
#: Lens sets a queue keeps: an image's coarse, early and fine projectors (one camera) ask
#: for the same lit lenses, the pair's other image for its own.
KEPT_SETS = 4


def lens_set(queue: cl.CommandQueue, lit: np.ndarray, ml_count: tuple[int, int],
             stride: int) -> LensSet:
    """The lenses flagged in ``lit`` as a :class:`LensSet` (colour stride ``stride``) on
    ``queue``: uploaded once, then kept with the queue for the next ask (the
    :data:`KEPT_SETS` asked for last; the tables are only read).

    ``lit`` is a bool per lens (flat, row-major ``(rows, cols)``); missing lenses must be
    ``False``.
    """
    cols, rows = ml_count
    lit = np.asarray(lit, bool).ravel()
    if lit.size != cols * rows:
        raise ValueError(f"lit must hold one flag per microlens ({rows} x {cols}), "
                         f"got {lit.size}")
    key = (cols, rows, int(stride), lit.tobytes())
    lock, kept = _kept_sets(queue)
    with lock:
        made = kept.pop(key, None)
        if made is not None:  # asked again: the newest
            kept[key] = made
        else:
            made = kept[key] = _uploaded_set(queue, lit.copy(), cols, rows, stride)
            while len(kept) > KEPT_SETS:
                kept.pop(next(iter(kept)))
        return made


def _kept_sets(queue: cl.CommandQueue) -> tuple[threading.Lock, dict]:
    """``queue``'s lock and kept lens sets (the least recently asked for first), made at
    the first call; a fresh pair each call where the queue object cannot hold them."""
    kept = getattr(queue, KEPT_ATTRIBUTE, None)
    if kept is None:
        kept = (threading.Lock(), {})
        try:
            setattr(queue, KEPT_ATTRIBUTE, kept)
        except AttributeError:
            pass
    return kept


def _uploaded_set(queue: cl.CommandQueue, lit: np.ndarray, cols: int, rows: int,
                  stride: int) -> LensSet:
    """The :class:`LensSet` of ``lit``, made and uploaded."""
    ky, kx = np.divmod(np.arange(cols * rows), cols)
    colour = (ky % stride) * stride + kx % stride
    ids = np.flatnonzero(lit)
    ids = ids[np.argsort(colour[ids], kind="stable")].astype(np.int32)
    counts = np.bincount(colour[ids], minlength=stride * stride)
    offsets = tuple(int(v) for v in np.concatenate([[0], np.cumsum(counts)]))
    row_flags = lit.reshape(rows, cols).any(axis=1).astype(np.uint8)
    return LensSet(upload(queue, np.concatenate([ids, np.zeros(1, np.int32)])),
                   offsets, upload(queue, row_flags), lit)
