"""Experiments for issue 15 on the error-budget case of ``benchmarks/accuracy.py``, each
against single-frame reconstruction in the same run: motion-tracking enhancement (MTE,
Novara et al. 2010) and ways to remove haze and ghosts.

    python benchmarks/accuracy_experiments.py [--seeding 0.05] [--cycles 2]

Single frame: ``reconstruct`` (MLEM 30 iterations) of each exposure, then ``piv3d``. MTE:
warp each volume onto the other exposure's time with the measured displacement (cubic
B-spline deformation), combine it with that exposure's own volume (arithmetic mean, or
geometric mean, which zeroes voxels lit in only one of them), re-reconstruct from that
first guess (MLEM, 10 iterations) and correlate again; repeated for ``--cycles``.
Haze and ghosts: the MLEM volume thresholded at 1, 3 or 10 % of its 99.9th percentile,
raised to a power (1.5, 2), zero-pixel masking (0.3), and 5 SMART iterations after MLEM.
None of these is part of the default chain.
"""

from __future__ import annotations

import argparse

import numpy as np
from accuracy import SHIFT_VOX, VOXEL_MM, errors, setup

from plenocl import Projector, get_queue, piv3d, random_particles, reconstruct
from plenocl.metrics import quality_q, recovery, render_particles
from plenocl.piv.deform import deform, prepare, resample
from plenocl.simulate import simulate_image


def dense_displacement(res, shape) -> np.ndarray:
    """The PIV field on every voxel, ``(3, nz, ny, nx)`` as ``(dz, dy, dx)`` voxels."""
    field = np.nan_to_num(np.stack([res.w, res.v, res.u]).astype(np.float64))
    target = tuple(np.arange(n, dtype=float) for n in shape)
    return resample(field, (res.z, res.y, res.x), target).astype(np.float32)


def mte_cycle(raw_a, raw_b, proj, vol_a, vol_b, res, combine: str):
    """One MTE cycle: the new volumes and their displacement field."""
    d = dense_displacement(res, proj.grid.shape)
    b_at_a = np.clip(deform(prepare(vol_b, 3), d, 1.0, 3), 0, None)
    a_at_b = np.clip(deform(prepare(vol_a, 3), d, -1.0, 3), 0, None)
    if combine == "mean":
        guess_a, guess_b = (vol_a + b_at_a) / 2, (vol_b + a_at_b) / 2
    else:
        guess_a, guess_b = np.sqrt(vol_a * b_at_a), np.sqrt(vol_b * a_at_b)
    new_a = reconstruct(raw_a, proj, iterations=10, start=guess_a)
    new_b = reconstruct(raw_b, proj, iterations=10, start=guess_b)
    return new_a, new_b, piv3d(new_a, new_b)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeding", type=float, default=0.05)
    parser.add_argument("--cycles", type=int, default=2)
    args = parser.parse_args()
    queue = get_queue()
    cam, grid = setup((96, 64))
    proj = Projector(cam, grid, queue)
    shift_mm = SHIFT_VOX * np.array(VOXEL_MM)
    box = tuple((lo + 0.3, hi - 0.3) for lo, hi in (grid.x, grid.y, grid.z))
    count = int(round(args.seeding * cam.ml_count[0] * cam.ml_count[1]))
    pos, inten = random_particles(box, count=count, seed=3, intensity=2e4)
    pa, pb = pos - shift_mm / 2, pos + shift_mm / 2
    kw = dict(rays_per_particle=2000, blur_px=0.8, photon_noise=True, background=20.0,
              read_noise=3.0, queue=queue)
    raw_a, raw_b = (simulate_image(cam, p, inten, seed=s, **kw) for p, s in ((pa, 6), (pb, 7)))
    true_a = render_particles(grid, pa, 1.0, sigma_vox=1.0)

    def report(label, vol_a, res) -> None:
        e, rep = errors(res, grid), recovery(vol_a, grid, pa)
        print(f"{label:24s} lateral {e['lateral']:.3f} depth {e['depth']:.2f} voxel, valid "
              f"{e['valid']:.0%}, Q {quality_q(vol_a, true_a):.3f}, recovered "
              f"{rep.fraction:.0%}, ghosts {rep.ghost_fraction:.0%}, non-zero voxels "
              f"{np.mean(vol_a > 0):.0%}", flush=True)

    print(f"seeding {args.seeding} particles per lens ({count}); grid {grid.shape}")
    vol_a, vol_b = reconstruct(raw_a, proj), reconstruct(raw_b, proj)
    res = piv3d(vol_a, vol_b)
    report("single frame", vol_a, res)
    for combine in ("mean", "geometric"):
        a, b, r = vol_a, vol_b, res
        for cycle in range(args.cycles):
            a, b, r = mte_cycle(raw_a, raw_b, proj, a, b, r, combine)
            report(f"MTE {combine}, cycle {cycle + 1}", a, r)
    for label, (a, b) in haze_variants(raw_a, raw_b, proj, vol_a, vol_b):
        report(label, a, piv3d(a, b))


def haze_variants(raw_a, raw_b, proj, vol_a, vol_b):
    """``(label, (vol_a, vol_b))`` of each haze/ghost treatment of the MLEM volumes."""
    for frac in (0.01, 0.03, 0.1):
        cut = [np.where(v > frac * np.percentile(v, 99.9), v, 0) for v in (vol_a, vol_b)]
        yield f"threshold {frac:g} of p99.9", cut
    for power in (1.5, 2.0):
        yield f"power {power:g}", [v**power for v in (vol_a, vol_b)]
    yield "masking 0.3", [reconstruct(r, proj, mask_fraction=0.3) for r in (raw_a, raw_b)]
    yield "MLEM then SMART 5", [reconstruct(r, proj, "smart", start=v, iterations=5)
                                for r, v in ((raw_a, vol_a), (raw_b, vol_b))]


if __name__ == "__main__":
    main()
