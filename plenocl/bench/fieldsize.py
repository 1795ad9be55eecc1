"""Benchmark: where a pair's error sits by field position and depth, stage by stage, on
cameras of several sizes with the same optics, voxel and seeding (issue 45;
``benchmarks/field_size.py``, docs/design.md §7.4).

Each camera is the paper's optics on a window of microlenses (``paper_optics``) with a
scene of ray-traced particles moved by a known motion (``budget_scene``: a uniform
displacement, or the rotation about x). The
chain runs as ``process_pair`` runs it, and every stage is compared with the truth:

- **volume**: the first volume's particles (its peaks, those along one line of sight
  merged and centred, :class:`plenocl.piv.refinement.SightLines`) against the true
  particles within :data:`MATCH` voxels: position error; also the raw peaks per true
  particle and the share recovered;
- **paired**: the particle pairs of the two volumes (along the refined predictor), each
  matched to a true particle by its midpoint: displacement error against that
  particle's own;
- **fitted**: the same pairs after the fit to the raw images;
- **correlation**: the correlation's vectors;
- **vectors**: the final field (``process_pair``'s);
- **across/along**: the same errors in each window's line-of-sight frame
  (:func:`sight_stage`): the two components across the line (in the grid's mean lateral
  voxel) as "lateral", the one along it (in depth voxels) as "depth". One camera places
  a point worst along its line of sight, which off the axis leans by ``r / s_o``, so
  what it misses there shows in x and y as a radial error; across the line it does not.

Errors are RMS lateral (over x and y) / depth in voxels, over everything and by distance
from the optical axis (mm) and by depth (``|z|`` in mm: the focal zone within 2 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..optics.sightline import line_of_sight, sight_frames
from ..peaks import find_particles
from ..pipeline import process_pair
from ..pipeline.pair import known_backgrounds
from ..piv.imagefit import ImageFit
from ..piv.refinement import (
    FocalZone,
    SightLines,
    pair_peaks,
    refine_with_particles,
    repredicted,
    volume_particles,
)
from .accuracy_section import UNIFORM, Motion, budget_scene, vector_errors

#: Distance from the optical axis (mm) of the radial bins; the last is open.
RADII_MM = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)
#: Depth zones, ``|z|`` (mm): the focal zone, the middle, the faces.
ZONES_MM = ((0.0, 2.0), (2.0, 6.0), (6.0, np.inf))
#: A found particle (or a pair's midpoint) is a true one within this ellipsoid (x, y, z
#: voxels).
MATCH = (1.0, 1.0, 3.0)
#: Fewest entries for a bin's RMS to be printed.
MIN_BIN = 3


@dataclass
class Stage:
    """One stage's errors: ``where`` ``(n, 3)`` (x, y, z) mm of each entry, ``error``
    ``(n, 3)`` (x, y, z) voxels."""

    name: str
    where: np.ndarray
    error: np.ndarray

    def rms(self, select: np.ndarray | None = None) -> tuple[float, float, int]:
        """Lateral and depth RMS (voxels) and the count of the entries ``select``."""
        e = self.error if select is None else self.error[select]
        if len(e) < MIN_BIN:
            return float("nan"), float("nan"), len(e)
        return (float(np.sqrt(np.mean(e[:, :2] ** 2))), float(np.sqrt(np.mean(e[:, 2] ** 2))),
                len(e))

    def by_radius(self) -> list[tuple[float, float, int]]:
        """:meth:`rms` per bin of :data:`RADII_MM`."""
        r = np.hypot(self.where[:, 0], self.where[:, 1])
        edges = (*RADII_MM, np.inf)
        return [self.rms((r >= lo) & (r < hi)) for lo, hi in zip(edges[:-1], edges[1:])]

    def by_zone(self) -> list[tuple[float, float, int]]:
        """:meth:`rms` per depth zone of :data:`ZONES_MM`."""
        z = np.abs(self.where[:, 2])
        return [self.rms((z >= lo) & (z < hi)) for lo, hi in ZONES_MM]


def matched(found: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(truth, found)`` of each true position's nearest found one within
    :data:`MATCH` (both ``(N, 3)`` (x, y, z) voxels)."""
    if not len(found) or not len(truth):
        return np.zeros(0, int), np.zeros(0, int)
    scale = 1.0 / np.asarray(MATCH)
    dist, idx = cKDTree(found * scale).query(truth * scale, distance_upper_bound=1.0)
    hit = np.flatnonzero(np.isfinite(dist))
    return hit, idx[hit]


def pair_stage(name: str, pairs, grid, scene) -> Stage:
    """The displacement errors of ``pairs`` matched by their midpoints to the true
    particles of ``scene`` (each one's own displacement, voxels)."""
    start, end = grid.to_index(scene.pa), grid.to_index(scene.pb)
    it, ip = matched(pairs.midpoints, (start + end) / 2)
    mid_mm = (scene.pa + scene.pb) / 2
    return Stage(name, mid_mm[it], pairs.displacements[ip] - (end - start)[it])


def sight_stage(stage: Stage, camera, grid) -> Stage:
    """``stage``'s errors in each entry's line-of-sight frame
    (:func:`plenocl.optics.sightline.sight_frames`): across the line (two components,
    mm over the grid's mean lateral voxel) and along it (mm over the depth voxel)."""
    dz, dy, dx = grid.spacing
    mm = stage.error * np.array([dx, dy, dz])
    frames = sight_frames(line_of_sight(camera, stage.where))
    local = np.einsum("nji,nj->ni", frames, mm)  # R^T e
    return Stage("across/along", stage.where,
                 local / np.array([(dx + dy) / 2, (dx + dy) / 2, dz]))


def field_stage(name: str, res, grid, motion: Motion = UNIFORM) -> Stage:
    """The errors of the valid vectors of ``res`` at their window centres against
    ``motion``."""
    return Stage(name, *vector_errors(res, grid, motion))


@dataclass
class SizeSplit:
    """The stages of one camera size, the peaks per true particle and the share
    recovered by radial bin, and the chain's seconds."""

    lenses: tuple[int, int]
    grid_shape: tuple[int, int, int]
    particles: int
    stages: list[Stage]
    peaks_per_particle: list[float]
    recovered: list[float]
    seconds: float


def size_split(cam, grid, proj, seeding: float, seed: int, queue,
               motion: Motion = UNIFORM) -> SizeSplit:
    """Run the default chain on one scene of ``cam`` moved by ``motion`` and split its
    error by stage."""
    scene = budget_scene(cam, grid, seeding, seed, queue, motion=motion)
    pair = process_pair(scene.raw_a, scene.raw_b, proj, particles=False)
    corr, focus, sight = pair.piv, FocalZone.of(cam, grid), SightLines.of(cam, grid)
    pa, pb = (volume_particles(v, sight=sight) for v in (pair.vol_a, pair.vol_b))
    truth = grid.to_index(scene.pa)
    it, ip = matched(pa, truth)
    stages = [Stage("volume", scene.pa[it], pa[ip] - truth[it])]
    predictor = repredicted(corr, pa, pb, focus=focus, sight=sight)
    stages.append(pair_stage("paired", pair_peaks(pa, pb, predictor), grid, scene))
    fit = ImageFit(cam, grid, (scene.raw_a, scene.raw_b), queue=queue,
                   backgrounds=known_backgrounds(pair.info_a, pair.info_b))
    stages.append(pair_stage("fitted", pair_peaks(pa, pb, predictor, fit=fit), grid, scene))
    stages.append(field_stage("correlation", corr, grid, motion))
    final = refine_with_particles(corr, pair.vol_a, pair.vol_b, focus=focus, fit=fit,
                                  sight=sight)
    stages.append(field_stage("vectors", final, grid, motion))
    stages.append(sight_stage(stages[-1], cam, grid))
    raw, _ = find_particles(pair.vol_a, reference="robust")
    per, rec = _per_radius(scene.pa, truth, raw, it)
    return SizeSplit(tuple(cam.ml_count), grid.shape, scene.count, stages, per, rec,
                     sum(pair.seconds.values()))


def _per_radius(pos_mm, truth, raw_peaks, recovered_idx) -> tuple[list[float], list[float]]:
    """Per radial bin: the volume's raw peaks near each true particle (within 1.5
    lateral and 8 depth voxels: a particle seen as several) and the share recovered."""
    near = cKDTree(raw_peaks / [1.5, 1.5, 8.0]).query_ball_point(truth / [1.5, 1.5, 8.0], 1.0)
    count = np.array([len(n) for n in near])
    hit = np.zeros(len(truth), bool)
    hit[recovered_idx] = True
    r = np.hypot(pos_mm[:, 0], pos_mm[:, 1])
    edges = (*RADII_MM, np.inf)
    per, rec = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (r >= lo) & (r < hi)
        per.append(float(count[sel].mean()) if sel.any() else float("nan"))
        rec.append(float(hit[sel].mean()) if sel.any() else float("nan"))
    return per, rec


def _cell(v: tuple[float, float, int]) -> str:
    lat, dep, n = v
    return f"{'-':>17s}" if n < MIN_BIN else f"{lat:.3f}/{dep:.2f} ({n:4d})"


def split_table(split: SizeSplit) -> str:
    """One size's stages as text: all, by radius, by depth zone."""
    edges = [f"{lo:g}-{hi:g}" for lo, hi in zip(RADII_MM[:-1], RADII_MM[1:])]
    heads = [*(f"r {e} mm" for e in edges), f"r > {RADII_MM[-1]:g} mm",
             *(f"|z| {lo:g}-{hi:g}" for lo, hi in ZONES_MM)]
    lines = [f"{split.lenses[0]} x {split.lenses[1]} lenses, grid {split.grid_shape} "
             f"(z, y, x), {split.particles} particles; the chain {split.seconds:.1f} s",
             f"{'stage':12s} {'all':>17s} | " + " ".join(f"{h:>17s}" for h in heads)]
    for st in split.stages:
        lines.append(f"{st.name:12s} {_cell(st.rms()):>17s} | "
                     + " ".join(_cell(c) for c in (*st.by_radius(), *st.by_zone())))
    lines.append(f"{'peaks/part.':12s} {'':>17s} | "
                 + " ".join(f"{v:17.2f}" for v in split.peaks_per_particle))
    lines.append(f"{'recovered':12s} {'':>17s} | "
                 + " ".join(f"{v:17.0%}" for v in split.recovered))
    return "\n".join(lines)


def pooled(splits: list[SizeSplit]) -> SizeSplit:
    """Several scenes of one camera as one: every stage's entries together (so each
    radial bin's RMS is taken over all of them), the particles and seconds summed, the
    peaks per particle and the share recovered averaged over the scenes.

    The band near the axis is small (within 5 mm: about 5 % of a full-size scene's
    vectors, some 15 independent windows), so one scene's ratio of a far band to it
    varies by about 0.1-0.15 between scenes; the pooled ratio is the figure to compare.
    """
    if not splits:
        raise ValueError("pooled needs at least one SizeSplit")
    first = splits[0]
    stages = [Stage(st.name, np.concatenate([s.stages[k].where for s in splits]),
                    np.concatenate([s.stages[k].error for s in splits]))
              for k, st in enumerate(first.stages)]
    return SizeSplit(first.lenses, first.grid_shape, sum(s.particles for s in splits),
                     stages, list(np.mean([s.peaks_per_particle for s in splits], axis=0)),
                     list(np.mean([s.recovered for s in splits], axis=0)),
                     sum(s.seconds for s in splits))


def stage_named(split: SizeSplit, name: str) -> Stage:
    """The stage ``name`` of ``split``."""
    return next(st for st in split.stages if st.name == name)


def off_axis_ratio(stage: Stage, band: int = 4) -> tuple[float, float]:
    """The lateral and depth RMS of radial bin ``band`` (20-25 mm) over those on the
    axis (the first bin)."""
    rows = stage.by_radius()
    return rows[band][0] / rows[0][0], rows[band][1] / rows[0][1]
