/* The three-point Gaussian peak offset in [-0.5, 0.5], parabolic where a value is <= 0 or
 * the log-curvature is not negative (plenocl.peaks.gaussian_subpixel), in PL_SUBPIXEL_REAL:
 * float unless the including file defines it (kernels/fftcorr.cl float, kernels/windowfit.cl
 * its PL_REAL, double where the device has it). */
#ifndef PLENOCL_SUBPIXEL_H
#define PLENOCL_SUBPIXEL_H

#ifndef PL_SUBPIXEL_REAL
#define PL_SUBPIXEL_REAL float
#endif

inline PL_SUBPIXEL_REAL pl_subpixel(PL_SUBPIXEL_REAL cm, PL_SUBPIXEL_REAL c0,
                                    PL_SUBPIXEL_REAL cp)
{
    PL_SUBPIXEL_REAL off = 0;
    const PL_SUBPIXEL_REAL dg = 2 * (log(cm) - 2 * log(c0) + log(cp));
    const PL_SUBPIXEL_REAL dp = 2 * (cm - 2 * c0 + cp);
    if (cm > 0 && c0 > 0 && cp > 0 && dg < 0)
        off = (log(cm) - log(cp)) / dg;
    else if (dp < 0)
        off = (cm - cp) / dp;
    return clamp(off, (PL_SUBPIXEL_REAL)-0.5, (PL_SUBPIXEL_REAL)0.5);
}

#endif
