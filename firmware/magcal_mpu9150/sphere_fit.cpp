#include "sphere_fit.h"

#include <math.h>
#include <string.h>

void sphere_begin(SphereSums *s, const float *ref)
{
    memset(s, 0, sizeof *s);
    if (ref) {
        s->ref[0] = ref[0];
        s->ref[1] = ref[1];
        s->ref[2] = ref[2];
    }
}

void sphere_add(SphereSums *s, float x, float y, float z)
{
    x -= s->ref[0];
    y -= s->ref[1];
    z -= s->ref[2];
    float r = x * x + y * y + z * z;
    s->n += 1.0f;
    s->s[0] += x;
    s->s[1] += y;
    s->s[2] += z;
    s->ss[0] += x * x;
    s->ss[1] += y * y;
    s->ss[2] += z * z;
    s->ss[3] += x * y;
    s->ss[4] += x * z;
    s->ss[5] += y * z;
    s->sr += r;
    s->sr_p[0] += r * x;
    s->sr_p[1] += r * y;
    s->sr_p[2] += r * z;
}

int8_t sphere_solve(const SphereSums *s, float centre[3], float *radius, int32_t *pivot_milli)
{
    // augmented 4x5 system [M | v]
    float a[4][5] = {
        {s->ss[0], s->ss[3], s->ss[4], s->s[0], s->sr_p[0]},
        {s->ss[3], s->ss[1], s->ss[5], s->s[1], s->sr_p[1]},
        {s->ss[4], s->ss[5], s->ss[2], s->s[2], s->sr_p[2]},
        {s->s[0], s->s[1], s->s[2], s->n, s->sr},
    };
    // Equilibrate (divide row and column i by sqrt(M_ii)) so that the pivot ratio reported as
    // `cond` measures how well the samples pin the sphere down, not the units of the sums.
    float d[4];
    for (uint8_t i = 0; i < 4; i++) {
        if (!(a[i][i] > 0.0f))
            return -1;
        d[i] = 1.0f / sqrtf(a[i][i]);
    }
    for (uint8_t i = 0; i < 4; i++) {
        for (uint8_t k = 0; k < 4; k++)
            a[i][k] *= d[i] * d[k];
        a[i][4] *= d[i];
    }
    float pmin = 0.0f, pmax = 0.0f;
    for (uint8_t col = 0; col < 4; col++) {
        uint8_t best = col;
        for (uint8_t row = col + 1; row < 4; row++)
            if (fabsf(a[row][col]) > fabsf(a[best][col]))
                best = row;
        if (best != col)
            for (uint8_t k = 0; k < 5; k++) {
                float t = a[col][k];
                a[col][k] = a[best][k];
                a[best][k] = t;
            }
        float p = fabsf(a[col][col]);
        if (!(p > 0.0f))
            return -1;
        if (col == 0 || p < pmin) pmin = p;
        if (col == 0 || p > pmax) pmax = p;
        for (uint8_t row = col + 1; row < 4; row++) {
            float f = a[row][col] / a[col][col];
            for (uint8_t k = col; k < 5; k++)
                a[row][k] -= f * a[col][k];
        }
    }
    float q[4];
    for (int8_t row = 3; row >= 0; row--) {
        float acc = a[row][4];
        for (uint8_t k = row + 1; k < 4; k++)
            acc -= a[row][k] * q[k];
        q[row] = acc / a[row][row];
    }
    for (uint8_t i = 0; i < 4; i++)
        q[i] *= d[i];
    float c2 = 0.0f;
    for (uint8_t i = 0; i < 3; i++) {
        float c = 0.5f * q[i];
        c2 += c * c;
        centre[i] = c + s->ref[i];
    }
    float r2 = q[3] + c2;
    if (!(r2 > 0.0f))
        return -1;
    *radius = sqrtf(r2);
    *pivot_milli = (int32_t)(1000.0f * pmin / pmax + 0.5f);
    return 0;
}
