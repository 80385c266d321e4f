/* The device probe: built with the projector's own headers and run once on every candidate
 * device before clgs uses it (clgs/runtime/devices.py), so a driver that cannot compile the
 * project's kernels (an unknown CPU, a missing builtin, a wrong vector width) is rejected with its
 * reason instead of failing later inside a reconstruction. */
#include "project_setup.h"

__kernel void probe(__global const float *t, __global float *out)
{
    const int g = get_global_id(0);
    /* the splat's own 2^t on 16 lanes (the x86 instruction path where the compiler offers it) */
    const float16 v = vload16(g, t);
    const float16 e = splat_exp2_16(v);
    const real8 r = sqrt8(e.lo * e.lo);
    vstore16((float16)(r, e.hi), g, out);
}
