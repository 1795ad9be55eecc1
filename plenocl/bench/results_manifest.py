"""What ``docs/results.md`` shows: the benchmark runs of ``python
benchmarks/results_page.py`` (:mod:`plenocl.bench.results`), in page order.

Each entry's options keep the whole manifest within :data:`BUDGET_MINUTES` on 2 CPU cores
with PoCL (``--list`` prints the estimates, each entry's wall time on such a machine,
rounded up): the error budget on the reduced 96 x 64-lens
camera at one seeding, one pair at the paper's full size as the headline, the projector
without its stored-matrix comparison of 122 M weights and the slow reconstructions of
the rotated array, and two images per calibration case instead of three. Each method
paragraph says what is measured and against which baseline; the figures and the date
come from the run itself.
"""

from __future__ import annotations

from .results import Entry

__all__ = ["BUDGET_MINUTES", "MANIFEST"]

#: The whole page's wall time on 2 CPU cores with PoCL, at most (minutes): 62 until the
#: whole sensor's three `field_size.py` rows under the rotation and at 0.02 and 0.1
#: particles per microlens (27 minutes, issue 45's lines) joined it, 90 until the paper's
#: synthetic case took six scenes per count instead of three (each scene one particle of
#: 180 in issue 47's 97 % line) and the focal zone's entry came, 93 until the region of
#: interest and the shallow volume came.
BUDGET_MINUTES = 98.0

#: `benchmarks/field_size.py` on both cameras' three scenes (the `field-size` entries).
FIELD_SIZE = ("benchmarks/field_size.py", "--lenses", "96", "64", "289", "193", "--seeds",
              "1", "2", "3")

#: Every entry of the page, in page order within each section.
MANIFEST: tuple[Entry, ...] = (
    Entry(
        "demo", "Accuracy",
        "The built-in example (`plenocl demo`)",
        "The README's first command, the boundary-layer demo on the small camera (850 x 850 "
        "px behind 50 x 50 lenses, 48 x 48 x 32 voxels), run in a fresh folder so nothing "
        "is resumed: the velocity RMS error of the valid vectors against the truth averaged "
        "over each final window, lateral and in depth, the mean profile's error, and the "
        "particles the default reconstruction recovers beside the paper's MART on the same "
        "images (the baseline).",
        ("benchmarks/demo_run.py",), 0.5),
    Entry(
        "demo-two-cameras", "Accuracy",
        "The built-in example seen by two cameras",
        "`plenocl demo --cameras 2`: the small boundary-layer demo's particles seen by two "
        "cameras 25 degrees apart about the depth axis, each calibrated from its white "
        "image and its pose from a dot target (from a pose as built 0.4 degree and 0.1 mm "
        "off), processed by `process_pair` with both cameras; the first camera alone on "
        "the same particles is the baseline: the velocity RMS error against the "
        "window-averaged truth, lateral and in depth, the particles recovered and the "
        "poses' errors, from a fresh folder.",
        ("benchmarks/demo_run.py", "--cameras", "2"), 1.0),
    Entry(
        "accuracy", "Accuracy",
        "Error budget at the paper's optics, 96 x 64 microlenses",
        "The velocity error of the default chain (`plenocl.process_pair`) at the paper's "
        "optics and voxel (0.183 x 0.175 x 0.133 mm, 20 mm of depth) on a 96 x 64-lens "
        "window of its 16 MP sensor, at 0.05 particles per microlens, for a uniform "
        "displacement and a solid-body rotation about the lateral x axis: RMS error of the "
        "valid vectors against the true displacement at the window centres, lateral and in "
        "depth (in voxels; in focus, near and far apart), from ray-traced raw images with "
        "0.8 px blur, photon and read noise. On the same images in the same run: PIV of "
        "volumes rendered from the true particles (what the windows alone cannot resolve), "
        "the default without the particles' fit to the raw images, its volumes correlated "
        "without the particle refinement, and the baseline, the chain before (voxels "
        "reconstructed and correlated); with each reconstruction's quality (Q, particles "
        "recovered, ghost intensity) and seconds per pair.",
        ("benchmarks/accuracy.py", "--lenses", "96", "64", "--seeding", "0.05"), 1.0),
    Entry(
        "cameras", "Accuracy",
        "Several cameras in one reconstruction",
        "The paper's optics and voxel on 116 x 78 lenses, 0.05 particles per microlens, "
        "uniform displacement, ray-traced images with 0.8 px blur, photon and read noise: "
        "`plenocl.process_pair`'s default chain on one camera (the baseline), on the same "
        "camera turned 12.5 degrees about y (a world grid through its pose), and on two "
        "cameras 25 degrees apart looking at the grid's centre (one volume from both "
        "cameras' images, the particles fitted to both cameras' raw images), on the same "
        "world particles in the same run, three scenes: the RMS error of the valid "
        "vectors in the world grid's voxels (x, y lateral; z depth), the particles the "
        "first volume recovers, its ghost intensity and seconds per pair (each camera's "
        "projectors built once before the rows, as a batch worker does, and timed apart); "
        "and the two cameras with 5 sub-voxel iterations instead of the default 7.",
        ("benchmarks/cameras.py", "--seeds", "1", "2", "3", "--fine-iterations", "5"), 5.0),
    Entry(
        "cameras-sweep", "Accuracy",
        "Several cameras: the angle between them, and a third",
        "The entry above's scene (seed 1) and chain: one camera (the baseline), two cameras "
        "25, 10 and 40 degrees apart, and three cameras at -25, 0 and 25 degrees, on the "
        "same world particles in the same run: the RMS error of the valid vectors in the "
        "world grid's voxels, the particles the first volume recovers, its ghost "
        "intensity and seconds per pair.",
        ("benchmarks/cameras.py", "--apart", "25", "10", "40", "--three", "--seeds", "1"),
        5.5),
    Entry(
        "robust-means", "Accuracy",
        "The particle refinement's window means: fit-weighted against robust and plain",
        "The `cameras` entry's scenes (116 x 78 lenses, three scenes), one camera and two "
        "cameras 25 degrees apart: each pair reconstructed and correlated once, then the "
        "particle refinement (the fit to the raw images, the pairing, the window means) "
        "run three times on the same volumes: each window's mean weighted by its pairs' "
        "fitted uncertainties (the default), the pairs alike within 3 robust standard "
        "deviations of the window's median (the previous default), and the pairs alike "
        "within the search range (the baseline, the refinement before both): the RMS "
        "error of the valid vectors, the valid share, and the RMS over every vector, the "
        "outliers' replacements included.",
        ("benchmarks/robust_means.py",), 4.0),
    Entry(
        "field-size", "Accuracy",
        "Where the error sits as the camera grows: 96 x 64 against the whole sensor",
        "The default chain on the paper's optics, voxel and seeding (0.05 particles per "
        "microlens, uniform displacement, ray-traced images with 0.8 px blur and noise) on "
        "96 x 64 lenses and on the whole 16 MP sensor (289 x 193), three scenes each: the "
        "RMS error (lateral / depth voxels) of every stage (the volume's particles, their "
        "pairs, the pairs fitted to the raw images, the correlation, the final vectors) "
        "over everything, by distance from the optical axis and by depth; each scene's "
        "table, then the scenes pooled, and the final vectors' error 20-25 mm off the axis "
        "over that within 5 mm. The reduced camera is the baseline: the same chain where "
        "the field holds no far field.",
        FIELD_SIZE, 5.5),
    Entry(
        "field-size-rotation", "Accuracy",
        "The camera's size under the rotation",
        "As `field-size`, under a solid-body rotation of 2 degrees about the grid's lateral "
        "x axis through its centre (the error budget's rotation) instead of the uniform "
        "displacement: the whole sensor's error against the reduced camera's (issue 45 "
        "asks within 1.5x).",
        (*FIELD_SIZE, "--motion", "rotation"), 10.0),
    Entry(
        "field-size-sparse", "Accuracy",
        "The camera's size at 0.02 particles per microlens",
        "As `field-size` at 0.02 particles per microlens instead of 0.05.",
        (*FIELD_SIZE, "--seeding", "0.02"), 5.0),
    Entry(
        "field-size-dense", "Accuracy",
        "The camera's size at 0.1 particles per microlens",
        "As `field-size` at 0.1 particles per microlens instead of 0.05.",
        (*FIELD_SIZE, "--seeding", "0.1"), 12.0),
    Entry(
        "region", "Accuracy",
        "A region of interest off the sensor's centre",
        "Particles seen through a region of interest (1200 x 900 px of the paper's 16 MP "
        "sensor, 12.9 mm right of and 8.0 mm below its centre in the object), the region's "
        "camera cut from the whole sensor's (`Camera.cropped`) and calibrated from the "
        "region's cut of the white image, against the same particles seen by the whole "
        "sensor on the same grid (the baseline) and against the region described as a "
        "sensor of its own (its axis at its own centre): the particles matched, their RMS "
        "error and the peaks' median offset from their nearest true particle.",
        ("benchmarks/region.py",), 1.0),
    Entry(
        "shallow", "Accuracy",
        "Depth motion in a volume hardly deeper than a window",
        "The gain (measured / true) of a uniform depth displacement of 0.5-2 voxels at 0.05 "
        "and 0.1 particles per microlens through the default chain on the 850 x 850 px "
        "camera, in a volume 4 mm deep (one window in depth, its centre in the focal zone's "
        "blind band) and in one 8 mm deep, beside the correlation alone on the same images "
        "(the baseline), and whether the chain warned that no window sees depth.",
        ("benchmarks/shallow.py",), 4.0),
    Entry(
        "weights", "Accuracy",
        "How true the weighting function is to the camera's images",
        "The paper's validation of its weights (its Fig. 8), by depth through the focal "
        "plane: a voxel of the paper's synthetic case (850 x 850 px behind 50 x 50 lenses, "
        "0.125 mm, one lens wide) at four places against the lenses, its column of the "
        "weight matrix against the raw image of 64 particles spread through it, ray traced "
        "sharp and with a 1 px blur: their correlation, the share of the weight on pixels "
        "the particles leave dark (what the paper's MART multiplies towards zero), and the "
        "pixels each lights. The paper's weights at the default aperture sampling are the "
        "baseline; beside them the voxel integrated over 3 x 3 sub-voxels, the aperture "
        "sampled four times as finely, and each sub-voxel alone against its own particles "
        "(the default reconstruction's grid).",
        ("benchmarks/weights.py",), 2.0),
    Entry(
        "lens-weights", "Accuracy",
        "Lens weights that integrate the voxel's extent",
        "The error budget's scenes (the paper's optics and voxel on 96 x 64 lenses, 0.05 "
        "particles per microlens, ray traced with 0.8 px blur, photon and read noise), two "
        "scenes per motion, through `plenocl.process_pair`'s defaults with the paper's "
        "bilinear lens weights (the baseline) and with `Projector(lens_weights=\"extent\")` "
        "on the same images: lateral and depth RMS error of the valid vectors, depth in the "
        "focal zone, particles recovered, ghost intensity, seconds per pair.",
        ("benchmarks/lens_weights.py",), 3.0),
    Entry(
        "lens-weights-full", "Accuracy",
        "Lens weights that integrate the voxel's extent, on the whole sensor",
        "The same comparison as the entry above on the paper's whole 16 MP sensor (289 x "
        "193 lenses, 300 x 200 x 150 voxels: the size users record), one scene per motion: "
        "the paper's bilinear lens weights (the baseline) and the extent weights on the "
        "same images in the same run.",
        ("benchmarks/lens_weights.py", "--lenses", "289", "193", "--scenes", "1"), 6.0),
    Entry(
        "cubic-recovery", "Accuracy",
        "Particle recovery on the paper's cube at cubic voxels",
        "The paper's synthetic camera (850 x 850 px behind 50 x 50 lenses) and its 5 mm cube "
        "at 40³ cubic voxels, 20 and 60 particles ray traced with a 1 px blur, 12 unseen "
        "scenes each: particles recovered (mean and worst scene), ghost intensity, Q and "
        "seconds per reconstruction, for `reconstruct()`'s default (coarse-to-fine on 3 x 3 "
        "sub-voxels) against the reconstruction on the voxels themselves (the baseline) and "
        "other schedules, each with the weights that integrate the voxel's extent (the "
        "default) and with the paper's lens weights; then where each one's misses lie: "
        "close pairs, the focal zone, the rest.",
        ("benchmarks/cubic_recovery.py", "--scenes", "12", "--lens-weights", "paper",
         "extent"), 3.5),
    Entry(
        "focal-zone", "Accuracy",
        "What one camera's images allow near the focal plane",
        "Why the cube's focal zone resists (issue 47). Near the focal plane a particle's "
        "image holds only where each lens edge its defocus disc crosses cuts the aperture, "
        "so moving it along the line through that edge at the focal plane (its distance to "
        "the edge and its depth scaled alike) leaves the image unchanged: ray-traced "
        "particles against themselves moved along their lines and by the same depths alone, "
        "beside the ray noise (the baseline). Then the cube's scenes of the entry above: "
        "each focal-zone particle's class (its disc in one lens cell, across one edge, "
        "across a corner), the share an estimator that knew each line could place within "
        "the 2-voxel match, the share the default recovers, and where its misses went.",
        ("benchmarks/focal_zone.py",), 1.0),
    Entry(
        "paper-mart", "Accuracy",
        "The paper's MART on the camera's images",
        "The paper's method, MART at its parameters (15 iterations, relaxation 0.7, no ratio "
        "floor), on the paper's synthetic case (850 x 850 px behind 50 x 50 lenses, its 5 mm "
        "cube on 40 x 40 x 20 voxels), 20 and 60 particles ray traced with a 1 px blur, and "
        "again with photon noise, a dark level and read noise, 6 unseen scenes each: with "
        "the paper's weights on its voxels and the image as it is (the baseline); with lens "
        "weights that integrate each 3 x 3 sub-voxel's extent, on the image as it is and "
        "with MART's default smoothing of the image (a 1 px Gaussian, `smooth_px`), from "
        "the sub-voxels' start, and within the support of the coarse MLEM run (what "
        "`reconstruct(method=\"mart\")` does); `reconstruct()`'s default beside them, with "
        "the paper's weights and on the smoothed image. Particles recovered (mean and "
        "worst scene), ghost intensity, Q and seconds per reconstruction.",
        ("benchmarks/paper_mart.py",), 4.0),
    Entry(
        "paper-pair", "Performance",
        "One pair at the paper's full size",
        "One image pair through `plenocl.process_pair` at the paper's size: the whole "
        "16 MP sensor (289 x 193 microlenses) and 300 x 200 x 150 voxels, 0.05 particles per "
        "microlens, uniform displacement. Per reconstruction setting, on the same two raw "
        "images in the same run: the seconds of each stage (both reconstructions, PIV, the "
        "particle refinement with its fit to the raw images), the lateral and depth RMS "
        "error of the valid vectors and the particles recovered. The default "
        "(coarse-to-fine MLEM with coarser aperture sampling in the coarse and early "
        "iterations, the extent lens weights) runs beside two baselines: the same with the "
        "paper's lens weights (`paperweights`, the default before the extent weights), and "
        "the same iterations all on the projector's full aperture sampling "
        "(`fullaperture`). The projectors and their sensitivities are built once before "
        "the rows, as a batch worker does, and timed apart.",
        ("benchmarks/paper_pair.py", "--settings", "default", "paperweights", "fullaperture"),
        3.5),
    Entry(
        "projector", "Performance",
        "Projector throughput and roofline",
        "Matrix-free forward and back projection, device-resident, medians of repeats. "
        "Small cubic grids on the 850 x 850 px camera against `scipy.sparse` CSR products "
        "of the same weights (the fixed cost per call); the paper's experiment (16 MP, "
        "300 x 200 x 150 voxels) in weights per second against the most a stored matrix "
        "could stream at this device's measured copy bandwidth (8 bytes per weight); the "
        "array rotated 0.15° on a sensor-axis grid, on a lens-row grid and with calibrated "
        "centres, against the axis-aligned array and against the general kernels that "
        "projected rotated arrays before. The stored-matrix comparison at 122 M weights, the "
        "rotated array's reconstructions and the scratch-size comparison are left out here "
        "(`benchmarks/projector.py` without `--skip-*` runs them).",
        ("benchmarks/projector.py", "--skip-stored", "--skip-reconstruction",
         "--skip-scratch", "--repeats", "3"), 3.0),
    Entry(
        "real-array", "Performance",
        "A real calibrated microlens array",
        "The lattice `plenocl calibrate` found on cicwi/plenoptomos' white image (27 x 20 "
        "lenses, the columns slightly off square to the rows) with the grid `plenocl grid` "
        "writes for it: forward + back projection on the projector's fast path against the "
        "ideal lattice (the baseline) and against the general kernels every calibrated "
        "array took before, medians of repeats; then its images and a short MLEM "
        "reconstruction against the general path's, on the same weighting model.",
        ("benchmarks/real_array.py",), 0.5),
    Entry(
        "posed", "Performance",
        "A world grid through a posed camera",
        "The paper's optics on 116 x 78 lenses and its grid: the camera unposed (the "
        "baseline) and turned 12.5 and 25 degrees about y, the world grid projected through "
        "its own frame (a separable projector on a frame grid and a trilinear resampling): "
        "forward + back projection on the voxels and on 3 x 3 sub-voxels (medians), a "
        "default reconstruction's seconds and the particles it recovers, and "
        "`process_pair`'s vectors in the world grid's voxels, on the same world particles.",
        ("benchmarks/posed.py", "--pair"), 2.5),
    Entry(
        "refocus", "Performance",
        "Refocusing at 16 MP",
        "A focal stack of 9 planes from one simulated raw image of the paper's camera by "
        "the OpenCL kernel (quadratic B-spline weights), against SciPy's shift-and-add "
        "(`scipy.ndimage.map_coordinates`, the same weights, one call per view) and the "
        "NumPy reference, on the same light field in the same run: median seconds, planes "
        "per second and taps per second; the light field's resampling timed apart.",
        ("benchmarks/refocus.py", "--camera", "paper", "--repeats", "3"), 1.5),
    Entry(
        "piv", "Performance",
        "3-D PIV on synthetic volumes",
        "`piv3d` with its defaults on synthetic volume pairs (Gaussian particles of 1 "
        "voxel) with known displacement fields, 96³ voxels, one repeat: RMS vector error "
        "over the interior and seconds per vector, against openpiv-python's 3-D PIV on the "
        "same volumes where it is installed (the `bench` extra); the deformation on the "
        "OpenCL device against SciPy's on the host, the direct correlation's window sums on "
        "the device against the host's, peak locking, and the deformation's interpolation "
        "orders.",
        ("benchmarks/piv.py", "--quick"), 1.5),
    Entry(
        "host-work", "Performance",
        "Host work moved to the device",
        "Data of the paper's size (a 150 x 200 x 286 voxel particle volume, a 16 MP image): "
        "the deformation's cubic B-spline prefilter on the device against SciPy's, the "
        "particles' tube sums along their lines of sight on the device against SciPy's "
        "`map_coordinates`, the image's median and noise by a bracketed selection against "
        "NumPy's medians, the support's dilation by separable maxima against SciPy's "
        "`binary_dilation`, and the lit microlenses by row counts against a summed-area "
        "table: each against the code it replaced on the same data in the same "
        "process, medians of repeats and the largest difference of the results.",
        ("benchmarks/host_work.py",), 0.5),
    Entry(
        "drivers", "Performance",
        "CPU OpenCL drivers side by side",
        "Every CPU OpenCL driver the loader lists (PoCL, Intel's CPU runtime, a system "
        "PoCL), in plenocl's default order, in one process: forward + back projection and "
        "5 MLEM iterations at the paper's size (medians of repeats, each driver's volume "
        "against the first driver's), and the small boundary-layer demo end to end with its "
        "velocity error. The drivers are each other's baseline.",
        ("benchmarks/drivers.py",), 1.5),
    Entry(
        "tracking", "Tracking",
        "Particles tracked through time",
        "The paper's optics on 96 x 64 lenses, 8 ray-traced frames at 0.05 particles per "
        "microlens (0.8 px blur, photon and read noise), a uniform motion and a rotation "
        "about the lateral x axis. `plenocl.track` on each series: per-step displacement "
        "errors (voxels, lateral and depth, the focal zone apart) of the tracks seen in 4 "
        "or more frames, the share of particles tracked, ghost tracks and seconds per "
        "frame. Baselines from the same frames: the measured positions smoothed without the "
        "neighbours' depth prior and by local lines, each frame's fit alone, and the pair "
        "chain (`plenocl.process_pair`) on the first pairs; and the tracks binned into the "
        "pair chain's windows (`plenocl.bin_tracks`).",
        ("benchmarks/tracking.py",), 1.5),
    Entry(
        "pose-calibration", "Calibration",
        "Cameras' poses from a dot target and from the particles",
        "The paper's optics on 40 x 30 lenses, ray-traced images with 0.8 px blur, photon "
        "and read noise. A camera's pose from three plates of 4 x 4 dots at known world "
        "positions, from a guess 0.65 degree and 0.2 mm off (`plenocl.calibrate_pose`): "
        "its errors against the true pose. Two cameras 25 degrees apart, the second's "
        "pose wrong, refined from five exposures of their particle images "
        "(`plenocl.self_calibrate`): per round each camera's systematic disparity (the "
        "RMS of its sensor quadrants' mean disparity vectors) and single-particle "
        "disparity, beside the true poses' on the same particles (the baseline: the "
        "fits' noise).",
        ("benchmarks/pose_calibration.py",), 1.0),
    Entry(
        "calibration", "Calibration",
        "Microlens centres from white images",
        "Centre RMS error (px) against the simulator's truth on white images of the "
        "850 x 850 px camera: clean, noisy, rotated and shifted, vignetted with lenses "
        "missing, saturated, lenses off the lattice, dark-subtracted, hexagonal arrays, and "
        "720 px images at other projects' scales. The paper's plain box centroid (the "
        "baseline), plenocl's windowed centroid, the grid model and the default (the two "
        "combined by their uncertainties), from the same detection in the same run, with "
        "each calibration's time. Then full-aperture images with every lens off its node "
        "(jitter and a radial distortion): the lattice alone against the per-lens default; "
        "and a hexagonal array whose odd rows sit off the camera file's shift. Medians over "
        "two images per case.",
        ("benchmarks/calibration.py", "--seeds", "2"), 6.0),
    Entry(
        "agreement", "Agreement",
        "Agreement across devices",
        "The same small workloads (forward and back projection, refocusing, simulated "
        "images, MLEM volumes) on every OpenCL device this machine shows that builds "
        "plenocl's kernels, each compared with the results of the first in plenocl's "
        "preference order (the default device) against stated tolerances "
        "(`plenocl.bench.agreement`); it exits non-zero beyond them. With a single device "
        "there is nothing to compare; `POCL_DEVICES=\"pthread basic\"` adds PoCL's serial "
        "driver to its threaded one.",
        ("-m", "plenocl", "devices", "--agree"), 1.0),
)
