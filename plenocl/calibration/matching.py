"""Step 3 (docs/design.md §3): the spots matched to their lenses ``(kx, ky)``: pitch and
rotation from nearest-neighbour vectors, the sub-pitch shift from the lattice phase, the
whole-pitch shift from the array's extent on the sensor; a hexagonal array's stagger."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ..camera import Camera
from ..camera.lattice import axial_basis, axial_to_offset, offset_to_axial
from .checks import image_pitch_px

#: Relative pitch error (measured vs the camera's) above which calibration refuses.
PITCH_TOLERANCE = 0.10


class LayoutMismatch(ValueError):
    """The white image shows another lens count or odd-row shift than the camera's;
    ``fix`` holds the camera fields it shows (:func:`dataclasses.replace` keywords). A
    whole sensor's camera file is then wrong; a region's count and shift, derived from
    the nominal layout (:meth:`plenocl.Camera.cropped`), follow the image."""

    def __init__(self, message: str, fix: dict) -> None:
        super().__init__(message)
        self.fix = fix


def _lattice_frame(pts: np.ndarray, pitch_nominal: float, symmetry: int = 4
                   ) -> tuple[float, float]:
    """Pitch (px) and rotation (rad) of the spot lattice from nearest-neighbour vectors
    (``symmetry``: 4 for a rectangular lattice, 6 for a hexagonal one)."""
    dist, idx = cKDTree(pts).query(pts, k=min(symmetry + 1, len(pts)))
    rough = float(np.median(dist[:, 1]))
    vec = pts[idx[:, 1:]] - pts[:, None, :]
    length = np.hypot(vec[..., 0], vec[..., 1])
    near = (length > 0.8 * rough) & (length < 1.2 * rough)
    pitch = float(np.median(length[near]))
    if abs(pitch / pitch_nominal - 1) > PITCH_TOLERANCE:
        raise ValueError(
            f"the spots of the white image are {pitch:.2f} px apart but the camera predicts "
            f"{pitch_nominal:.2f} px microlens images: check the camera file (microlens pitch, "
            "pixel pitch, focal lengths, magnification) or whether this is a white image "
            "taken with the main lens stopped down")
    theta = np.arctan2(vec[..., 1][near], vec[..., 0][near])
    return pitch, float(np.angle(np.exp(1j * symmetry * theta).mean()) / symmetry)


def match_lattice(pts: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Lens indices ``(N, 2)`` as ``(kx, ky)`` (``-1``: off the lattice) and the distance
    (in pitches) of each spot from its lattice node.

    The lattice is anchored on the spots nearest the array's nominal centre and grown
    outward, refitting an affine index-to-pixel model at each step, so a small error
    in the initial pitch or rotation never accumulates across a large array.
    """
    cols, rows = camera.ml_count
    pitch, rot = _lattice_frame(pts, image_pitch_px(camera), camera.layout.neighbours)
    centre = camera.ideal_microlens_centers().reshape(-1, 2).mean(0)
    c, s = math.cos(rot), math.sin(rot)
    basis = axial_basis(camera.odd_row_shift, camera.ml_row_pitch_mm / camera.ml_pitch_mm)
    lin = pitch * np.array([[c, -s], [s, c]]) @ basis.T  # columns: d(px)/d(q), d(px)/d(r)
    every = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2)
    middle = offset_to_axial(every, camera.odd_row_shift).mean(0)
    model = np.vstack([lin.T, centre - lin @ middle])
    f = _fractional_index(pts, model)
    near = np.argsort(np.hypot(*(pts - centre).T))[:100]
    phase = np.angle(np.exp(2j * np.pi * f[near]).mean(0)) / (2 * np.pi)
    model[2] += lin @ phase
    model = _grow_lattice(pts, model, near)
    f = _fractional_index(pts, model)
    base = np.rint(f).astype(np.int64)
    dev = np.abs(f - base).max(1)
    if camera.layout.hexagonal:
        k = _hexagonal_indices(base, dev <= 0.3, model, camera, pitch)
    else:
        k = base + _lens_count_and_shift(base[dev <= 0.3], pts[dev <= 0.3], model, camera,
                                         pitch)
    inside = (k[:, 0] >= 0) & (k[:, 0] < cols) & (k[:, 1] >= 0) & (k[:, 1] < rows)
    k[(dev > 0.3) | ~inside] = -1
    return k, dev


def _lens_count_and_shift(base: np.ndarray, pts: np.ndarray, model: np.ndarray,
                          camera: Camera, pitch: float) -> np.ndarray:
    """Check the camera file's lens count against the white image and return the index
    shift that makes lens 0 the first lens of the array; refuse a wrong count, naming
    both counts (``[microlens_array] count``).

    The rule (docs/design.md §2): the array's lenses are those whose image centre lies
    on the sensor. Along each axis the first and last lens are the outermost spots seen
    (between the 0.2 % and 99.8 % quantiles of the spots' lattice indices, so stray
    spots do not count), corrected at the sensor's edge from the fitted lattice: a spot
    whose lattice centre lies off the sensor is not a lens of the array, and a lens
    whose centre lies on the sensor within half a pitch of its edge is one, whether or
    not its cut image was detected. So an array that fills or overfills the sensor gets
    one count and one labelling, whatever the image's noise or encoding.
    """
    count = np.array(camera.ml_count)
    if len(base) < 10:
        return _whole_pitch_shift(base, *camera.ml_count)
    size = np.array(camera.pixels, float)
    lo, hi = np.rint(np.percentile(base, [0.2, 99.8], axis=0)).astype(int)
    first, last = lo.copy(), hi.copy()
    for axis in (0, 1):
        other = float(np.median(base[:, 1 - axis]))
        edge = _EdgeLattice(model, axis, other, size[axis], pitch)
        first[axis], last[axis] = edge.boundary(lo[axis], -1), edge.boundary(hi[axis], +1)
    seen = last - first + 1
    if (seen != count).any():
        raise LayoutMismatch(
            f"the white image shows about {seen[0]} x {seen[1]} microlens images (columns x "
            f"rows, counting those whose centre lies on the sensor) but the camera file has "
            f"{count[0]} x {count[1]} microlenses: correct [microlens_array] count = "
            "[columns, rows] in the camera file" + _dark_margin(pts, size, pitch, seen < count),
            dict(ml_count=tuple(int(n) for n in seen)))
    return -first


def _dark_margin(pts: np.ndarray, size: np.ndarray, pitch: float, short: np.ndarray) -> str:
    """Where fewer lenses are seen than the file has and the spots leave more than a
    pitch of the sensor dark on a side (one dark edge column or row does): that the
    array may be partly dark, not the count wrong ("" otherwise)."""
    lo, hi = np.min(pts, axis=0), np.max(pts, axis=0)
    dark = [f"{'xy'[axis]} {lo[axis]:.0f}-{hi[axis]:.0f} of {size[axis]:.0f} px"
            for axis in (0, 1) if short[axis]
            and (lo[axis] > pitch or size[axis] - 1 - hi[axis] > pitch)]
    if not dark:
        return ""
    return (f"; or, if the count is right, part of the array is dark: the lit lenses span "
            f"{' and '.join(dark)} (occluded, vignetted or outside the illumination): "
            "light the whole array for the white image")


def _hexagonal_indices(base: np.ndarray, ok: np.ndarray, model: np.ndarray,
                       camera: Camera, pitch: float) -> np.ndarray:
    """Lens indices ``(kx, ky)`` of spots at axial lattice indices ``base`` (``ok``: on
    the lattice) on a hexagonal array, with the counting rule of
    :func:`_lens_count_and_shift` (docs/design.md §3): row 0 is the first row whose
    centres lie on the sensor, lens 0 of the even rows their first such lens, and the
    odd rows sit ``odd_row_shift`` pitches from them; a camera file whose count or shift
    disagrees with the image is refused, naming the fix."""
    if ok.sum() < 10:
        raise ValueError(f"only {int(ok.sum())} spots lie on a hexagonal lattice: too few to "
                         "number the lenses; check the white image and the camera file")
    size, (cols, rows) = np.array(camera.pixels, float), camera.ml_count
    q, r = base[ok].T
    lo, hi = np.rint(np.percentile(r, [0.2, 99.8])).astype(int)
    # along the rows' normal: q drifts by -shift per row (e2 leans by shift along a row)
    middle = float(np.median(r))
    row_pitch = pitch * camera.ml_row_pitch_mm / camera.ml_pitch_mm
    edge = _EdgeLattice(model, 1, float(np.median(q)), size[1], row_pitch,
                        drift=camera.odd_row_shift, origin=middle)
    first_r, last_r = edge.boundary(lo, -1), edge.boundary(hi, +1)
    even = first_r + 2 * int(round((np.median(r) - first_r) / 2))
    row = q[r == even]
    if len(row) == 0:
        raise ValueError("no spot in the middle row of the white image; check it")
    edge = _EdgeLattice(model, 0, float(even), size[0], pitch)
    first_q, last_q = edge.boundary(int(row.min()), -1), edge.boundary(int(row.max()), +1)
    seen = (last_q - first_q + 1, last_r - first_r + 1)
    if seen != (cols, rows):
        raise LayoutMismatch(
            f"the white image shows about {seen[0]} x {seen[1]} microlens images (lenses in "
            f"an even row x rows, counting those whose centre lies on the sensor) but the "
            f"camera file has {cols} x {rows} microlenses: correct [microlens_array] count = "
            "[columns, rows] in the camera file", dict(ml_count=tuple(map(int, seen))))
    origin = np.array([first_q + camera.odd_row_shift * (even - first_r), first_r])
    k = axial_to_offset(base - origin.astype(np.int64), camera.odd_row_shift)
    _check_stagger(k[ok], camera)
    return k


def _check_stagger(k: np.ndarray, camera: Camera) -> None:
    """Refuse a hexagonal camera file whose odd rows are shifted the wrong way: then most
    odd rows show a lens just before their lens 0 (or after their last) and lack the
    lens the file puts at their other end. An array that overfills the sensor may show
    both in its odd rows (one lens more than the count): either labelling then holds,
    and the lens beyond the count is not used."""
    cols = camera.ml_count[0]
    wrong, end = (-1, cols - 1) if camera.odd_row_shift > 0 else (cols, 0)
    odd = k[:, 1] % 2 == 1
    rows_odd = np.unique(k[odd, 1])
    rows_wrong = np.unique(k[odd & (k[:, 0] == wrong), 1])
    rows_end = np.unique(k[odd & (k[:, 0] == end), 1])
    half = len(rows_odd) / 2
    if len(rows_odd) and len(rows_wrong) > half and len(rows_end) <= half:
        raise LayoutMismatch(
            f"the white image's odd rows of lenses sit {-camera.odd_row_shift:+g} pitch from "
            f"the even ones, the camera file says {camera.odd_row_shift:+g}: set "
            f"[microlens_array] odd_row_shift = {-camera.odd_row_shift:g}",
            dict(ml_odd_row_shift=-camera.odd_row_shift))


class _EdgeLattice:
    """Lattice node centres along one axis, on the lattice line through the spots'
    middle, against the sensor's extent ``[-0.5, size - 0.5]`` along that axis."""

    def __init__(self, model: np.ndarray, axis: int, other: float, size: float,
                 pitch: float, drift: float = 0.0, origin: float = 0.0) -> None:
        self.model, self.axis, self.other = model, axis, other
        self.size, self.pitch = size, pitch
        self.drift, self.origin = drift, origin  # the other index moves by -drift per step

    def centre(self, k: int) -> float:
        idx = np.empty(2)
        idx[self.axis] = k
        idx[1 - self.axis] = self.other - self.drift * (k - self.origin)
        return float((idx @ self.model[:2] + self.model[2])[self.axis])

    def margin(self, k: int) -> float:
        """Distance of node ``k``'s centre inside the sensor's edge (negative: off it)."""
        c = self.centre(k)
        return min(c + 0.5, self.size - 0.5 - c)

    def boundary(self, k: int, side: int) -> int:
        """The outermost lens index from the outermost spot ``k`` on ``side`` (-1, +1)."""
        for _ in range(3):  # spots centred off the sensor are not lenses of the array
            if self.margin(k) >= 0:
                break
            k -= side
        beyond = k + side  # a lens cut by the sensor's edge, detected or not
        if 0 <= self.margin(beyond) < self.pitch / 2:
            k = beyond
        return k


def _grow_lattice(pts: np.ndarray, model: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Refit the affine model on spots within a radius (lens units) of the anchor spots,
    doubling the radius until every spot is included."""
    radius = 8.0
    while True:
        f = _fractional_index(pts, model)
        idx = np.rint(f)
        grown = np.abs(f - f[anchor].mean(0)).max(1) <= radius
        sel = grown & (np.abs(f - idx).max(1) <= 0.3)
        if sel.sum() >= 3:
            design = np.column_stack([idx[sel], np.ones(int(sel.sum()))])
            model, *_ = np.linalg.lstsq(design, pts[sel], rcond=None)
        if grown.all():
            return model
        radius *= 2


def _fractional_index(pts: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Invert the affine model ``px = [kx, ky, 1] @ model`` for fractional indices."""
    return np.linalg.solve(model[:2].T, (pts - model[2]).T).T


def _whole_pitch_shift(base: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Shift of the indices that puts the most spots inside the array (smallest wins ties)."""
    best, best_n = np.zeros(2, np.int64), -1
    for dx, dy in sorted(((a, b) for a in range(-3, 4) for b in range(-3, 4)),
                         key=lambda t: t[0] ** 2 + t[1] ** 2):
        kx, ky = base[:, 0] + dx, base[:, 1] + dy
        n = int(((kx >= 0) & (kx < cols) & (ky >= 0) & (ky < rows)).sum())
        if n > best_n:
            best, best_n = np.array([dx, dy]), n
    return best
