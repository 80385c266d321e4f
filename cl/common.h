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

#endif
