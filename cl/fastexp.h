/* exp(x) for x <= 0 without a builtin call, for the exp-bound inner loops (see kernels).
 *
 * 2^t with t = x log2(e): t = n + f with n an integer (by truncation, exact for t <= 0) and
 * f in (-0.5, 0.5]; 2^f by its degree-6 Taylor polynomial (relative error below 2e-7), and 2^n
 * added straight into the float's exponent bits. Inputs below -87 give 0; inputs above 0 are
 * treated as 0 (Gaussians never produce them). Double builds use the builtin exp. */
#ifndef CLGS_FASTEXP_H
#define CLGS_FASTEXP_H
#include "common.h"

#ifdef REAL_DOUBLE
#define fast_exp8(x) exp(x)
#define fast_exp16(x) exp(x)
#define fast_exp(x) exp(x)
#else

#define FE_C1 0.69314718055994531f
#define FE_C2 0.24022650695910071f
#define FE_C3 0.055504108664821580f
#define FE_C4 0.0096181291076284772f
#define FE_C5 0.0013333558146428443f
#define FE_C6 0.00015403530393381609f

/* fast_exp<W> for a vector width W (8 and 16 are made below); splat_exp2<W> (project_setup.h)
 * is the same 2^t without the clamps, for arguments the callers keep in range. */
#define CLGS_DEFINE_FAST_EXP(W)                                                                   \
    inline float##W fast_exp##W(float##W x)                                                       \
    {                                                                                             \
        float##W t = x * 1.4426950408889634f;                                                     \
        t = (t > 0.0f) ? (float##W)(0.0f) : t;                                                    \
        const int##W under = t < -125.0f;                                                         \
        t = under ? (float##W)(-125.0f) : t;                                                      \
        const int##W n = convert_int##W(t - 0.5f); /* truncation: ceil for negatives */          \
        const float##W f = t - convert_float##W(n); /* in (-0.5, 0.5] */                         \
        float##W p = FE_C6;                                                                       \
        p = p * f + FE_C5;                                                                        \
        p = p * f + FE_C4;                                                                        \
        p = p * f + FE_C3;                                                                        \
        p = p * f + FE_C2;                                                                        \
        p = p * f + FE_C1;                                                                        \
        p = p * f + 1.0f;                                                                         \
        const float##W r = as_float##W(as_int##W(p) + (n << 23));                                 \
        return under ? (float##W)(0.0f) : r;                                                      \
    }
CLGS_DEFINE_FAST_EXP(8)
CLGS_DEFINE_FAST_EXP(16)

inline float fast_exp(float x)
{
    float t = x * 1.4426950408889634f;
    t = (t > 0.0f) ? 0.0f : t;
    if (t < -125.0f) return 0.0f;
    int n = convert_int(t - 0.5f);
    float f = t - (float)n;
    float p = FE_C6;
    p = p * f + FE_C5;
    p = p * f + FE_C4;
    p = p * f + FE_C3;
    p = p * f + FE_C2;
    p = p * f + FE_C1;
    p = p * f + 1.0f;
    return as_float(as_int(p) + (n << 23));
}
#endif
#endif
