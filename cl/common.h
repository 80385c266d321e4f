/* Shared definitions for every clgs kernel.
 * REAL is float by default; tests build with -DREAL=double to check gradients. */
#ifndef CLGS_COMMON_H
#define CLGS_COMMON_H

#ifndef REAL
#define REAL float
#endif

/* -DREAL=double also needs the extension; REAL_DOUBLE is set by the host for that build. */
#ifdef REAL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

typedef REAL real;
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
typedef CAT(REAL, 2) real2;
typedef CAT(REAL, 3) real3;
typedef CAT(REAL, 4) real4;
typedef CAT(REAL, 8) real8;
typedef CAT(REAL, 16) real16;

/* A literal in the kernels' precision. */
#define RC(x) ((real)(x))

/* Precision-dependent names: the integer vectors that comparing reals gives (masks), the
 * conversion to real8, and the machine epsilon. */
#ifdef REAL_DOUBLE
typedef long mask1;
typedef long8 mask8;
typedef long16 mask16;
#define convert_mask8 convert_long8 /* an int8 comparison result as the mask of a real8 select */
#define convert_real8 convert_double8
#define REAL_EPS DBL_EPSILON
#else
typedef int mask1;
typedef int8 mask8;
typedef int16 mask16;
#define convert_mask8(x) (x)
#define convert_real8 convert_float8
#define REAL_EPS FLT_EPSILON
#endif

/* real8 / real16 at any real-aligned address as a plain vector access: PoCL's vload8 / vstore8
 * are library calls, and a call in a loop makes the compiler spill every live vector around it */
typedef real8 real8u __attribute__((aligned(sizeof(real))));
typedef real16 real16u __attribute__((aligned(sizeof(real))));
#define LD8G(p) (*(__global const real8u *)(p))
#define ST8G(p) (*(__global real8u *)(p))
#define LD16G(p) (*(__global const real16u *)(p))
#define ST16G(p) (*(__global real16u *)(p))

/* Eight reals of ptr at base + the eight lanes of the int8 idx. */
#define GATHER8(ptr, base, idx) \
    (real8)((ptr)[(base) + (idx).s0], (ptr)[(base) + (idx).s1], (ptr)[(base) + (idx).s2], \
            (ptr)[(base) + (idx).s3], (ptr)[(base) + (idx).s4], (ptr)[(base) + (idx).s5], \
            (ptr)[(base) + (idx).s6], (ptr)[(base) + (idx).s7])

#endif
