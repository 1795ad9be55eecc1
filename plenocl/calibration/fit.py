"""Step 5 and the public entry points (docs/design.md §3): :func:`find_centers` (the grid
model and each lens's centroid combined by their uncertainties), :func:`calibrate`,
:func:`import_centers` and :func:`warn_about`."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..camera import Camera
from ..io.centres import read_centres
from .checks import image_pitch_px, validate_image
from .diagnostics import save_diagnostic, save_failure_diagnostic
from .disks import (
    choose_aperture,
    detect_disks,
    disk_centroids,
    flatten_disks,
)
from .gridmodel import grid_model
from .lenscentres import fit_disks
from .matching import LayoutMismatch, match_lattice
from .regionfile import lattice_offset, region_file_centres
from .result import CenterFit
from .spots import (
    DUPLICATE_RADIUS,
    detect_spots,
    remove_hot_pixels,
    suppress_duplicates,
    windowed_centroids,
)

#: Fraction of the expected lenses that must show a spot.
MIN_FOUND_FRACTION = 0.25

#: Of a white image's spots, at least this fraction have their nearest neighbour within
#: REGULAR_SPREAD of the typical spacing (white images, stopped down or at full aperture,
#: with vignetting or a third of the lenses dark: 0.79-1.0; particle images: 0.1-0.4).
REGULAR_SHARE = 0.6
REGULAR_SPREAD = 0.1

#: Where the centres come from: grid model, raw centroid, or both weighted by uncertainty.
METHODS = ("combined", "fit", "centroid")

#: Microlens images (px) from which full-aperture calibration fits each lens's disk; on
#: smaller ones the disk model's sampling error (0.06 px RMS at 7.7 px, rotated 2°)
#: exceeds what it resolves, and ``method="combined"`` keeps the grid model.
PER_LENS_MIN_PITCH_PX = 10.0


def find_centers(white_image, camera: Camera, *, method: str = "combined",
                 degree: int | str = "auto", fill_missing: bool = False,
                 aperture: str = "auto") -> CenterFit:
    """Measure every microlens image centre in a white image.

    Parameters
    ----------
    white_image
        ``(H, W)`` raw white image (8/16-bit integer or float): stopped down (one small
        spot per microlens) or at full aperture (one disk filling most of each lens).
    camera
        The camera (nominal layout); sets the expected pitch and the lens count.
    method
        ``"combined"`` (default): the grid model's prediction and the lens's own centroid
        weighted by their uncertainties (a lens that really sits off the lattice keeps its
        offset, noise is smoothed); ``"fit"``: the global grid model's prediction for
        each found lens; ``"centroid"``: each spot's own centroid (the paper's method).
        At full aperture ``"combined"`` fits each lens's disk with its neighbours'
        (touching disks' centroids carry their neighbours' offsets) and weighs that fit
        against the grid model refitted to all of them (docs/design.md §3; on lenses
        under ``PER_LENS_MIN_PITCH_PX``, or where the image shows no lens off the
        lattice and the disk fits are noisier than the centroids, the centres are
        ``"fit"``'s); ``"fit"`` is the grid model of
        the disks' centroids, the lattice alone.
    degree
        Grid-model polynomial degree: 1 (affine), 2, 3, or ``"auto"`` (affine unless
        a cubic distortion term is significant).
    fill_missing
        Give lenses without a spot the model's prediction instead of ``NaN``.
    aperture
        ``"stopped"`` (spots: windowed centroids), ``"full"`` (disks: centroids in a
        circular window, vignetting divided out) or ``"auto"`` (default: full when
        over ``FULL_APERTURE_FRACTION`` of the pixels are bright).

    Returns
    -------
    CenterFit
        Centres, raw centroids, the model and the measured layout.

    Raises
    ------
    ValueError
        When the image is not a plausible white image for this camera.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if degree != "auto" and degree not in (1, 2, 3):
        raise ValueError(f"degree must be 1, 2, 3 or 'auto', got {degree!r}")
    pitch = image_pitch_px(camera)
    img = remove_hot_pixels(validate_image(white_image, camera), pitch)
    kind = choose_aperture(img, pitch, aperture)
    if kind == "full":
        flat = flatten_disks(img, pitch)
        peaks, strength = detect_disks(flat, pitch)
        _check_regular(peaks, "bright disks")
        _check_count(len(peaks), camera, "bright disks")
        cents, sigma, split = disk_centroids(flat, peaks, pitch)
    else:
        peaks, strength = detect_spots(img, pitch)
        _check_regular(peaks, "bright spots")
        _check_count(len(peaks), camera, "bright spots")
        cents, sigma, split = windowed_centroids(img, peaks, pitch)
    ok = np.isfinite(cents).all(1)
    cents, strength, split = cents[ok], strength[ok], split[ok]
    keep = suppress_duplicates(cents, strength, DUPLICATE_RADIUS * pitch)
    cents, split = cents[keep], split[keep]
    _check_count(len(cents), camera, "well-formed spots")
    given = camera
    camera, (k, dev) = _matched(cents, camera)
    _check_lattice(dev, "disks" if kind == "full" else "spots")
    if kind == "full" and method == "combined":  # the disks' centroids: the lattice only
        per_lens, method = pitch >= PER_LENS_MIN_PITCH_PX, "fit"
    else:
        per_lens = False
    fit = _assemble(camera, cents, split, k, dev, sigma, img.shape, method, degree,
                    fill_missing, interior=kind == "full")
    if kind == "full" and method != "centroid":
        fit = _cut_by_the_edge(fit, flat)
    if per_lens:  # the lattice is the prior; each lens's own disk says where it is
        fit = _follow_lenses(fit, img, camera, degree, fill_missing)
    if camera.full_pixels is not None:  # a region's nominal array: onto the measured one
        camera = _placed(camera, fit, given)
    return dataclasses.replace(fit, aperture=kind, camera=camera)


def _matched(cents: np.ndarray, camera: Camera) -> tuple[Camera, tuple]:
    """:func:`match_lattice` of the spots, and the camera they were matched on: a region
    of interest cut by :meth:`Camera.cropped` (``full_pixels``) takes the lens count and
    odd-row shift its white image shows (the region's lenses were counted on the nominal
    layout, whose offset the image alone knows); a whole sensor's camera file that
    disagrees with its image is refused (:class:`LayoutMismatch`)."""
    for _ in range(2):  # the count, then a hexagonal region's shift
        try:
            return camera, match_lattice(cents, camera)
        except LayoutMismatch as exc:
            if camera.full_pixels is None:
                raise
            camera = dataclasses.replace(camera, microlens_centers=None, **exc.fix)
    return camera, match_lattice(cents, camera)


def _placed(camera: Camera, fit: CenterFit, given: Camera) -> Camera:
    """A region's camera (:meth:`Camera.cropped`, its lenses placed on the nominal layout
    and their count and shift as its white image shows them, :func:`_matched`) with its
    nominal array moved onto the measured one (``ml_offset_mm`` by the fit's shift), so
    that the simulator and the depth range see the lenses where they are; a count more
    than a lens off the region's nominal one (the camera file's count then not the whole
    sensor's) warns."""
    if max(abs(a - b) for a, b in zip(camera.ml_count, given.ml_count)) > 1:
        warnings.warn(
            f"the region's white image shows {camera.ml_count[0]} x {camera.ml_count[1]} "
            f"lenses where the camera's layout puts {given.ml_count[0]} x "
            f"{given.ml_count[1]} in it: crop the camera of the whole sensor "
            "([microlens_array] count = the whole array's lenses; docs/design.md §2)",
            stacklevel=3)
    move = np.array(fit.shift_px) * camera.pixel_pitch_mm / camera.lens_image_scale
    return dataclasses.replace(camera, microlens_centers=None,
                               ml_offset_mm=tuple(np.add(camera.ml_offset_mm, move)))


def _follow_lenses(prior: CenterFit, img: np.ndarray, camera: Camera, degree,
                   fill_missing: bool) -> CenterFit:
    """Full aperture, ``method="combined"``: every lens's disk fitted in the image
    (:func:`plenocl.lenscentres.fit_disks`, started from the lattice model), the smooth
    grid model refitted to those fits (of the lenses whose neighbours were all found:
    a disk the sensor's edge cuts is fitted less surely), and each centre moved from the
    model toward its own fit by their uncertainties (:func:`_combine`): lenses cut by the
    sensor's edge or with too little light keep the model. Where the image shows no lens
    off the lattice and the fits are no surer than the centroids
    (:func:`_lattice_suffices`), the centres are the centroids' lattice."""
    cols, rows = camera.ml_count
    h, w = img.shape
    c = prior.model
    on = (c[..., 0] >= 0) & (c[..., 0] <= w - 1) & (c[..., 1] >= 0) & (c[..., 1] <= h - 1)
    disks = fit_disks(img, prior.model, image_pitch_px(camera), lit=prior.found | ~on)
    local, noise = disks.centres, np.where(np.isfinite(disks.sigma), disks.sigma, np.nan)
    measured = prior.found & np.isfinite(noise)
    inner = measured & _surrounded(prior.found, camera, rings=1)
    fitted = inner if inner.sum() >= MIN_INTERIOR else measured  # disks the edge cuts: biased
    deg, use, model = grid_model(camera, local.reshape(-1, 2), fitted.ravel(), degree)
    inlier = use.reshape(rows, cols) & measured
    if _lattice_suffices(prior, local, model, inlier):
        deg, model, scatter, trusted = prior.degree, prior.model, 0.0, np.zeros_like(inlier)
    else:
        scatter = _lattice_scatter(local, model, noise, inlier)
        trusted = _trusted(local, model, noise, scatter, inlier, measured) & measured
    centers = _combine(model, local, np.nan_to_num(noise, nan=np.inf), scatter, trusted)
    centers[~prior.found] = model[~prior.found] if fill_missing else np.nan
    local[~measured] = np.nan
    resid = np.hypot(*(local - model)[inlier].T)
    return CenterFit(centers, local, model, prior.found, inlier, deg, *_layout(model, camera),
                     float(np.sqrt(np.mean(resid**2))), "combined", noise, scatter)


#: Significance (standard deviations of a null correlation, ``1/√n``) that the disk fits'
#: and the centroids' offsets from the lattice must share before the lenses' own offsets
#: are followed.
DEVIATION_SIGNIFICANCE = 3.0


def _lattice_suffices(prior: CenterFit, local: np.ndarray, model: np.ndarray,
                      inlier: np.ndarray) -> bool:
    """Whether the centroids' lattice (``prior``) is kept as it is: the image shows no
    lens off the lattice (:func:`_lenses_deviate`) and the disks' centroids scatter about
    their lattice no more than the disk fits (``local``) about the model refitted to them
    (soft, noisy disks; on sharp touching disks the fits are the surer, their model
    stays)."""
    if _lenses_deviate(local - model, prior.centroids - prior.model, inlier):
        return False
    return _rms_offset(prior.centroids, prior.model, prior.inlier) <= _rms_offset(
        local, model, inlier)


def _rms_offset(points: np.ndarray, model: np.ndarray, use: np.ndarray) -> float:
    """RMS (px, per axis) of ``points`` about ``model`` over the lenses ``use``."""
    d = (points - model)[use & np.isfinite(points).all(-1)]
    return float(np.sqrt(np.mean(d**2))) if d.size else np.inf


def _lenses_deviate(own: np.ndarray, centroid: np.ndarray, inlier: np.ndarray) -> bool:
    """Whether the image shows lenses really off the lattice: two independent estimates
    of each ``inlier`` lens's offset, its disk fit's from the model refitted to the fits
    (``own``) and its centroid's from the centroids' lattice (``centroid``), correlate
    beyond chance (``DEVIATION_SIGNIFICANCE / √n``). Their errors hardly correlate (the
    centroid weighs the whole disk, the fit mostly its edge; measured ρ -0.09 and 0.08 on
    exact lattices against 0.86 and 0.40 with 0.2 and 0.05 px jitter), so a real offset
    of the lenses shows however far the fits' noise exceeds their stated deviations."""
    a, b = own[inlier].ravel(), centroid[inlier].ravel()
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return False
    a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    rho = float(a @ b) / np.sqrt(max(float(a @ a) * float(b @ b), 1e-300))
    return rho * np.sqrt(ok.sum()) > DEVIATION_SIGNIFICANCE


def _cut_by_the_edge(fit: CenterFit, flat: np.ndarray) -> CenterFit:
    """At full aperture, a lens whose centre lies on the sensor but whose disk the
    sensor's edge cuts too much to be detected is still lit: where the flattened image
    is bright at the model's centre, the lens is found, at the model's centre (the
    centres there are the model's anyway)."""
    h, w = flat.shape
    c = np.rint(fit.model).astype(np.int64)
    on = (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    lit = np.zeros_like(on)
    lit[on] = flat[c[..., 1][on], c[..., 0][on]] > 0.5
    cut = ~fit.found & lit
    if not cut.any():
        return fit
    centers = fit.centers.copy()
    centers[cut] = fit.model[cut]
    return dataclasses.replace(fit, centers=centers, found=fit.found | cut)


#: Of a white image's spots, at least half lie within this many pitches of their lattice
#: node (real arrays: a few hundredths; maxima of noise or of a particle image: scattered).
ON_LATTICE = 0.1


def _check_lattice(dev: np.ndarray, what: str) -> None:
    """Refuse spots that do not form a lattice: ``dev`` is each one's distance (pitches)
    from its node (:func:`match`)."""
    share = float(np.mean(dev <= ON_LATTICE))
    if share < 0.5:
        raise ValueError(
            f"the {len(dev)} {what} found do not lie on a lattice (only {share:.0%} within "
            f"{ON_LATTICE:g} pitch of a node): this does not look like a white image. Image "
            "a uniform bright target with the main lens stopped down (e.g. f/16) or at full "
            "aperture, and check the exposure and the camera file's pitch")


def _check_regular(peaks: np.ndarray, what: str) -> None:
    """Refuse spots that are not spaced like a lattice's, whatever its pitch: a white
    image's spots have their nearest neighbour one pitch away; a particle image's lie in
    clusters (one per particle) at spacings that vary with each particle's depth."""
    if len(peaks) < 8:
        return  # too few to judge: the count check names the problem
    dist = cKDTree(peaks).query(peaks, k=2)[0][:, 1]
    typical = float(np.median(dist))
    share = float(np.mean(np.abs(dist / typical - 1) <= REGULAR_SPREAD))
    if share < REGULAR_SHARE:
        raise ValueError(
            f"this does not look like a white image: the {len(peaks)} {what} found are "
            f"irregularly spaced (only {share:.0%} have their nearest neighbour within "
            f"{REGULAR_SPREAD:.0%} of the typical {typical:.3g} px, where a white image's "
            "lie on the microlens lattice): a particle image? Calibrate with a white image "
            "of a uniform bright target, the main lens stopped down (e.g. f/16) or at full "
            "aperture")


def _check_count(n: int, camera: Camera, what: str) -> None:
    """Refuse an image with far fewer spots than the camera has lenses on the sensor."""
    nominal = camera.ideal_microlens_centers().reshape(-1, 2)
    w, h = camera.pixels
    expected = int(((nominal >= 0).all(1) & (nominal[:, 0] < w) & (nominal[:, 1] < h)).sum())
    if n < max(4, MIN_FOUND_FRACTION * expected):
        raise ValueError(
            f"found only {n} {what} where the camera expects {expected} microlens images: "
            "this does not look like a white image. Image a uniform bright target with the "
            "main lens stopped down (e.g. f/16: one small spot per lens) or at full aperture "
            "(one disk filling each lens; aperture='full', --aperture full, if the automatic "
            "choice missed it), and check the exposure and the camera file")


def _lens_grid(camera: Camera, per_spot: np.ndarray, k: np.ndarray,
               dev: np.ndarray) -> np.ndarray:
    """Scatter per-spot values ``(N, 2)`` into ``(rows, cols, 2)`` (``NaN``: no spot); of
    two spots matched to one lens the one nearer its lattice node wins."""
    cols, rows = camera.ml_count
    grid = np.full((rows, cols, 2), np.nan)
    order = np.argsort(dev, kind="stable")
    per_spot, k = per_spot[order], k[order]
    ok = k[:, 0] >= 0
    flat = k[ok, 1] * cols + k[ok, 0]
    uniq, first = np.unique(flat, return_index=True)
    grid.reshape(-1, 2)[uniq] = per_spot[ok][first]
    return grid


def _assemble(camera, cents, split, k, dev, sigma, shape, method, degree,
              fill_missing, interior: bool = False) -> CenterFit:
    """The grid model, the noise and scatter, and the centres (``interior``: the model is
    fitted to the lenses whose neighbours all have a spot, see :func:`_surrounded`)."""
    cols, rows = camera.ml_count
    grid = _lens_grid(camera, cents, k, dev)
    found = np.isfinite(grid).all(-1)
    c = grid.reshape(-1, 2)
    margin = 3 * sigma + 1
    h, w = shape
    use = found.ravel() & (c[:, 0] > margin) & (c[:, 1] > margin)
    use &= (c[:, 0] < w - 1 - margin) & (c[:, 1] < h - 1 - margin)
    if use.sum() < 6:
        use = found.ravel().copy()
    if interior:
        inner = use & _surrounded(found, camera, rings=2).ravel()
        use = inner if inner.sum() >= MIN_INTERIOR else use
    deg, use, model = grid_model(camera, c, use, degree)
    found = _drop_far_spots(found, grid, model, image_pitch_px(camera))
    grid[~found] = np.nan
    inlier = use.reshape(rows, cols) & found
    noise = _centroid_noise(_lens_grid(camera, split, k, dev), found)
    scatter = _lattice_scatter(grid, model, noise, inlier)
    combined = _combine(model, grid, noise, scatter, _trusted(grid, model, noise, scatter,
                                                                inlier, found))
    centers = {"fit": model, "centroid": grid, "combined": combined}[method].copy()
    centers[~found] = model[~found] if fill_missing else np.nan
    resid = np.hypot(*(grid - model).reshape(-1, 2)[use].T)
    return CenterFit(centers, grid, model, found, inlier, deg, *_layout(model, camera),
                     float(np.sqrt(np.mean(resid**2))), method, noise, scatter)


def _centroid_noise(split: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Per-lens centroid noise (px, per axis), ``(rows, cols)``: the split differences
    (``E|d|² = 8 σ²`` over both axes) averaged over each lens's 5 x 5 neighbourhood, so
    that it follows vignetting and exposure across the array without one spot's luck."""
    d2 = np.where(found, np.nansum(split**2, axis=-1), 0.0)
    n = ndimage.uniform_filter(found.astype(float), 5, mode="nearest")
    total = ndimage.uniform_filter(d2, 5, mode="nearest")
    # The filter's running sums leave rounding (even below zero) where a neighbourhood
    # holds no spot: such a lens has no noise to report (0), a found one counts itself.
    seen = n > 0.5 / 25
    mean = np.where(seen, np.maximum(total, 0.0) / np.where(seen, n, 1.0), 0.0)
    return np.sqrt(mean / 8.0)


def _lattice_scatter(grid, model, noise, inlier) -> float:
    """RMS (px, per axis) of the lenses' true offsets from the grid model: the centroids'
    scatter about the model with their noise taken out (0 when noise explains it all)."""
    if not inlier.any():
        return 0.0
    resid2 = ((grid - model)[inlier] ** 2).sum(-1) / 2
    return float(np.sqrt(max(float(np.mean(resid2) - np.mean(noise[inlier] ** 2)), 0.0)))


def _trusted(grid, model, noise, scatter: float, inlier, found) -> np.ndarray:
    """The spots whose centroids may move their centres: the fit's inliers, and the other
    found spots (near the sensor's edge, or outliers of the fit) whose offset from the
    model stays within 3 standard deviations of what displacement and noise explain. A
    spot cut by the sensor's edge has a biased centroid (measured: 0.6 px on a 2-degree
    array) and a blemish moves one: those keep the model."""
    r2 = np.nansum((grid - model) ** 2, axis=-1)
    return inlier | (found & (r2 <= 9 * 2 * (scatter**2 + noise**2)))


def _combine(model, grid, noise, scatter: float, trusted) -> np.ndarray:
    """Each lens's centre from the grid model and its own centroid, weighted by their
    uncertainties: ``model + w (centroid - model)`` with ``w = τ² / (τ² + σ_k²)`` (τ: the
    lenses' true scatter about the lattice, σ_k: the centroid's noise). Lenses that
    really sit off the lattice keep their offset; noise-level scatter is smoothed away.
    Only ``trusted`` spots move (not the fit's outliers: a blemish or a stray spot)."""
    w = scatter**2 / np.maximum(scatter**2 + noise**2, 1e-30)
    return model + np.where(trusted, w, 0.0)[..., None] * np.nan_to_num(grid - model)


#: Lenses with every neighbour found needed before a full-aperture grid model leaves the
#: array's outer lenses out of its fit.
MIN_INTERIOR = 12


def _surrounded(found: np.ndarray, camera: Camera, rings: int = 1) -> np.ndarray:
    """``(rows, cols)``: found lenses whose every lattice neighbour (4 in a rectangular
    array, 6 in a hexagonal one) lies in the array and was found, ``rings`` deep (2: the
    neighbours' neighbours too). A full-aperture disk's window takes in slivers of its
    neighbours' disks, symmetric about an inner lens but one-sided at the array's edge
    (0.35 px there at 65 px per lens, rectangular; 2-4 px hexagonal, where the slivers
    pull the window along), so the model is fitted to the inner lenses and predicts the
    outer ones."""
    xy = camera.lens_lattice_coords() * [1.0, camera.ml_row_pitch_mm / camera.ml_pitch_mm]
    flat = xy.reshape(-1, 2)
    want = camera.layout.neighbours
    # each lens and its neighbours; a missing neighbour (beyond the array) is index n
    dist, near = cKDTree(flat).query(flat, k=want + 1, distance_upper_bound=1.01)
    complete = np.isfinite(dist).all(1)
    ok = found.ravel()
    for _ in range(rings):
        ok = complete & np.append(ok, False)[near].all(1)  # near holds the lens itself
    return ok.reshape(found.shape)


def _drop_far_spots(found, grid, model, pitch) -> np.ndarray:
    """Spots far from the model (a hot pixel, a stray reflection) are not that lens's."""
    dist = np.hypot(*(grid - model).transpose(2, 0, 1))
    return found & ~(dist > 0.25 * pitch)


def _layout(model: np.ndarray, camera: Camera) -> tuple:
    """Rotation (deg), pitch along the array axes (px) and shift of the array centre."""
    ax = np.nanmean(np.diff(model, axis=1), axis=(0, 1))
    ay = np.nanmean(np.diff(model, axis=0), axis=(0, 1))  # hexagonal: the mean row step
    rot = camera.layout.rotation_deg(ax, ay)
    shift = model.reshape(-1, 2).mean(0) - camera.ideal_microlens_centers().reshape(-1, 2).mean(0)
    return rot, (float(np.hypot(*ax)), float(np.hypot(*ay))), (float(shift[0]), float(shift[1]))


def calibrate(white_image, camera: Camera, *, diagnostic_png: str | Path | None = None,
              method: str = "combined", degree: int | str = "auto",
              fill_missing: bool = False, aperture: str = "auto") -> Camera:
    """Calibrate the microlens image centres of ``camera`` from a white image.

    Parameters
    ----------
    white_image
        ``(H, W)`` raw white image (8/16-bit integer or float) taken with the main lens
        stopped down (one small spot per microlens) or at full aperture (one disk per
        microlens, as camera vendors supply them).
    camera
        The camera with its nominal layout (rotation and offset may be unknown).
    diagnostic_png
        Optional path of a PNG overlaying the found centres on the image; written also
        when calibration fails, then showing what was found (spots, the nominal array).
    method, degree, fill_missing, aperture
        See :func:`find_centers`.

    Returns
    -------
    Camera
        A copy with ``microlens_centers`` ``(rows, cols, 2)`` as ``(col, row)`` px and
        ``calibrated=True``; ``NaN`` marks lenses without a spot (warned about).

    Raises
    ------
    ValueError
        When the image is not a plausible white image for this camera.
    """
    try:
        fit = find_centers(white_image, camera, method=method, degree=degree,
                           fill_missing=fill_missing, aperture=aperture)
    except ValueError as exc:
        if diagnostic_png is not None:  # what was found: when it helps most
            save_failure_diagnostic(diagnostic_png, white_image, camera, str(exc))
        raise
    warn_about(fit)
    if diagnostic_png is not None:
        save_diagnostic(diagnostic_png, white_image, fit)
    return fit.camera.with_centers(fit.centers)


#: Imported centres must lie within this many pitches (median) of the camera's nominal
#: lattice: farther, the file and the camera describe different arrays.
IMPORT_TOLERANCE = 0.5


def import_centers(path: str | Path, camera: Camera) -> Camera:
    """``camera`` calibrated with the centres of a centres CSV or of LFIT's ``.mat``
    calibration (another tool's; formats in :mod:`plenocl.io.centres`), checked against
    the camera's nominal layout: refused when they lie, in the median, more than
    :data:`IMPORT_TOLERANCE` pitches from its lattice (swapped x and y, indices counted
    from 1, another camera file), since every later stage would then see the wrong
    lenses. A region of interest's camera (:meth:`Camera.cropped`) takes a file of the
    whole sensor's centres, the region's lenses then taken from it as
    :meth:`Camera.cropped` takes a calibrated camera's, or of the region's own lenses in
    its pixels (:func:`plenocl.calibration.regionfile.region_file_centres`)."""
    if camera.full_pixels is not None:
        centers = region_file_centres(path, camera, IMPORT_TOLERANCE)
    else:
        centers = read_centres(path, camera.ml_count)
        off = lattice_offset(centers, camera)
        if off > IMPORT_TOLERANCE:
            raise ValueError(f"the centres in {path} lie {off:.2f} pitches (median) from the "
                             "camera's nominal lattice: check that x_px is the column and "
                             "y_px the row, that lens indices count from 0, and that the "
                             "camera file's pitch, count, rotation and offset are this "
                             "camera's")
    found = np.isfinite(centers).all(-1)
    missing = int((~found).sum())
    if missing:
        warnings.warn(f"{missing} of {found.size} microlenses have no centre in {path} "
                      "(NaN: their pixels are not used)", stacklevel=2)
    return camera.with_centers(centers)


def warn_about(fit: CenterFit) -> None:
    """Warn about missing lenses and a noisy or distorted fit (what :func:`calibrate` and
    ``plenocl calibrate`` say besides the centres)."""
    total = fit.found.size
    if fit.n_missing:
        fate = "use the grid model's prediction" if np.isfinite(fit.centers).all() else \
            ("are NaN (fill_missing=True, plenocl calibrate --fill-missing, gives them the "
             "grid model's prediction)")
        warnings.warn(f"calibration found no spot for {fit.n_missing} of {total} microlenses "
                      f"(dead, occluded or off the sensor); their centres {fate}", stacklevel=3)
    if fit.residual_rms_px > 0.25:
        warnings.warn(f"the spot centroids scatter by {fit.residual_rms_px:.2f} px RMS about the "
                      f"grid model: the white image is noisy or the array distorted; check the "
                      "diagnostic image (plenocl calibrate --diagnostic FILE.png, or "
                      "calibrate(..., diagnostic_png=...))", stacklevel=3)
