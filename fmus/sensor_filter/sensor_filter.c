/* sensor_filter: x follows u through a first-order low-pass (exact discretization of
 * x' = 2 pi fc (u - x)); y = x + sigma * n, n standard normal from a splitmix64 generator seeded
 * by `seed` and kept in the model data (so it is saved, restored and serialized with the state). */
#include <math.h>

#include "fmu_model.h"

static uint64_t next(uint64_t *s) {
    uint64_t z = (*s += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static double uniform(uint64_t *s) { return ((next(s) >> 11) + 0.5) * 0x1.0p-53; } /* in (0, 1) */

static double normal(uint64_t *s) { /* Box-Muller, one value per call */
    double u1 = uniform(s), u2 = uniform(s);
    return sqrt(-2.0 * log(u1)) * cos(6.283185307179586 * u2);
}

static void outputs(ModelData *m) {
    for (int i = 0; i < N; ++i) m->y[i] = m->x[i] + (m->sigma > 0.0 ? m->sigma * normal(&m->rng) : 0.0);
}

int model_init(ModelData *m) {
    if (!(m->cutoff >= 0.0) || !(m->sigma >= 0.0)) {
        fmu_log(m, MODEL_ERROR, "cutoff (%g) and sigma (%g) must be >= 0", m->cutoff, m->sigma);
        return MODEL_ERROR;
    }
    m->rng = (uint64_t)(uint32_t)m->seed * 0x2545F4914F6CDD1Dull + 1u;
    for (int i = 0; i < N; ++i) m->x[i] = m->u[i];
    outputs(m);
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    double a = m->cutoff > 0.0 ? 1.0 - exp(-6.283185307179586 * m->cutoff * h) : 1.0;
    for (int i = 0; i < N; ++i) m->x[i] += a * (m->u[i] - m->x[i]);
    outputs(m);
    return MODEL_OK;
}
