"""Tolerances of the kernel tests, named once per quantity (``import tolerances as tol``).

plenocl's kernels compute in float32 (unit roundoff 2^-24 ≈ 6e-8); the NumPy twins in
``plenocl.reference`` compute the same quantities in float64. Each name below is one
quantity compared one way; its comment says why the value fits float32 there. A value is
what the tests asserted before it was named: none was loosened. Where two tests compare
the same quantity with different values, both names stay (the stricter test is not made
looser, the looser one was not checked against the stricter value). ``RTOL`` names go to
``rtol``/``rel``, ``FLOOR`` names are ``atol`` as a fraction of the compared array's peak
(or absolute where the data are of order 1, as the comment says). The cross-device
tolerances of ``plenocl devices --agree`` are a separate table
(``plenocl.bench.agreement.TOLERANCES``): two devices, not a kernel and its twin.
"""

from __future__ import annotations

# --- projector: weights, forward and back projection -------------------------------------

#: One voxel's weights (and its one-hot forward projection) against the float64 weights:
#: ``max |kernel - reference| <= WEIGHTS * peak``. Each weight is a handful of float32
#: products of coordinates of order 1, with a few-ulp error near 1e-7; 1e-5 of the peak
#: leaves room for the ~100 aperture samples summed into one pixel. Also a whole forward
#: projection against ``A x`` from the dense matrix, and the atomic-scatter back
#: projection against the gather (the same sums in another order).
WEIGHTS = 1e-5

#: The total of one voxel's footprint, kernel against reference (``rel``): ~10^3 float32
#: weights summed, each off by up to 1e-5 of the peak in the same direction at worst.
FOOTPRINT_TOTAL = 1e-4

#: Adjointness ``|<A x, y> - <x, Aᵀ y>| <= ADJOINT * <A |x|, |y|>``: two float32 operators
#: accumulating in different orders over ~10^4-10^6 terms, compared in float64.
ADJOINT = 1e-4

#: The back projection against ``Aᵀ y`` from the float64 dense matrix (``rtol``), with
#: :data:`BACK_VS_MATRIX_FLOOR` of the peak as ``atol`` for the small entries: a pixel's
#: ~10^2 float32 contributions, each rounded once, accumulate to a few 1e-6.
BACK_VS_MATRIX = 2e-5
BACK_VS_MATRIX_FLOOR = 1e-6

#: Light conservation in float32 (``rtol``/``rel``, or ``abs`` for sums of order 1): a
#: voxel's weights sum to 1 (at most ``1 + CONSERVATION``), the sensitivity's total equals
#: the projection of ones, a simulated image's total equals its particles' intensity,
#: binning keeps the total. Sums of ~10^2-10^4 float32 terms of one sign: the rounding
#: grows as n * 2^-24 in the worst case, 1e-5 in practice.
CONSERVATION = 1e-5

#: The same quantity computed another way, where only the float32 summation order
#: differs: slab splits, scalar and direct kernel variants, skipped empty slices, a
#: cropped sub-projector's own back projection, the command line's refocus run again
#: (``rtol``); with :data:`RECOMPUTED_FLOOR` as ``atol`` (absolute for data of order 1,
#: else of the peak): values near zero have no relative precision.
RECOMPUTED = 1e-5
RECOMPUTED_FLOOR = 1e-6

#: Results that differ by no more than the rounding of a few float32 operations: the same
#: kernel on the device and through the host, a focal-stack plane and the single refocus
#: of that plane, masked slices, binning after spreading (``rtol``); a few ulps of 2^-24.
ROUNDING = 1e-6

# --- light field: refocusing -------------------------------------------------------------

#: The shift-and-add kernel against ``refocus_views`` (float64), on awkward sizes with
#: NaN views (``rtol``), and :data:`REFOCUS_FLOOR` absolute for views of order 10: a
#: B-spline weighted mean of ~50 views, each weight a float32 polynomial in the shift.
REFOCUS = 2e-5
REFOCUS_FLOOR = 1e-5

#: Refocusing at alpha = 1 against the mean over the aperture smoothed by the B-spline's
#: zero-offset taps (``rtol``): no shift, so only the mean's float32 sum rounds. Stricter
#: than :data:`REFOCUS`; kept apart.
REFOCUS_UNSHIFTED = 1e-5

# --- reconstruction: MLEM, SMART, MART --------------------------------------------------

#: A solver's volume against the float64 NumPy solver after 5-12 iterations (``rtol``),
#: :data:`SOLVER_FLOOR` of the peak as ``atol``: each iteration multiplies by float32
#: ratios of projections; relative errors of ~1e-5 per iteration compound, and voxels
#: MLEM drives towards 0 keep only an absolute precision.
SOLVER = 2e-3
SOLVER_FLOOR = 1e-5

#: Ten plus ten iterations against twenty (``rtol``; :data:`RESUMED_FLOOR` of the peak):
#: the start volume is rounded to float32 between the two runs and MLEM's fixed point
#: iteration amplifies that over ten more iterations.
RESUMED = 1e-3
RESUMED_FLOOR = 1e-4

#: A reconstruction on its cropped (illuminated) box against the full grid, or with the
#: image scaled by 1e±6 (``rtol``): the same iterations with sums in another order over
#: 14-15 iterations. Floors (of the peak) differ per test and stay where they are.
ITERATED = 1e-4

#: The device's lateral binning (``kernels/supersample.cl``) against ``bin_lateral`` of
#: the scaled volume (``rtol``): at most 16 scaled float32 terms of one sign per voxel.
#: The kernel adds them in the order NumPy 2.x does (bit for bit then), but that order is
#: NumPy's choice; in another order the sum moves by at most ~15 x 2^-24 relative.
BINNED = 1e-6

# --- simulation ------------------------------------------------------------------------

#: The ray-tracing kernel against the NumPy tracer, ray for ray (``rel`` of the image
#: totals): the same rays in float32, each deposit rounded once; landing totals agree
#: to a few ulps.
SIMULATED_TOTAL = 1e-6

#: The same trace split into many small launches (``atol``, counts of order 100): float
#: atomic adds into a pixel in another order.
SIMULATED_SPLIT = 1e-4

# --- PIV ------------------------------------------------------------------------------

#: A float32 PIV kernel against its twin, ``atol`` of the peak (1 for Pearson
#: coefficients): the direct correlation against ``correlate_windows``, the device
#: deformer against the host's, FFTW against SciPy's FFT. Sums of ~10^3-10^4 products
#: normalised by float32 norms.
PIV_TWIN = 2e-5

#: The device's mixed-radix FFT (``kernels/fftcorr.cl``) against NumPy's float64 FFT,
#: ``atol`` of the spectrum's peak: log2(n) float32 butterfly passes per axis, each
#: rounding once; measured 1-4e-7.
FFT_LINES = 1e-6

#: A normalised correlation plane's value through the device's FFT correlation against
#: the host's or the float64 twin's (``atol``; ``rtol`` for the peak ratio): a 3-D float32
#: FFT over 10^3-10^5 values and back, normalised by float32 energies; measured up to
#: 3e-5.
FFT_PLANE = 1e-4

#: The uncertainty's correlated-sum factor on the device against the host's (``rtol``):
#: box means by float32 running sums (double where the device has it), lagged products
#: of ~10^4-10^6 float32 terms summed per row; measured up to 8e-7.
CORRELATED_FACTOR = 1e-5

#: A Pearson coefficient's bound, and its value for a window against itself
#: (``|r| <= 1 + PEARSON``): the float32 normalisation rounds either way.
PEARSON = 1e-5

#: Displacements, in voxels, that go through a float32 device path and a float64 host
#: path (``atol``): device PIV against host PIV, through window deformation and peak fits.
DISPLACEMENT = 1e-4

#: A uniform PIV field interpolated to every voxel (``atol``, displacements of order 1):
#: float32 interpolation weights that sum to 1 within a few ulps.
UNIFORM_FIELD = 1e-5

# --- image fit: ray bundles ---------------------------------------------------------------

#: The ray-bundle kernel's patch rows (value and derivatives) against the float64 NumPy
#: renderer, ``atol`` as a fraction of each row's peak. Lattice coordinates (up to ~10^2
#: lens indices) and sensor positions (~10^3 px) are float32, so a ray lands a few 1e-5
#: lattice units and ~1e-4 px off; a ray on a pixel edge may take the neighbouring 5 x 5
#: window (a ~1e-3 change of 1/200 of the light). Measured up to 2.4e-4 (PoCL).
RAYBUNDLE = 5e-4

#: The image fit's positions rendered on the device against NumPy (voxels, ``abs``): the
#: float32 rows perturb each Gauss-Newton step by ~1e-5 of itself; small against the fit's
#: accuracy (0.04 voxel laterally, 0.4-0.6 in depth).
IMAGEFIT_POSITION_VOXELS = 1e-3
