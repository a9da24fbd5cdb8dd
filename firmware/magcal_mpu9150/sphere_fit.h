// Least-squares sphere fit from running sums, in float32 (the AVR's only float).
//
// A sample p lies on a sphere of centre c and radius R when |p|^2 = 2 c.p + (R^2 - |c|^2), which
// is linear in q = (2c, R^2 - |c|^2). Least squares over all samples gives the 4x4 normal
// equations M q = v with M = sum [p 1]^T [p 1] and v = sum |p|^2 [p 1]. The sums are all the
// board keeps, so memory does not grow with the number of samples.
//
// Precision: with a hard-iron offset of a few hundred uT the naive sums (p as measured) are
// dominated by the offset and float32 cancels most of the information away; subtracting a
// reference sample first (centred sums) keeps the numbers at the size of the field itself.
#ifndef MAGCAL_SPHERE_FIT_H
#define MAGCAL_SPHERE_FIT_H

#include <stdint.h>

struct SphereSums {
    float ref[3];      // subtracted from every sample (all 0 for the naive sums)
    float n;
    float s[3];        // sum p
    float ss[6];       // sum xx, yy, zz, xy, xz, yz
    float sr;          // sum |p|^2
    float sr_p[3];     // sum |p|^2 p
};

// Start a fit; ref is the reference subtracted from every sample, or 0 for none (naive).
void sphere_begin(SphereSums *s, const float *ref);
void sphere_add(SphereSums *s, float x, float y, float z);
// Solve; returns 0 and fills centre/radius (same unit as the samples) and the pivot ratio
// (smallest / largest pivot magnitude of the equilibrated system, times 1000: near 0 when the
// samples hardly constrain the sphere or the sums are dominated by an offset), or -1 when the
// system is singular.
int8_t sphere_solve(const SphereSums *s, float centre[3], float *radius, int32_t *pivot_milli);

#endif
