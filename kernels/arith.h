/* Plain-arithmetic helpers shared by the kernels (kernels/common.h, kernels/projector.h,
 * kernels/raybundle.cl). PoCL's CPU driver (3.0, distro build) calls its builtins
 * (floor, fabs, ...) out of line, spilling vector registers at each call, so hot code
 * uses these instead; each returns what the builtin would. */
#ifndef PLENOCL_ARITH_H
#define PLENOCL_ARITH_H

inline float pl_abs(float x) { return x < 0.0f ? -x : x; }
inline int pl_mini(int a, int b) { return a < b ? a : b; }
inline int pl_maxi(int a, int b) { return a > b ? a : b; }

/* floor and ceil as integers, for |x| < 2^31 */
inline int pl_floori(float x)
{
    const int i = (int)x;
    return (float)i > x ? i - 1 : i;
}

inline int pl_ceili(float x)
{
    const int i = (int)x;
    return (float)i < x ? i + 1 : i;
}

/* Float atomic add by a compare-and-swap loop (scatters without 64-bit atomics). */
inline void pl_atomic_addf(volatile __global float *p, float q)
{
    volatile __global uint *u = (volatile __global uint *)p;
    uint old = *u, assumed;
    do {
        assumed = old;
        old = atomic_cmpxchg(u, assumed, as_uint(as_float(assumed) + q));
    } while (old != assumed);
}

#endif /* PLENOCL_ARITH_H */
